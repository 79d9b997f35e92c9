"""A smoke training run, through the command line's ``main``, that kills itself with SIGKILL at
a chosen point or signals itself, for tests/test_crash.py and tests/test_kill_sweep.py.
``python tests/crash_run.py OUT_DIR POINT [--resume]``; POINT is one of KILL_POINTS, one of
WIDE_KILL_POINTS, SIGNAL_POINTS, or 'none'. SIGKILL cannot be caught: nothing is flushed, no finally block runs,
exactly like a Colab runtime that disappears. SIGINT and SIGTERM are caught: the run stops
cleanly and prints the command that continues it."""
import os
import signal
import sys

from course_utils import checkpoint, train

STEPS, SAVE_EVERY = 6, 2


def die():
    os.kill(os.getpid(), signal.SIGKILL)


def arm(point: str) -> None:
    """Patch the library so the process dies at ``point`` (names say where)."""
    real_append, real_save = checkpoint.MetricsLog.append, checkpoint.save
    real_replace, real_torch_save = os.replace, checkpoint.torch.save

    if point == "before_first_checkpoint":        # after step 1's metrics, no checkpoint yet
        def append(self, record):
            real_append(self, record)
            if record["step"] == 1:
                die()
        checkpoint.MetricsLog.append = append
    elif point == "after_metrics_before_checkpoint":   # step 3 logged, checkpoint still at step 2
        def append(self, record):
            real_append(self, record)
            if record["step"] == 3:
                die()
        checkpoint.MetricsLog.append = append
    elif point == "torn_metrics_line":           # half of step 3's JSON line reached the disk
        def append(self, record):
            if record["step"] == 3:
                with open(self.path, "a") as f:
                    f.write('{"step": 3, "reward_me')
                    f.flush()
                    os.fsync(f.fileno())
                die()
            real_append(self, record)
        checkpoint.MetricsLog.append = append
    elif point == "during_checkpoint_write":     # model written, trainer state not yet
        def torch_save(obj, path, *a, **k):
            if isinstance(obj, dict) and obj.get("step") == 4:
                die()
            return real_torch_save(obj, path, *a, **k)
        checkpoint.torch.save = torch_save
    elif point == "between_renames":             # old checkpoint moved aside, new not in place
        def replace(src, dst):
            real_replace(src, dst)
            if str(dst).endswith(checkpoint.PREVIOUS) and train_step[0] == 4:
                die()
        train_step = [0]

        def save(run_dir, model, tokenizer, state):
            train_step[0] = state["step"]
            return real_save(run_dir, model, tokenizer, state)
        checkpoint.os.replace = replace
        checkpoint.save = save
        train.checkpoint.save = save
    elif point == "after_checkpoint":            # step 4 fully saved, dies right after
        def save(run_dir, model, tokenizer, state):
            out = real_save(run_dir, model, tokenizer, state)
            if state["step"] == 4:
                die()
            return out
        train.checkpoint.save = save
    elif point == "between_summary_and_report":   # summary.json written, report.md not yet
        def write_report(*args, **kwargs):
            die()
        train._write_report = write_report
    elif point in SIGNAL_POINTS:                 # a signal (or two) in the middle of step 3
        how, times = point.rsplit("_", 1)
        sig = signal.SIGINT if how == "sigint" else signal.SIGTERM
        real_step = train.grpo_step
        calls = [0]

        def grpo_step(*args, **kwargs):
            calls[0] += 1
            if calls[0] == 3:
                for _ in range(int(times)):
                    os.kill(os.getpid(), sig)
            return real_step(*args, **kwargs)
        train.grpo_step = grpo_step
    elif point != "none":
        raise SystemExit(f"unknown kill point {point!r}")


# The moments a clock cannot be trusted to hit: a few lines of code wide. The wide windows
# (before the first checkpoint, a step logged but not yet saved, just after a save) are hit by
# tests/test_crash.py's 20-kill sweep; the points for them stay here to reproduce one by hand.
KILL_POINTS = ("torn_metrics_line", "during_checkpoint_write", "between_renames",
               "between_summary_and_report")
WIDE_KILL_POINTS = ("before_first_checkpoint", "after_metrics_before_checkpoint", "after_checkpoint")
SIGNAL_POINTS = ("sigint_1", "sigterm_1", "sigint_2")   # the signal, and how many times


def arguments(out_dir: str) -> list[str]:
    return ["--preset", "smoke", "--out_dir", out_dir, "--max_steps", str(STEPS),
            "--save_every", str(SAVE_EVERY), "--train_prompts", "16", "--no-progress"]


if __name__ == "__main__":
    out_dir, point = sys.argv[1], sys.argv[2]
    arm(point)
    raise SystemExit(train.main(arguments(out_dir) + (["--resume"] if "--resume" in sys.argv else [])))
