"""SIGKILL a training run at the narrow points a clock would rarely hit (mid-line, mid-save,
between the renames) and at random moments (8 per CI run), resume it, and finish with parameters
and metrics bitwise equal to an uninterrupted run of the same seed.
Ctrl-C and SIGTERM stop it cleanly instead, with a checkpoint and the command that resumes it
(issue 14, finding 12)."""
import os
import random
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from course_utils import checkpoint

SCRIPT = Path(__file__).with_name("crash_run.py")
sys.path.insert(0, str(SCRIPT.parent))
from crash_run import KILL_POINTS, SIGNAL_POINTS, STEPS  # noqa: E402


def _run(out: Path, point: str, resume: bool = False) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), str(out), point] + (["--resume"] if resume else []),
                          capture_output=True, text=True, timeout=300)


def _strip(records):  # wall-clock fields differ run to run; everything else must not
    return [{k: v for k, v in r.items() if "time" not in k and k != "tokens_per_s"} for r in records]


DURATION = {}   # the uninterrupted run's wall time, for the kill sweep


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    out = tmp_path_factory.mktemp("full")
    started = time.perf_counter()
    proc = _run(out, "none")
    DURATION["uninterrupted"] = time.perf_counter() - started
    assert proc.returncode == 0, proc.stderr[-2000:]
    return out


@pytest.mark.parametrize("point", KILL_POINTS)
def test_a_killed_run_resumes_to_the_same_result(tmp_path, uninterrupted, point):
    killed = _run(tmp_path, point)
    assert killed.returncode == -signal.SIGKILL, (killed.returncode, killed.stderr[-2000:])
    found = checkpoint.find(tmp_path)   # whatever the moment, a complete checkpoint survives
    assert found is not None and (found / checkpoint.STATE_FILE).exists()
    resumed = _run(tmp_path, "none", resume=True)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert_same_run(uninterrupted, tmp_path)


def assert_same_run(uninterrupted: Path, run: Path) -> None:
    """Same parameters bit for bit, the same metrics, every step logged once, nothing left over."""
    a = load_file(str(uninterrupted / "checkpoint" / "model.safetensors"))
    b = load_file(str(run / "checkpoint" / "model.safetensors"))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    ra = checkpoint.MetricsLog(uninterrupted / "metrics.jsonl").read()
    rb = checkpoint.MetricsLog(run / "metrics.jsonl").read()
    assert [r["step"] for r in rb] == list(range(1, STEPS + 1))   # none missing, none twice
    assert _strip(ra) == _strip(rb)
    leftovers = [p.name for p in run.iterdir() if p.name.startswith(".") and p.name != ".lock"]
    assert not leftovers, leftovers
    # every file a finished run has, the derived report and curves included (issue 26, 2)
    missing = [n for n in checkpoint.RUN_FILES if not (run / n).exists()]
    assert not missing, missing


@pytest.mark.parametrize("point", SIGNAL_POINTS)
def test_ctrl_c_and_sigterm_stop_cleanly_and_print_the_command_that_resumes(tmp_path, uninterrupted,
                                                                            point):
    stopped = _run(tmp_path, point)
    sig = signal.SIGTERM if point.startswith("sigterm") else signal.SIGINT
    assert stopped.returncode == 128 + sig, (stopped.returncode, stopped.stderr[-2000:])
    assert "Traceback" not in stopped.stderr, stopped.stderr[-2000:]
    message = stopped.stderr.strip().splitlines()[-1]
    step = torch.load(checkpoint.find(tmp_path) / checkpoint.STATE_FILE, weights_only=True)["step"]
    if point.endswith("_1"):   # one signal: step 3 finishes and is saved
        assert "after step 3 of 6, with a checkpoint saved" in message, message
        assert step == 3
    else:                      # a second signal stops at once: the checkpoint of step 2 stands
        assert "before the step in flight finished" in message, message
        assert step == 2
    command = shlex.split(message.split("To continue, run: ", 1)[1])
    assert command[:3] == ["python", "-m", "course_utils.train"] and command[-1] == "--resume"
    resumed = subprocess.run([sys.executable] + command[1:], capture_output=True, text=True,
                             timeout=300)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert_same_run(uninterrupted, tmp_path)


# Eight kills keep the suite's time in bounds (each costs up to one run's duration, and twenty
# took three minutes on a 2-core AVX2 machine); every CI run draws fresh moments, so the runs add
# up to a larger sweep. KILL_SWEEP_KILLS=N runs a longer sweep on demand.
SWEEP_KILLS = int(os.environ.get("KILL_SWEEP_KILLS") or 8)


def test_kills_at_random_moments_then_a_resume_give_the_uninterrupted_run(tmp_path, uninterrupted):
    """SWEEP_KILLS SIGKILLs, each at a moment drawn uniformly over an uninterrupted run's
    duration, so they land in start-up, the evaluations, steps, log appends and checkpoint
    writes alike. A run directory is resumed after each kill; whenever a resume survives to the
    end, that run is compared with the uninterrupted one and the next kill goes to a fresh
    directory. The moments are drawn afresh on every CI run; KILL_SWEEP_SEED replays a draw (the
    same fractions of the run's duration, so timing noise still moves the moments a little). The
    time is bounded by SWEEP_KILLS of one run's duration plus the resumes that finish."""
    seed = int(os.environ.get("KILL_SWEEP_SEED") or time.time_ns() % 2 ** 31)
    rng = random.Random(seed)
    print(f"kill sweep: KILL_SWEEP_SEED={seed} replays this draw")   # shown if an assert below fails
    duration = DURATION["uninterrupted"]
    runs, kills, outcomes = [tmp_path / "run0"], 0, []
    while kills < SWEEP_KILLS:
        delay = rng.uniform(0, duration)
        proc = subprocess.Popen([sys.executable, str(SCRIPT), str(runs[-1]), "none", "--resume"],
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        try:
            proc.wait(timeout=delay)
        except subprocess.TimeoutExpired:
            proc.kill()
            kills += 1
        stderr = proc.communicate()[1]
        assert proc.returncode in (0, -signal.SIGKILL), (seed, proc.returncode, stderr[-2000:])
        found = checkpoint.find(runs[-1]) if runs[-1].exists() else None
        step = torch.load(found / checkpoint.STATE_FILE, weights_only=True)["step"] if found else 0
        outcomes.append(f"{delay:.1f}s:{'finished' if proc.returncode == 0 else 'killed'}@{step}")
        if proc.returncode == 0:      # this directory's run is whole: check it, use a new one
            assert_same_run(uninterrupted, runs[-1])
            runs.append(tmp_path / f"run{len(runs)}")
    if runs[-1].exists():
        resumed = _run(runs[-1], "none", resume=True)
        assert resumed.returncode == 0, (seed, resumed.stderr[-2000:])
        assert_same_run(uninterrupted, runs[-1])
    print(f"kill sweep, KILL_SWEEP_SEED={seed}, one run {duration:.1f} s, {len(runs)} run "
          f"directories: {' '.join(outcomes)}")
