"""Checkpoints that survive a crash, and the append-only metrics log.

A checkpoint is a directory: the model (``save_pretrained``, safetensors), the tokenizer, and
``trainer_state.pt`` (optimizer, scheduler, step, random-generator states, config). It is
written to a temporary directory and then renamed into place, so a crash mid-write leaves the
previous checkpoint whole. State is read back with ``torch.load(weights_only=True)``: loading
a checkpoint never runs code from the file.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import tempfile
from pathlib import Path

import torch

from .config import Config

STATE_FILE = "trainer_state.pt"
# Fields that may change when a run is resumed; any other difference means a different run.
# Not eval_prompts: the "before" evaluation is kept from the first invocation, and an "after"
# on another set of prompts would not be comparable with it.
RESUMABLE_CHANGES = {"out_dir", "max_steps", "epochs", "eval_every", "save_every"}


class CheckpointError(RuntimeError):
    """A checkpoint cannot be used for this run; the message says why."""


class RunLock:
    """An exclusive lock on a run directory, held for the whole run, so two runs (a double
    click on a training cell, two seeds started with one out_dir, a --resume while the run is
    live) can never write into one directory at once. The operating system releases it when
    the process ends, however it ends, so a crash never leaves a stale lock behind. The lock
    file names its holder, and a refused run says who that is."""

    def __init__(self, run_dir: Path):
        self.path = Path(run_dir) / ".lock"
        self.file = None

    def __enter__(self) -> "RunLock":
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.file = open(self.path, "a+")
        try:
            _lock_file(self.file)
        except OSError:
            self.file.seek(0)
            holder = self.file.read().strip() or "another process"
            self.file.close()
            raise CheckpointError(f"{self.path.parent} is in use by {holder}: wait for that run to "
                                  f"finish, or give this one another out_dir") from None
        self.file.seek(0)
        self.file.truncate()
        self.file.write(f"process {os.getpid()} on {socket.gethostname()}")
        self.file.flush()
        return self

    def __exit__(self, *exc) -> None:
        self.file.close()  # closing releases the lock


def _lock_file(f) -> None:
    """Take a non-blocking exclusive lock on an open file; OSError if another process holds it."""
    if os.name == "nt":  # pragma: no cover - Windows
        import msvcrt
        msvcrt.locking(f.fileno(), msvcrt.LK_NBLCK, 1)
    else:
        import fcntl
        fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)


def write_json(path: Path, obj) -> None:
    """Write a JSON file atomically: a uniquely named temporary file in the same directory,
    flushed to disk, then renamed over the target, so a reader (or a crash) never sees half."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}-", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(json.dumps(obj, indent=2))
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def save(run_dir: Path, model, tokenizer, state: dict) -> Path:
    """Write ``run_dir/checkpoint`` atomically (temporary directory, then renames)."""
    run_dir = Path(run_dir)
    final, tmp, old = run_dir / "checkpoint", run_dir / ".checkpoint-tmp", run_dir / ".checkpoint-old"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    model.save_pretrained(tmp)
    tokenizer.save_pretrained(tmp)
    torch.save(state, tmp / STATE_FILE)
    if final.exists():
        # the previous checkpoint stays on disk until the new one is in place; if a crash left
        # only .checkpoint-old, it is kept too (it is the one being resumed from)
        shutil.rmtree(old, ignore_errors=True)
        os.replace(final, old)
    os.replace(tmp, final)
    shutil.rmtree(old, ignore_errors=True)
    return final


def find(run_dir: Path) -> Path | None:
    """The newest complete checkpoint in ``run_dir`` (also after a crash between the renames)."""
    for name in ("checkpoint", ".checkpoint-old"):
        path = Path(run_dir) / name
        if (path / STATE_FILE).exists():
            return path
    return None


def load_state(path: Path, config: dict) -> dict:
    """Trainer state from a checkpoint, refusing one written by an incompatible config."""
    state = torch.load(Path(path) / STATE_FILE, weights_only=True)
    # A setting added to Config after the checkpoint was written was at its default then.
    defaults = Config().to_dict()
    saved = {**{k: v for k, v in defaults.items() if k in config}, **state.get("config", {})}
    different = sorted(k for k in set(saved) | set(config)
                       if k not in RESUMABLE_CHANGES and saved.get(k) != config.get(k))
    if different:
        details = ", ".join(f"{k}: checkpoint {saved.get(k)!r} vs now {config.get(k)!r}"
                            for k in different)
        raise CheckpointError(f"the checkpoint in {path} was written by a different config "
                              f"({details}). Resume with the same settings, or start a new run "
                              f"in another out_dir.")
    return state


class MetricsLog:
    """One JSON object per line, flushed and fsynced per record so a crash loses at most the
    line being written. On resume, records after the checkpoint's step are dropped, so the log
    has no duplicated or missing steps."""

    def __init__(self, path: Path):
        self.path = Path(path)

    def truncate_after(self, step: int) -> None:
        if not self.path.exists():
            return
        kept = [r for r in self.read() if r.get("step", 0) <= step]
        fd, tmp = tempfile.mkstemp(dir=self.path.parent, prefix=f".{self.path.name}-", suffix=".tmp")
        with os.fdopen(fd, "w") as f:
            f.write("".join(json.dumps(r) + "\n" for r in kept))
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, self.path)

    def append(self, record: dict) -> None:
        with open(self.path, "a") as f:
            f.write(json.dumps(record) + "\n")
            f.flush()
            os.fsync(f.fileno())

    def read(self) -> list[dict]:
        """Every record. Only the *last* line may be unreadable (a crash cut it while it was
        being written); an unreadable line before another one means the file was damaged, and
        reading on, or resuming over it, would silently drop every later step."""
        if not self.path.exists():
            return []
        lines = self.path.read_text().splitlines()
        records = []
        for number, line in enumerate(lines, 1):
            try:
                records.append(json.loads(line))
            except json.JSONDecodeError:
                if number == len(lines):
                    break  # the torn last line of a crash: everything before it is intact
                raise CheckpointError(
                    f"{self.path}, line {number} of {len(lines)}, is not a JSON record, and later "
                    f"lines follow it: the log was damaged. Repair or delete that line, or start "
                    f"a new run in another out_dir.") from None
        return records
