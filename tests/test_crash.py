"""SIGKILL a training run at several points (during a checkpoint write among them), resume it,
and finish with parameters and metrics bitwise equal to an uninterrupted run of the same seed."""
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from course_utils import checkpoint

SCRIPT = Path(__file__).with_name("crash_run.py")
sys.path.insert(0, str(SCRIPT.parent))
from crash_run import KILL_POINTS, STEPS  # noqa: E402


def _run(out: Path, point: str, resume: bool = False) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), str(out), point] + (["--resume"] if resume else []),
                          capture_output=True, text=True, timeout=300)


def _strip(records):  # wall-clock fields differ run to run; everything else must not
    return [{k: v for k, v in r.items() if "time" not in k and k != "tokens_per_s"} for r in records]


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    out = tmp_path_factory.mktemp("full")
    proc = _run(out, "none")
    assert proc.returncode == 0, proc.stderr[-2000:]
    return out


@pytest.mark.parametrize("point", KILL_POINTS)
def test_a_killed_run_resumes_to_the_same_result(tmp_path, uninterrupted, point):
    killed = _run(tmp_path, point)
    assert killed.returncode == -signal.SIGKILL, (killed.returncode, killed.stderr[-2000:])
    found = checkpoint.find(tmp_path)
    if point == "before_first_checkpoint":
        assert found is None
    else:  # whatever the moment, a complete checkpoint survives
        assert found is not None and (found / checkpoint.STATE_FILE).exists()
    resumed = _run(tmp_path, "none", resume=True)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    a = load_file(str(uninterrupted / "checkpoint" / "model.safetensors"))
    b = load_file(str(tmp_path / "checkpoint" / "model.safetensors"))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    ra = checkpoint.MetricsLog(uninterrupted / "metrics.jsonl").read()
    rb = checkpoint.MetricsLog(tmp_path / "metrics.jsonl").read()
    assert [r["step"] for r in rb] == list(range(1, STEPS + 1))   # none missing, none twice
    assert _strip(ra) == _strip(rb)
    assert not (tmp_path / ".checkpoint-tmp").exists() and not (tmp_path / ".checkpoint-old").exists()
