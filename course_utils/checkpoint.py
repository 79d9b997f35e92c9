"""Checkpoints that survive a crash, and the append-only metrics log.

A checkpoint is a directory: the model (``save_pretrained``, safetensors), the tokenizer,
``trainer_state.pt`` (optimizer, scheduler, step, random-generator states, config) and a
manifest of every file's SHA-256, written last. It is written to a temporary directory and then
renamed into place, so a crash mid-write leaves the previous checkpoint whole; the previous one
is kept, and a checkpoint whose files do not match its manifest is never resumed. State is read back with ``torch.load(weights_only=True)``: loading
a checkpoint never runs code from the file.
"""

from __future__ import annotations

import errno
import hashlib
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


# What an OSError on the run directory means for the learner, by errno.
FILESYSTEM_CAUSES = {
    errno.ENOSPC: "no space left on the device: free some space (old runs, checkpoints), then "
                  "continue with --resume",
    errno.EDQUOT: "the disk quota is used up: free some space, then continue with --resume",
    errno.EACCES: "permission denied: choose an out_dir you can write to",
    errno.EPERM: "the operation is not permitted there (a protected or immutable folder): choose "
                 "another out_dir",
    errno.EROFS: "the file system is read-only: choose an out_dir on a writable disk",
    errno.ENOTDIR: "a part of the path is a file, not a folder: choose another out_dir",
    errno.EEXIST: "it exists and is not a folder: choose another out_dir",
    errno.EISDIR: "a folder is in the way of a file the run writes: move it, or choose another "
                  "out_dir",
    errno.ENAMETOOLONG: "a name in the path is too long for the file system: choose a shorter "
                        "out_dir",
    errno.ENOENT: "a folder on the path does not exist and cannot be created there: choose "
                  "another out_dir",
}


def filesystem_error(err: OSError, run_dir: Path) -> "CheckpointError | None":
    """A one-line CheckpointError for a file-system failure on the run directory (its path and
    its cause), or None for an OSError of another kind, which is left to propagate."""
    cause = FILESYSTEM_CAUSES.get(err.errno)
    run_dir = Path(run_dir).absolute()
    if err.filename is not None:   # only the run directory, a file in it or a folder above it
        target = Path(os.fsdecode(err.filename)).absolute()
        if not (target == run_dir or run_dir in target.parents or target in run_dir.parents):
            return None
        # an I/O error, a lost network or Drive mount, ...: the file and what the system said
        cause = cause or ("check the disk or the mounted drive it is on, then continue with "
                          "--resume")
    elif err.errno not in (errno.ENOSPC, errno.EDQUOT):
        return None
    path = err.filename or run_dir
    return CheckpointError(f"cannot write the run in {run_dir} ({path}: {err.strerror or err}); "
                           f"{cause}")


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
    """Write a JSON file atomically (see ``write_text``)."""
    write_text(path, json.dumps(obj, indent=2))


