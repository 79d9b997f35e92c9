import os

# The unit tests are the CPU's contract (CI and the README's install have no GPU), and their
# bitwise and exact-equality checks hold on the CPU: on a machine with a GPU they still run on
# the CPU. The GPU path is checked by benchmarks/gpu_check.py; COURSE_TEST_GPU=1 keeps the GPU
# visible to the tests. (Set before torch can initialise CUDA; subprocesses inherit it.)
if os.environ.get("COURSE_TEST_GPU") != "1":
    os.environ["CUDA_VISIBLE_DEVICES"] = ""

import pytest
import torch

from course_utils import models


@pytest.fixture(scope="session")
def tokenizer():
    return models.load_tokenizer(models.TINY)


@pytest.fixture(scope="session")
def tiny_model(tokenizer):
    model = models.tiny_qwen2(len(tokenizer), seed=0)
    model.generation_config.eos_token_id = tokenizer.eos_token_id
    return model.eval()


@pytest.fixture
def gen():
    return torch.Generator().manual_seed(0)


@pytest.fixture
def resume_pair(tmp_path):
    """Train the smoke preset 4 steps in one go, and 2 + 2 steps with a resume in between;
    returns both runs' metrics and final parameters, for bitwise comparisons."""
    from safetensors.torch import load_file

    from course_utils import checkpoint, train
    from course_utils.config import load_config

    def run(**settings):
        settings = {"save_every": 1, **settings}
        train.train(load_config("smoke", out_dir=str(tmp_path / "full"), max_steps=4, **settings), progress=False)
        train.train(load_config("smoke", out_dir=str(tmp_path / "part"), max_steps=2, **settings), progress=False)
        train.train(load_config("smoke", out_dir=str(tmp_path / "part"), max_steps=4, **settings),
                    resume=True, progress=False)
        records = [checkpoint.MetricsLog(tmp_path / d / "metrics.jsonl").read() for d in ("full", "part")]
        params = [load_file(str(tmp_path / d / "checkpoint" / "model.safetensors")) for d in ("full", "part")]
        return records, params

    return run


@pytest.fixture(scope="session")
def finished_run(tmp_path_factory):
    """A finished smoke run (3 steps, a checkpoint after each), shared read-only by the tests
    of the run directory; a test that changes a run works on ``copy_run()``."""
    from course_utils import train
    from course_utils.config import load_config

    out = tmp_path_factory.mktemp("finished") / "run"
    train.train(load_config("smoke", out_dir=str(out), max_steps=3, save_every=1), progress=False)
    return out


@pytest.fixture
def copy_run(finished_run, tmp_path):
    """A function that copies the finished run into this test's tmp_path (without its lock)."""
    import shutil

    def copy():
        run = tmp_path / "run"
        shutil.copytree(finished_run, run, ignore=shutil.ignore_patterns(".lock"))
        return run
    return copy
