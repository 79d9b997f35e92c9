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
from pathlib import Path

import torch

from .config import Config

STATE_FILE = "trainer_state.pt"
# Fields that may change when a run is resumed; any other difference means a different run.
RESUMABLE_CHANGES = {"out_dir", "max_steps", "epochs", "eval_every", "save_every", "eval_prompts"}


class CheckpointError(RuntimeError):
    """A checkpoint cannot be used for this run; the message says why."""


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
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text("".join(json.dumps(r) + "\n" for r in kept))
        os.replace(tmp, self.path)

    def append(self, record: dict) -> None:
        with open(self.path, "a") as f:
            f.write(json.dumps(record) + "\n")
            f.flush()
            os.fsync(f.fileno())

    def read(self) -> list[dict]:
        if not self.path.exists():
            return []
        records = []
        for line in self.path.read_text().splitlines():
            try:
                records.append(json.loads(line))
            except json.JSONDecodeError:
                break  # a line cut by a crash: everything before it is intact
        return records
