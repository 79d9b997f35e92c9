"""Lesson 7, 6.9's runs: the gated recipe of 6.8 with the policy term only at the forks.

    python benchmarks/forks_runs.py --seed 16                    # the forks arm on a tuning seed
    python benchmarks/forks_runs.py --seed 16 --control          # the gated recipe itself
    python benchmarks/forks_runs.py --seed 16 --control --max_steps 5   # the control's first steps

The forks arm is 6.8's gated recipe (``notebooks/results/gated/tuning/gated-seed16``'s
config, seed and out_dir aside) with ``top_entropy_quantile`` = 0.2 and nothing else changed:
the clipped surrogate trains only the fifth of each step's completion tokens with the highest
entropy (Wang et al. 2025; TRL's flag of that name), while the KL and the entropy bonus keep
every token. A full run (150 steps) copies its config, metrics, summary and report to
``notebooks/results/forks/<arm>-seed<N>``; a shortened one stays in ``runs/forks``. The third
command above is how ``notebooks/results/forks/rerun-gated-seed16-steps5`` was made (its
config, metrics and summary copied from ``runs/forks/gated-seed16-steps5``): the stored control,
rerun for 5 steps on the forks runs' machine, which the build checks against the stored log.

Run it alone, one run after another: two torch processes on 2 cores slow each other down many
times over. The runs are bf16 (``precision`` 'auto' on a CPU with bf16 units), so a run is
only comparable with its control on the same kind of machine (lesson 7, 6.7): the summary
records the CPU.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from course_utils import train  # noqa: E402
from course_utils.config import Config  # noqa: E402

RESULTS = ROOT / "notebooks" / "results"
RECIPE = RESULTS / "gated" / "tuning" / "gated-seed16" / "config.json"
TOP_ENTROPY_QUANTILE = 0.2   # the paper's fifth
STORED_FILES = ("config.json", "metrics.jsonl", "summary.json", "report.md")


def config_for(seed: int, control: bool, max_steps: int | None) -> Config:
    values = json.loads(RECIPE.read_text())
    arm = "gated" if control else "forks"
    full = max_steps is None or max_steps == values["max_steps"]
    # relative to the repository's root (main() runs there), as every stored config's out_dir is
    values.update(seed=seed, out_dir=f"runs/forks/{arm}-seed{seed}" + ("" if full else f"-steps{max_steps}"))
    if max_steps is not None:
        values["max_steps"] = max_steps
    if not control:
        values["top_entropy_quantile"] = TOP_ENTROPY_QUANTILE
    return Config.from_dict(values).validate()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, required=True)
    parser.add_argument("--control", action="store_true", help="the gated recipe, unchanged")
    parser.add_argument("--max_steps", type=int, default=None, help="shorten the run (left in runs/forks)")
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args()
    cfg = config_for(args.seed, args.control, args.max_steps)
    os.chdir(ROOT)
    train.train(cfg, progress=False, overwrite=args.overwrite)
    if args.max_steps is None:
        run = Path(cfg.out_dir)
        stored = RESULTS / "forks" / run.name
        stored.mkdir(parents=True, exist_ok=True)
        for name in STORED_FILES:
            shutil.copy2(run / name, stored / name)
        print(f"[forks_runs] stored {stored.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
