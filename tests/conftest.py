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
