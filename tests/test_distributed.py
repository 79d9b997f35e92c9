"""Two processes (accelerate launch, gloo on the CPU) make the same update as one process on
the same global batch: each process keeps whole groups, rewards are gathered for the batch-level
statistics, the loss is normalized by global counts and the gradients are summed."""
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

SCRIPT = Path(__file__).with_name("distributed_step.py")


def _run(command, out, variant, env=None):
    proc = subprocess.run(command + [str(SCRIPT), str(out), variant], capture_output=True, text=True,
                          timeout=600, env={**os.environ, **(env or {})})
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("variant", ["inverse_variance", "adaptive"])
def test_two_processes_make_the_same_update_as_one(tmp_path, variant):
    one = _run([sys.executable], tmp_path / "one.pt", variant)
    launcher = shutil.which("accelerate", path=str(Path(sys.executable).parent)) or "accelerate"
    two = _run([launcher, "launch", "--multi_gpu", "--num_processes", "2", "--num_machines", "1",
                "--mixed_precision", "no", "--dynamo_backend", "no"], tmp_path / "two.pt", variant,
               env={"ACCELERATE_USE_CPU": "1", "OMP_NUM_THREADS": "1"})
    assert (one["processes"], two["processes"]) == (1, 2)
    if variant == "adaptive":   # the second step trained with the weight the first one set
        assert one["entropy_weight"] > 0 and one["control_coef"] > one["entropy_weight"]
    controls = [k for k in one if k.startswith("control_")]
    for key in ("reward_mean", "adv_std", "entropy_weight", "loss", "grad_norm", *controls):
        assert abs(one[key] - two[key]) <= 1e-5 * max(1.0, abs(one[key])), key
    a, b = torch.load(tmp_path / "one.pt"), torch.load(tmp_path / "two.pt")
    assert a.keys() == b.keys()
    diff = sum(float(((a[k] - b[k]) ** 2).sum()) for k in a) ** 0.5
    size = sum(float((a[k] ** 2).sum()) for k in a) ** 0.5
    assert size > 0 and diff / size < 1e-4, diff / size
