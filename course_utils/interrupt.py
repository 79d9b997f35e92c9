"""Stopping a run on request: Ctrl-C, Colab's "interrupt execution" (both SIGINT) or SIGTERM
(``kill``, a job scheduler) ends the step in flight, saves a checkpoint and says how to resume.

Without this, SIGINT raises ``KeyboardInterrupt`` in the middle of whatever runs (a sampling
loop, an optimizer update, a checkpoint write) and SIGTERM ends the process silently: the step
in flight is lost, and the user is left to guess what state the run is in. Here the first signal
only sets a flag that the training loop reads between steps. Outside the loop (the evaluations
before and after training) there is no step to finish and the checkpoint on disk is already
whole, so the first signal stops at once. A second signal always stops at once: the last
checkpoint stands (the message says which step it holds, or that none was written yet) and the
step in flight is redone on resume.
"""

from __future__ import annotations

import signal
import threading

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Interrupted(Exception):
    """The run stopped on a signal; the message says where it stands and how to resume."""

    def __init__(self, message: str, signum: int):
        super().__init__(message)
        self.exit_code = 128 + signum   # the shell's convention: 130 for SIGINT, 143 for SIGTERM


class StopRequests:
    """A context manager that turns SIGINT and SIGTERM into a stop request for the training loop
    while ``deferring`` is True, and into an immediate ``Interrupted`` otherwise. Handlers can only
    be installed from the main thread; anywhere else this does nothing and signals keep their
    usual meaning."""

    def __init__(self, how_to_resume: str):
        self.how_to_resume = how_to_resume
        self.signum: int | None = None   # the first signal received, if any
        self.deferring = False
        # the step of the newest checkpoint on disk, kept up to date by the training loop; None
        # while the run has none (set-up, the first evaluation, the steps before the first save)
        self.checkpoint_step: int | None = None
        # False until the run has changed out_dir (cleared it, written its config): a stop
        # before that leaves the directory as it was, and the same command starts over
        self.started = False
        self._previous = {}

    def __enter__(self) -> "StopRequests":
        if threading.current_thread() is threading.main_thread():
            self._previous = {s: signal.signal(s, self._handle) for s in SIGNALS}
        return self

    def __exit__(self, *exc) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, handler)

    @property
    def requested(self) -> bool:
        return self.signum is not None

    def _handle(self, signum: int, frame) -> None:
        if self.deferring and self.signum is None:
            self.signum = signum
            print(f"\n[course_utils] {signal.Signals(signum).name}: stopping after this step, then "
                  f"saving a checkpoint (send it again to stop at once)", flush=True)
            return
        name = signal.Signals(signum).name
        if not self.started:
            raise Interrupted(f"stopped on {name} during set-up; nothing in the run directory was "
                              f"changed: run the same command again", signum)
        where = (f"the checkpoint at step {self.checkpoint_step} stands" if self.checkpoint_step
                 else "no checkpoint had been written yet, so the run will start from the beginning")
        what = "before the step in flight finished" if self.deferring else "outside a training step"
        raise Interrupted(f"stopped on {name} {what}; {where}. To continue, {self.how_to_resume}",
                          signum)

    def stopped(self, step: int, total: int) -> Interrupted:
        """The exception to raise once the loop has saved a checkpoint after ``step``."""
        return Interrupted(f"stopped on {signal.Signals(self.signum).name} after step {step} of "
                           f"{total}, with a checkpoint saved. To continue, {self.how_to_resume}",
                           self.signum)
