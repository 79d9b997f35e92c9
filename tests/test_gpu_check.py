"""benchmarks/gpu_check.py, the T4 run's first check: its code path on a CPU (shrunk), its GPU
report from a result of the shape it writes, and the random-weight model of Qwen2.5-0.5B's
shapes it falls back on."""
import json
import os
import subprocess
import sys
from pathlib import Path

import torch

from course_utils import models, plan

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "gpu_check.py"
sys.path.insert(0, str(ROOT / "benchmarks"))


def test_the_check_runs_shrunk_on_a_cpu(tmp_path):
    out = tmp_path / "gpu-check.json"
    run = subprocess.run([sys.executable, str(SCRIPT), "--smoke", "--out", str(out)],
                         capture_output=True, text=True, timeout=300, cwd=tmp_path,
                         env={**os.environ, "CUDA_VISIBLE_DEVICES": ""})   # the CPU path, on a GPU machine too
    assert run.returncode == 0, run.stderr[-2000:]
    result = json.loads(out.read_text())
    assert result["steps"] == 2 and len(result["step_seconds"]) == 2
    assert result["nonfinite_skipped"] == 0 and result["scaler_scale"] == [None] * 3
    assert {"generation", "forward", "backward", "optimizer"} <= set(result["phase_seconds"])
    assert result["prompt_len"] > 16           # the snippet's tokens plus the chat template
    assert "resident peak" in run.stdout and "non-finite skips: 0" in run.stdout


def test_without_a_gpu_it_says_so_instead_of_pretending(capsys):
    import gpu_check

    if torch.cuda.is_available():   # pragma: no cover - CI has no GPU
        return
    assert gpu_check.main([]) == 2
    assert "no CUDA GPU here" in capsys.readouterr().err


def test_the_gpu_report_sets_each_measurement_against_the_plan():
    """The GPU branch of the report, from a result of the shape main() writes on a GPU."""
    import gpu_check

    result = dict(
        emulation=dict(gpu="Some GPU", gpu_total_gib=139.8, outside_allocator_gib_at_start=0.5,
                       allocator_cap_gib=14.25),
        model=models.QWEN25_SHAPED, precision="fp16", steps=3, prompt_len=180, max_new_tokens=64,
        micro_batch_rows=8,
        planned=dict(tensors_gib=10.1, reserved_gib=11.1, process_gib=12.1, seconds_per_step_t4=8.0),
        measured=dict(reserved_gib=9.5, allocated_gib=9.0, outside_allocator_gib=0.6, allocator_cache=0.0556),
        step_seconds=[1.0, 2.0, 3.0], phase_seconds={"generation": [0.5, 0.6, 0.7]},
        completion_tokens=[64, 64, 64], nonfinite_skipped=1, scaler_scale=[65536.0, 32768.0, 32768.0, 32768.0])
    text = gpu_check.report(result)
    assert "allocator capped at 14.25 GiB" in text
    assert "max_memory_reserved)    9.50 GiB   plan  11.10 GiB" in text
    assert "max_memory_allocated)    9.00 GiB   plan  10.10 GiB" in text
    assert "median of 3): 2.00 (generation 0.60)" in text
    assert "non-finite skips: 1; gradient scaler's scale per step: 65536, 32768, 32768, 32768" in text
    assert "probe" not in text and "cap bounds" not in text   # an older result has no probes

    result.update(scaler="GradScaler", probes=dict(
        allocator_cap=dict(refused_past_cap=True, granted_under_cap=False),
        autocast_copies=dict(planned_copies_gib=0.92, forward_extra_gib=[0.93, 0.94], held_after_gib=[0.0, 0.01])))
    text = gpu_check.report(result)
    assert "a block past it refused True, one under it granted False" in text
    assert "sampling forward: 0.93, 0.94 GiB (plan 2P = 0.92 GiB), held after it 0.00, 0.01 GiB" in text
    assert "gradient scaler (GradScaler)'s scale per step: 65536" in text


def test_the_shaped_model_has_qwen25_05bs_parameters_and_architecture():
    """The fallback model: Qwen2.5-0.5B-Instruct's shapes (on the meta device, no memory)."""
    from transformers import Qwen2ForCausalLM

    with torch.device("meta"):
        model = Qwen2ForCausalLM(models.qwen25_shaped_config())
    assert sum(p.numel() for p in model.parameters()) == plan.QWEN25_05B.n_params
    assert models.architecture(models.QWEN25_SHAPED) == plan.QWEN25_05B
    tokenizer = models.load_tokenizer(models.QWEN25_SHAPED)
    assert len(tokenizer) <= models.qwen25_shaped_config().vocab_size   # its ids are the model's
