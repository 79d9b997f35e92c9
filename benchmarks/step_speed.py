"""The cpu preset's GRPO step: the old path against the new one, side by side in one run.

    python benchmarks/step_speed.py                       # ~10 min on 2 cores
    python benchmarks/step_speed.py --steps 4 --rounds 1 --baseline 67ede1c

Arms, each a fresh process running ``benchmarks/step_worker.py`` on the same steps (same
seed, prompts and first samples; sampled completions then differ between arms, so tokens are
reported beside seconds):

* ``old fp32``: the library as of ``--baseline`` (a git worktree of that commit; default the
  last commit before the speed work), fp32, exactly the step the main job ran before;
* ``reference fp32``: this checkout, ``kernels='reference'`` (the default: bitwise the old
  computation, so the stored runs reproduce), fp32;
* ``fast fp32``: ``kernels='fast'``, fp32 (what a CPU without bf16 units gets with it);
* ``fast bf16``: ``kernels='fast'``, bf16 (what ``precision='auto'`` picks on a CPU with AMX).

Arms alternate for ``--rounds`` rounds so that drift in the machine's speed hits all of them.
Run it alone: a second torch process on 2 cores slows both many times over. It prints a
Markdown table for benchmarks/RESULTS.md and writes the raw numbers with ``--json``.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
BASELINE = "67ede1c"   # main before issue 24 (the 7.9 s fp32 step of the issue)
PHASES = ("generation", "forward", "backward", "optimizer")


def run_arm(library: Path, precision: str, kernels: str | None, steps: int) -> dict:
    out = Path(tempfile.mkstemp(suffix=".json")[1])
    env = dict(os.environ, PYTHONPATH=str(library))
    subprocess.run([sys.executable, str(ROOT / "benchmarks" / "step_worker.py"), "--steps",
                    str(steps), "--precision", precision, "--out", str(out)]
                   + ([] if kernels is None else ["--kernels", kernels]),
                   env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    result = json.loads(out.read_text())
    out.unlink()
    if not result["library"].startswith(str(library)):
        raise RuntimeError(f"the worker imported {result['library']}, not the library in {library}")
    return result


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--steps", type=int, default=5, help="measured steps per arm and round")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--baseline", default=BASELINE, help="git commit of the old path")
    parser.add_argument("--json", default=None, help="write the raw results here")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        old = Path(tmp) / "baseline"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(old), args.baseline],
                       check=True, capture_output=True)
        try:
            arms = {"old fp32": (old, "fp32", None), "reference fp32": (ROOT, "fp32", "reference"),
                    "fast fp32": (ROOT, "fp32", "fast"), "fast bf16": (ROOT, "bf16", "fast")}
            results: dict[str, list[dict]] = {name: [] for name in arms}
            for r in range(args.rounds):
                for name, (library, precision, kernels) in arms.items():
                    results[name].append(run_arm(library, precision, kernels, args.steps))
                    print(f"round {r + 1}: {name} done", file=sys.stderr)
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(old)],
                           capture_output=True)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    print(report(results, args))


def report(results: dict[str, list[dict]], args) -> str:
    def pooled(name, key):
        return [x for r in results[name] for x in (r[key] if key != "phase" else [])]

    def phase(name, p):
        return statistics.median([x for r in results[name] for x in r["phase_seconds"].get(p, [])])

    step = {n: statistics.median(pooled(n, "step_seconds")) for n in results}
    tokens = {n: statistics.mean(pooled(n, "completion_tokens")) for n in results}
    first = next(iter(results.values()))[0]
    lines = [f"## The cpu preset's step, old path vs new ({args.rounds} rounds x {args.steps} steps "
             f"per arm after a warm-up; torch {first['torch']}, {first['threads']} threads)", "",
             "| phase (median s) | " + " | ".join(results) + " |", "|---|" + "---|" * len(results)]
    for p in PHASES:
        lines.append(f"| {p} | " + " | ".join(f"{phase(n, p):.2f}" for n in results) + " |")
    lines.append("| **whole step** | " + " | ".join(f"**{step[n]:.2f}**" for n in results) + " |")
    lines.append("| completion tokens per step (mean) | " + " | ".join(f"{tokens[n]:.0f}" for n in results) + " |")
    base = "old fp32"
    lines.append(f"| speed-up over {base} (step) | " + " | ".join(f"{step[base] / step[n]:.2f}x" for n in results) + " |")
    per_token = {n: step[n] / tokens[n] for n in results}
    lines.append(f"| speed-up per completion token | " + " | ".join(f"{per_token[base] / per_token[n]:.2f}x" for n in results) + " |")
    peaks = {k: statistics.median([r["matmul_gflops"][k] for rs in results.values() for r in rs])
             for k in ("fp32", "bf16")}
    lines += ["", f"Matrix-multiply peak measured in the same processes (2048^3, best of 3): "
                  f"fp32 {peaks['fp32']:.0f} GFLOP/s, bf16 {peaks['bf16']:.0f} GFLOP/s "
                  f"({peaks['bf16'] / peaks['fp32']:.1f}x)."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
