"""A run directory defends what is in it (issue 14, findings 2 and 4): a fresh run does not
overwrite an earlier one without being told to, a resume refuses a directory whose pieces do not
belong together instead of starting it over, and a damaged checkpoint is never resumed: the one
before it is used, with a message."""
import json
import shutil

import pytest
import torch
from safetensors.torch import load_file

from course_utils import checkpoint, train
from course_utils.config import ConfigError, load_config


def _cfg(out, **overrides):
    return load_config("smoke", out_dir=str(out), **{"max_steps": 3, "save_every": 1, **overrides})


def _snapshot(run_dir):
    """Every file's bytes, to show a refused call changed nothing."""
    return {str(p.relative_to(run_dir)): p.read_bytes() for p in sorted(run_dir.rglob("*"))
            if p.is_file() and p.name != ".lock"}


# --- finding 2: earlier runs are not overwritten silently ---

def test_a_fresh_run_refuses_a_directory_that_holds_a_run(copy_run, tmp_path):
    run = copy_run()
    before = _snapshot(run)
    with pytest.raises(checkpoint.CheckpointError, match="already holds a run.*--resume.*--overwrite"):
        train.train(_cfg(run), progress=False)
    with pytest.raises(SystemExit, match="^error: .*already holds a run"):
        train.main(["--preset", "smoke", "--out_dir", str(run), "--max_steps", "3", "--no-progress"])
    assert _snapshot(run) == before


def test_overwrite_replaces_the_run_and_contradicts_resume(copy_run, tmp_path):
    run = copy_run()
    (run / "notes.txt").write_text("mine")          # not a run file: overwrite leaves it alone
    with pytest.raises(ConfigError, match="resume and overwrite"):
        train.train(_cfg(run, seed=1), resume=True, overwrite=True, progress=False)
    summary = train.train(_cfg(run, seed=1), overwrite=True, progress=False)
    assert not summary["resumed"] and (run / "notes.txt").read_text() == "mine"
    assert json.loads((run / "config.json").read_text())["seed"] == 1
    assert [r["step"] for r in checkpoint.MetricsLog(run / "metrics.jsonl").read()] == [1, 2, 3]


def test_resuming_a_finished_run_changes_nothing(copy_run, tmp_path):
    run = copy_run()
    before = _snapshot(run)
    summary = train.train(_cfg(run), resume=True, progress=False)
    assert summary == json.loads((run / "summary.json").read_text())
    assert _snapshot(run) == before


def _without_checkpoints(run):
    for name in (checkpoint.CURRENT, checkpoint.PREVIOUS):
        shutil.rmtree(run / name)


@pytest.mark.parametrize("damage, reason", [
    ("checkpoints deleted", "it is a finished run"),
    ("checkpoints deleted, unfinished", "metrics reach step 3, past the first checkpoint at step 1"),
    ("another config", "another run's .*seed"),
])
def test_resume_without_a_checkpoint_refuses_a_run_it_would_overwrite(copy_run, tmp_path,
                                                                      damage, reason):
    run = copy_run()
    _without_checkpoints(run)
    cfg = _cfg(run)
    if damage == "checkpoints deleted, unfinished":
        summary = json.loads((run / "summary.json").read_text())
        checkpoint.write_json(run / "summary.json", {"before": summary["before"]})
    if damage == "another config":
        cfg = _cfg(run, seed=7)
    before = _snapshot(run)
    with pytest.raises(checkpoint.CheckpointError, match=f"no checkpoint to resume from.*{reason}"):
        train.train(cfg, resume=True, progress=False)
    assert _snapshot(run) == before


def test_resume_restarts_a_run_that_stopped_before_its_first_checkpoint(finished_run, copy_run, tmp_path):
    run = copy_run()
    _without_checkpoints(run)
    summary = json.loads((run / "summary.json").read_text())
    checkpoint.write_json(run / "summary.json", {"before": summary["before"]})
    # killed after step 1 was logged and before its checkpoint was written (the first save is at
    # step 1): the log may hold the step of the first checkpoint (a 20-kill sweep found this)
    checkpoint.MetricsLog(run / "metrics.jsonl").truncate_after(1)
    train.train(_cfg(run), resume=True, progress=False)
    a = load_file(str(finished_run / "checkpoint" / "model.safetensors"))
    b = load_file(str(run / "checkpoint" / "model.safetensors"))
    assert all(torch.equal(a[k], b[k]) for k in a)


