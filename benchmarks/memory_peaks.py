"""The CPU peaks that course_utils.plan's memory estimate is checked against, measured once.

    python benchmarks/memory_peaks.py [--out benchmarks/memory_peaks.json]

Each shape runs ``tests/memory_probe.py`` in a fresh process: two GRPO-shaped training steps of
a random model with Qwen2.5-0.5B's full architecture (24 layers) on the CPU, and the peak
resident memory they added. The two large shapes took four minutes together on a 2-core AVX2
machine, too long to repeat in every test run, so ``tests/test_plan.py`` checks the plan against
the peaks stored here and measures only the smallest shape live (so a torch or allocator that
changes the peak still meets the plan's bound in every test run). Rerun this after changing the
probe or the plan's memory model.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
PROBE = ROOT / "tests" / "memory_probe.py"
# (prompts, group size, prompt tokens, completion tokens, LoRA rank): the shapes tests/test_plan.py
# reads. Two regimes for full fine-tuning (a small batch, where AdamW's update is the larger
# transient, and a larger one, where activations and logits are), and LoRA at the larger one.
SHAPES = [(1, 4, 64, 16, 0), (3, 8, 128, 40, 0), (3, 8, 128, 40, 16)]


def measure(shape: tuple[int, ...]) -> float:
    """The peak resident memory (GiB) the probe's two steps added, in a fresh CPU-only process."""
    env = {**os.environ, "CUDA_VISIBLE_DEVICES": ""}
    out = subprocess.run([sys.executable, str(PROBE), *map(str, shape)], capture_output=True,
                         text=True, timeout=900, check=True, env=env, cwd=ROOT)
    return json.loads(out.stdout.strip().splitlines()[-1])["peak_gib"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "memory_peaks.json"))
    args = parser.parse_args()
    rows = []
    for shape in SHAPES:
        peak = measure(shape)
        print(f"prompts {shape[0]}, group {shape[1]}, prompt {shape[2]}, completion {shape[3]}, "
              f"LoRA rank {shape[4]}: {peak:.3f} GiB", flush=True)
        rows.append(dict(zip(("prompts", "group_size", "prompt_len", "completion_len", "lora_rank"),
                             shape), peak_gib=peak))
    result = dict(date=datetime.date.today().isoformat(), torch=torch.__version__,
                  machine=platform.machine(), cpu_capability=torch.backends.cpu.get_cpu_capability(),
                  python=platform.python_version(), peaks=rows)
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
