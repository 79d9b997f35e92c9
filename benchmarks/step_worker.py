"""One arm of benchmarks/step_speed.py: time GRPO steps of the cpu preset in this process.

    python benchmarks/step_worker.py --steps 6 --precision bf16 --kernels fast [--out result.json]

Imports ``course_utils`` from wherever PYTHONPATH points, so step_speed.py can run the same
script against an older checkout of the library (the old path) and this one (the new path).
Writes per-step seconds by phase, completion tokens and the matmul peaks of this process.
"""
from __future__ import annotations

import argparse
import json
import statistics

import torch

from grpo_vs_trl import matmul_peak_flops   # benchmarks/ is this script's folder, so on sys.path


def matmul_gflops(dtype: torch.dtype) -> float:
    return matmul_peak_flops(repeats=6, dtype=dtype) / 1e9


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--steps", type=int, default=6)
    parser.add_argument("--precision", default="fp32")
    parser.add_argument("--kernels", default=None, help="reference or fast (absent in old checkouts)")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()

    import course_utils
    from course_utils import data, train
    from course_utils.config import load_config

    kernels = {} if args.kernels is None else dict(kernels=args.kernels)
    cfg = load_config("cpu", precision=args.precision, out_dir="/tmp/unused", **kernels)
    policy = train.setup(cfg)
    prompts = data.make_prompts(cfg, policy.tokenizer, held_out=False)
    records = []
    for step in range(args.steps + 1):   # step 0 is a warm-up, not reported
        m = train.grpo_step(policy, train.batch_for_step(step, prompts, cfg))
        if step:
            records.append(m)
    phases = sorted({k for r in records for k in r if k.startswith("time_")})
    result = dict(
        library=course_utils.__file__, precision=args.precision, kernels=args.kernels, steps=args.steps,
        step_seconds=[r["step_time"] for r in records],
        phase_seconds={k[5:]: [r.get(k, 0.0) for r in records] for k in phases},
        completion_tokens=[r["completion_tokens"] * cfg.prompts_per_step * cfg.group_size
                           for r in records],
        reward_mean=[r["reward_mean"] for r in records],
        matmul_gflops=dict(fp32=matmul_gflops(torch.float32), bf16=matmul_gflops(torch.bfloat16)),
        threads=torch.get_num_threads(), torch=torch.__version__,
    )
    text = json.dumps(result)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text)
    print(f"{args.precision} {args.kernels}: median step {statistics.median(result['step_seconds']):.2f} s; " +
          ", ".join(f"{k} {statistics.median(v):.2f}" for k, v in result["phase_seconds"].items()))


if __name__ == "__main__":
    main()