@pytest.mark.parametrize("damage, message", [
    ("summary.json", "no before-training evaluation"),
    ("metrics.jsonl", "ends at step 1 but the checkpoint is at step 3"),
])
def test_resume_refuses_a_checkpoint_without_its_log_or_summary(copy_run, tmp_path, damage,
                                                                message):
    run = copy_run()
    if damage == "summary.json":
        (run / "summary.json").unlink()
    else:
        checkpoint.MetricsLog(run / "metrics.jsonl").truncate_after(1)
    before = _snapshot(run)
    with pytest.raises(checkpoint.CheckpointError, match=message):
        train.train(_cfg(run), resume=True, progress=False)
    assert _snapshot(run) == before


# --- finding 4: checkpoint contents are verified, and the previous one is kept ---

def _garble(path, at=4096, size=4096):
    data = bytearray(path.read_bytes())
    at = min(at, len(data) - size)
    data[at:at + size] = bytes(255 - b for b in data[at:at + size])
    path.write_bytes(bytes(data))


def test_the_previous_checkpoint_is_kept_with_a_manifest(finished_run):
    for name, step in ((checkpoint.CURRENT, 3), (checkpoint.PREVIOUS, 2)):
        manifest = json.loads((finished_run / name / checkpoint.MANIFEST).read_text())
        assert manifest["step"] == step and "model.safetensors" in manifest["files"]
        assert checkpoint.verify(finished_run / name) is None


@pytest.mark.parametrize("garbled", ["model.safetensors", checkpoint.STATE_FILE])
def test_a_damaged_checkpoint_is_set_aside_and_the_previous_one_resumed(finished_run, copy_run, tmp_path,
                                                                        capsys, garbled):
    run = copy_run()
    _garble(run / "checkpoint" / garbled)
    assert garbled in checkpoint.verify(run / "checkpoint")
    train.train(_cfg(run), resume=True, progress=False)
    out = capsys.readouterr().out
    assert f"{garbled} does not match its SHA-256" in out and "resuming from" in out
    assert "resumed from" in out and "at step 2" in out
    assert (run / "checkpoint-damaged" / garbled).exists()             # kept for inspection
    # step 3 redone from the previous checkpoint: the same model, no step lost or doubled
    a = load_file(str(finished_run / "checkpoint" / "model.safetensors"))
    b = load_file(str(run / "checkpoint" / "model.safetensors"))
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert [r["step"] for r in checkpoint.MetricsLog(run / "metrics.jsonl").read()] == [1, 2, 3]


def test_when_every_checkpoint_is_damaged_resume_refuses(copy_run, tmp_path):
    run = copy_run()
    _garble(run / "checkpoint" / "model.safetensors")
    (run / "checkpoint-previous" / checkpoint.MANIFEST).write_text("{")
    with pytest.raises(checkpoint.CheckpointError, match="no whole checkpoint is left.*--overwrite"):
        train.train(_cfg(run), resume=True, progress=False)
    assert (run / "checkpoint-damaged").exists() and (run / "checkpoint-previous-damaged").exists()


# --- unique temporary names, and what a killed process left behind ---

def test_leftovers_of_a_killed_process_are_removed_under_the_lock(copy_run, tmp_path):
    run = copy_run()
    (run / ".checkpoint-tmp-dead").mkdir()
    (run / ".summary.json-dead.tmp").write_text("{")
    train.train(_cfg(run, max_steps=4), resume=True, progress=False)
    assert not [p.name for p in run.iterdir() if p.name.startswith(".") and p.name != ".lock"]


def test_memory_that_certainly_cannot_fit_is_refused_before_anything_is_written(tmp_path):
    out = tmp_path / "run"
    with pytest.raises(SystemExit, match=r"^error: group_size 1024 x prompts_per_step 512.*GiB"):
        train.main(["--preset", "smoke", "--out_dir", str(out), "--group_size", "1024",
                    "--prompts_per_step", "512"])
    assert not out.exists()
