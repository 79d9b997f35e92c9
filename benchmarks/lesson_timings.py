"""Time each lesson's full run (the solution notebook, not smoke mode) and store the result.

    python benchmarks/lesson_timings.py            # lessons 1-6 and 8
    python benchmarks/lesson_timings.py 4 6        # just these

It clones this repository's HEAD (committed work only) into a temporary folder and executes
``notebooks/solutions/NN_*.ipynb`` there, top to bottom, with this interpreter's packages and
``COURSE_SMOKE`` unset, so nothing in the working tree is touched. Each lesson's wall time, with
the commit, the date and the machine, replaces that lesson's record in
``notebooks/results/lesson-timings.json``; the README's "full CPU run" column is rendered from
that file by ``notebooks/build.py``, so no run time in the lessons table is typed by hand.
Lesson 7 is not timed: its full run needs a T4 (on a CPU it runs shrunk).

Run it alone: two torch processes on 2 cores slow each other down many times over.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
# the same machine record, commit and clone as the README's timing table
from readme_timings import fresh_clone, head_commit, machine  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TIMINGS = ROOT / "notebooks" / "results" / "lesson-timings.json"
TIMED = [1, 2, 3, 4, 5, 6, 8]


def run_notebook(path: Path, timeout_s: int) -> float:
    """Execute one notebook in its own folder, as Colab or nbmake would; its wall time in s."""
    import nbclient
    import nbformat

    nb = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(nb, timeout=timeout_s, kernel_name="python3",
                                     resources={"metadata": {"path": str(path.parent)}})
    start = time.perf_counter()
    client.execute()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("lessons", nargs="*", type=int, default=TIMED,
                        help=f"lesson numbers, of {TIMED} (default: all of them)")
    parser.add_argument("--timeout_s", type=int, default=3600, help="per cell")
    args = parser.parse_args()
    unknown = sorted(set(args.lessons) - set(TIMED))
    if unknown:
        raise SystemExit(f"error: lessons {unknown} are not timed here; choose from {TIMED} "
                         f"(lesson 7's full run needs a T4)")
    commit = head_commit()
    records = json.loads(TIMINGS.read_text()) if TIMINGS.exists() else {}
    os.environ.pop("COURSE_SMOKE", None)   # the full run, whatever the calling shell says
    with tempfile.TemporaryDirectory(prefix="lesson-timing-") as tmp:
        clone = fresh_clone(tmp)
        for lesson in args.lessons:
            (path,) = (clone / "notebooks" / "solutions").glob(f"{lesson:02d}_*.ipynb")
            print(f"[lesson_timings] running {path.name} (full)", flush=True)
            seconds = run_notebook(path, args.timeout_s)
            records[str(lesson)] = dict(notebook=path.name, commit=commit,
                                        date=datetime.date.today().isoformat(),
                                        machine=machine(), seconds=round(seconds, 1))
            print(f"[lesson_timings] {json.dumps(records[str(lesson)])}", flush=True)
            # written after each lesson, so a stopped run keeps what it measured
            TIMINGS.write_text(json.dumps(dict(sorted(records.items(), key=lambda kv: int(kv[0]))),
                                          indent=1) + "\n")
    print(f"[lesson_timings] wrote {TIMINGS}")


if __name__ == "__main__":
    main()
