"""Time one of the README's two commands, word for word, in a fresh clone, and store the result.

    python benchmarks/readme_timings.py main    # set up and run the main job
    python benchmarks/readme_timings.py test    # set up and run the tests (what CI runs)

It clones this repository's HEAD (committed work only) into a temporary folder, runs the line
after ``<!-- command: NAME -->`` in README.md there with bash, and appends one record to
``notebooks/results/readme-timings.jsonl``: the command's name, the commit, the date, the
machine (CPU model, the cores this process may use, whether the CPU has bf16 matrix units),
the wall time in seconds, the exit status and the result (pytest's summary line, or the main
job's held-out greedy pass rates). The README's timing table is rendered from that file by
``notebooks/build.py``, so no wall time in the README is typed by hand.

Run it alone: two torch processes on 2 cores slow each other down many times over.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TIMINGS = ROOT / "notebooks" / "results" / "readme-timings.jsonl"


def readme_commands(readme: str) -> dict[str, str]:
    """Each ``<!-- command: NAME -->`` block of the README: NAME -> its bash line (the same
    parser tests/test_repo.py checks against CI's script)."""
    blocks = re.findall(r"<!-- command: (\w+) -->\s*```bash\n(.+?)\n```", readme, flags=re.S)
    return {name: body.strip() for name, body in blocks}


def readme_command(name: str, readme: str) -> str:
    commands = readme_commands(readme)
    if name not in commands:
        raise SystemExit(f"error: README.md has no '<!-- command: {name} -->' block; "
                         f"it has {sorted(commands)}")
    return commands[name]


def machine() -> dict:
    """The CPU model, the cores this process may use, and its bf16 matrix units (from the
    kernel's CPU flags, so nothing here imports torch)."""
    info = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else ""
    model = re.search(r"^model name\s*:\s*(.+)$", info, re.M)
    flags = set((re.search(r"^flags\s*:\s*(.+)$", info, re.M) or [None, ""])[1].split())
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return dict(cpu=model.group(1).strip() if model else "unknown", cores=cores,
                bf16_units=sorted(flags & {"amx_bf16", "avx512_bf16"}))


def head_commit() -> str:
    """The commit a fresh clone of this repository checks out (committed work only)."""
    return subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], check=True,
                          capture_output=True, text=True).stdout.strip()


def fresh_clone(folder: str) -> Path:
    """A clone of this repository's HEAD inside ``folder``: what a newcomer gets."""
    clone = Path(folder) / "clone"
    subprocess.run(["git", "clone", "-q", str(ROOT), str(clone)], check=True)
    return clone


def result_of(name: str, clone: Path, output: str) -> str:
    """What the command produced: pytest's last summary line, or the main job's held-out
    greedy pass rates read from the run it wrote."""
    if name == "test":
        lines = [line for line in output.splitlines() if re.search(r"\d+ (passed|failed)", line)]
        return lines[-1].strip("= ") if lines else "no pytest summary line"
    summary = clone / "runs" / "cpu" / "summary.json"
    if not summary.exists():
        return "no runs/cpu/summary.json written"
    after = json.loads(summary.read_text())["after"]["greedy"]
    return (f"held-out greedy pass (both) {after['pass_both']:.1%}, two-digit targets "
            f"{after['pass_both_two_digit']:.1%}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("command", choices=["main", "test"], help="which README command to time")
    args = parser.parse_args()
    readme = (ROOT / "README.md").read_text()
    command = readme_command(args.command, readme)
    commit = head_commit()
    with tempfile.TemporaryDirectory(prefix="readme-timing-") as tmp:
        clone = fresh_clone(tmp)
        print(f"[readme_timings] running the README's '{args.command}' command in {clone}",
              flush=True)
        start = time.perf_counter()
        run = subprocess.run(["bash", "-c", command], cwd=clone, capture_output=True, text=True)
        seconds = time.perf_counter() - start
        output = run.stdout + run.stderr
        record = dict(command=args.command, commit=commit,
                      date=datetime.date.today().isoformat(), machine=machine(),
                      seconds=round(seconds, 1), returncode=run.returncode,
                      result=result_of(args.command, clone, output))
    with TIMINGS.open("a") as f:
        f.write(json.dumps(record) + "\n")
    print(output[-3000:])
    print(f"[readme_timings] {json.dumps(record)}\n[readme_timings] appended to {TIMINGS}")
    sys.exit(run.returncode)


if __name__ == "__main__":
    main()