def write_text(path: Path, text: str) -> None:
    """Write a text file atomically: a uniquely named temporary file in the same directory,
    flushed to disk, then renamed over the target, so a reader (or a crash) never sees half."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}-", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


MANIFEST = "manifest.json"
CURRENT, PREVIOUS = "checkpoint", "checkpoint-previous"
TMP_PREFIX = ".checkpoint-tmp-"
LEGACY = ".checkpoint-old"   # an older layout's moved-aside checkpoint: verified like the others


def read_json(path: Path, fix: str):
    """A run file's JSON, or a one-line CheckpointError naming the file and ``fix`` when it is
    unreadable, empty, truncated or not a JSON object (a crash, a full disk, a bad copy)."""
    path = Path(path)
    try:
        value = json.loads(path.read_text())
    except OSError as err:
        raise CheckpointError(f"{path} cannot be read ({err.strerror or err}): {fix}") from None
    except (ValueError, UnicodeDecodeError):
        raise CheckpointError(f"{path} is damaged (not valid JSON, or empty): {fix}") from None
    if not isinstance(value, dict):
        raise CheckpointError(f"{path} is damaged (it holds a {type(value).__name__}, not a JSON "
                              f"object): {fix}")
    return value


def damaged_name(name: str) -> str:
    """Where ``find`` moves a checkpoint directory whose files do not match its manifest."""
    return name.lstrip(".") + "-damaged"


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 24), b""):
            digest.update(block)
    return digest.hexdigest()


def _write_manifest(path: Path, step: int) -> None:
    """Every file's size and SHA-256, written *last*: a checkpoint whose manifest exists was
    written whole, and a byte changed later (a bad disk, a half-copied Drive folder) shows up
    as a mismatch. Hashing reads about 1.5 GB/s, a second per save of the cpu preset."""
    files = {str(f.relative_to(path)): {"bytes": f.stat().st_size, "sha256": _sha256(f)}
             for f in sorted(path.rglob("*")) if f.is_file()}
    write_json(path / MANIFEST, {"step": step, "files": files})


def verify(path: Path) -> str | None:
    """What is wrong with the checkpoint in ``path``, or None if every file matches its manifest."""
    path = Path(path)
    try:
        manifest = json.loads((path / MANIFEST).read_text())
        files = manifest["files"]
    except (OSError, ValueError, KeyError, TypeError):
        return f"its {MANIFEST} is missing or unreadable"
    for name, expected in files.items():
        f = path / name
        if not f.is_file():
            return f"{name} is missing"
        if f.stat().st_size != expected["bytes"] or _sha256(f) != expected["sha256"]:
            return f"{name} does not match its SHA-256 in {MANIFEST}"
    return None


def save(run_dir: Path, model, tokenizer, state: dict) -> Path:
    """Write ``run_dir/checkpoint`` and keep the one before it as ``checkpoint-previous``.

    The new checkpoint is written to a uniquely named temporary directory, its manifest last,
    and only then renamed into place; the current one is renamed to ``checkpoint-previous``
    first. A crash at any moment leaves at least one whole checkpoint (``find`` picks it)."""
    run_dir = Path(run_dir)
    remove_leftovers(run_dir)
    tmp = Path(tempfile.mkdtemp(dir=run_dir, prefix=TMP_PREFIX))
    try:
        model.save_pretrained(tmp)
        tokenizer.save_pretrained(tmp)
        torch.save(state, tmp / STATE_FILE)
        _write_manifest(tmp, state.get("step", 0))
    except BaseException as err:
        shutil.rmtree(tmp, ignore_errors=True)
        if not isinstance(err, (OSError, RuntimeError)) and type(err).__name__ != "SafetensorError":
            raise   # a stop request, a bug: never relabelled as a full disk
        # safetensors and torch.save report a full disk in their own words ("inline_container",
        # "I/O error") that never mention space: say what it was, once the half-written copy
        # is gone and the previous checkpoint is known to be whole
        if isinstance(err, OSError) and err.errno in (errno.ENOSPC, errno.EDQUOT) or \
                _free_bytes(run_dir) < LOW_SPACE_BYTES:
            raise CheckpointError(
                f"writing the checkpoint in {run_dir} failed: no space left on the device "
                f"({_free_bytes(run_dir) // 2**20} MiB free; {type(err).__name__}: "
                f"{str(err).strip().splitlines()[0][:100] if str(err).strip() else ''}). The last "
                f"checkpoint is whole: free some space, then continue with --resume") from None
        raise
    final, previous = run_dir / CURRENT, run_dir / PREVIOUS
    if final.exists():
        # a crash between these renames leaves checkpoint-previous (or the current checkpoint)
        # whole; the new one is never half in place
        shutil.rmtree(previous, ignore_errors=True)
        os.replace(final, previous)
    os.replace(tmp, final)
    shutil.rmtree(run_dir / LEGACY, ignore_errors=True)
    return final


# Below this much free space a failed checkpoint write is reported as a full disk.
LOW_SPACE_BYTES = 64 * 2**20


def _free_bytes(path: Path) -> int:
    try:
        return shutil.disk_usage(path).free
    except OSError:
        return 2**62   # unknown: do not claim the disk is full


def remove_leftovers(run_dir: Path) -> None:
    """Delete what a killed process left half-written: temporary checkpoint directories and
    temporary JSON files. Only called with the run directory's lock held, so none of them can
    belong to a live process."""
    for path in Path(run_dir).glob(TMP_PREFIX + "*"):
        shutil.rmtree(path, ignore_errors=True)
    for path in Path(run_dir).glob(".*.tmp"):
        path.unlink(missing_ok=True)


def find(run_dir: Path) -> Path | None:
    """The newest whole checkpoint in ``run_dir``, verified against its manifest; None if the run
    never wrote one. A damaged checkpoint is moved aside (``checkpoint`` to ``checkpoint-damaged``:
    kept for inspection, never resumed or rotated again) and the previous one is used, with a
    message; if every checkpoint is damaged, CheckpointError."""
    run_dir = Path(run_dir)
    problems = []
    for name in (CURRENT, PREVIOUS, LEGACY):
        path = run_dir / name
        if not path.is_dir():
            continue
        # no manifest means the write never finished (it is written last), or the folder was
        # copied in part: damaged, never trusted unchecked
        problem = verify(path)
        if problem is None:
            if problems:
                print(f"[course_utils] {'; '.join(problems)}: resuming from {path} instead")
            return path
        damaged = run_dir / damaged_name(name)
        shutil.rmtree(damaged, ignore_errors=True)
        os.replace(path, damaged)
        problems.append(f"the checkpoint in {path} is damaged ({problem}; moved to {damaged.name})")
    if problems:
        raise CheckpointError(f"{'; '.join(problems)}, and no whole checkpoint is left: start the "
                              f"run again with --overwrite, or in another out_dir")
    return None


def config_differences(saved: dict, config: dict) -> str:
    """The settings in which ``config`` differs from ``saved`` (a run's stored config), other
    than those a resume may change, as "name: checkpoint X vs now Y, ..."; empty if none."""
    # A setting added to Config after the run was written was at its default then.
    defaults = Config().to_dict()
    saved = {**{k: v for k, v in defaults.items() if k in config}, **saved}
    different = sorted(k for k in set(saved) | set(config)
                       if k not in RESUMABLE_CHANGES and saved.get(k) != config.get(k))
    return ", ".join(f"{k}: checkpoint {saved.get(k)!r} vs now {config.get(k)!r}" for k in different)


def load_state(path: Path, config: dict) -> dict:
    """Trainer state from a checkpoint, refusing one written by an incompatible config."""
    state = torch.load(Path(path) / STATE_FILE, weights_only=True)
    different = config_differences(state.get("config", {}), config)
    if different:
        raise CheckpointError(f"the checkpoint in {path} was written by a different config "
                              f"({different}). Resume with the same settings, or start a new run "
                              f"in another out_dir.")
    return state


# What a run writes into its directory (besides the lock file): --overwrite removes exactly these.
RUN_FILES = ("config.json", "metrics.jsonl", "summary.json", "report.md", "curves.png")
CHECKPOINT_DIRS = (CURRENT, PREVIOUS, LEGACY) + tuple(damaged_name(n)
                                                      for n in (CURRENT, PREVIOUS, LEGACY))


def run_contents(run_dir: Path) -> list[str]:
    """The names of a run's files and checkpoints present in ``run_dir``."""
    return [n for n in RUN_FILES + CHECKPOINT_DIRS if (Path(run_dir) / n).exists()]


def clear(run_dir: Path) -> None:
    """Remove a run's files and checkpoints (and nothing else) so a new run can start there."""
    for name in run_contents(run_dir):
        path = Path(run_dir) / name
        shutil.rmtree(path) if path.is_dir() else path.unlink()
    remove_leftovers(run_dir)


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
        lines = self.path.read_text(errors="replace").splitlines()
        records = []
        for number, line in enumerate(lines, 1):
            try:
                record = json.loads(line)
            except json.JSONDecodeError:
                if number == len(lines):
                    break  # the torn last line of a crash: everything before it is intact
                raise CheckpointError(
                    f"{self.path}, line {number} of {len(lines)}, is not a JSON record, and later "
                    f"lines follow it: the log was damaged. Repair or delete that line, or start "
                    f"a new run in another out_dir.") from None
            step = record.get("step") if isinstance(record, dict) else None
            if not isinstance(step, int) or isinstance(step, bool):
                # JSON, but not a record (``null``, a list, no step): not a crash's torn line
                raise CheckpointError(
                    f"{self.path}, line {number} of {len(lines)}, is not a step record (a JSON "
                    f"object with an integer 'step'): the log was damaged. Repair or delete that "
                    f"line, or start a new run in another out_dir.")
            expected = records[-1]["step"] + 1 if records else 1
            if step != expected:
                # a duplicated or missing step would plot and average as if it were real
                raise CheckpointError(
                    f"{self.path}, line {number}, holds step {step} where step {expected} should "
                    f"follow: the log has {'a repeated' if step < expected else 'a missing'} step "
                    f"and was damaged or mixed with another run's. Repair it, or start a new run "
                    f"in another out_dir.")
            records.append(record)
        return records
