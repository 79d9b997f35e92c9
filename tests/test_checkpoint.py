"""Checkpoints: a crash between the two renames of a save leaves a usable checkpoint."""
import json
import shutil

import pytest
import torch

from course_utils import checkpoint


class _Saveable:
    def __init__(self, tag):
        self.tag = tag

    def save_pretrained(self, path):
        (path / "weights.json").write_text(json.dumps(self.tag))


def _step(run_dir):
    return checkpoint.load_state(checkpoint.find(run_dir), {})["step"]


def test_a_crash_between_renames_keeps_a_checkpoint_and_the_next_save_recovers(tmp_path):
    checkpoint.save(tmp_path, _Saveable(1), _Saveable("tok"), {"step": 1})
    checkpoint.save(tmp_path, _Saveable(2), _Saveable("tok"), {"step": 2})
    assert checkpoint.find(tmp_path) == tmp_path / "checkpoint" and _step(tmp_path) == 2
    assert checkpoint.load_state(tmp_path / "checkpoint-previous", {})["step"] == 1
    # the crash: the current checkpoint was moved aside, the new one never arrived
    shutil.rmtree(tmp_path / "checkpoint-previous")
    (tmp_path / "checkpoint").rename(tmp_path / "checkpoint-previous")
    assert checkpoint.find(tmp_path) == tmp_path / "checkpoint-previous" and _step(tmp_path) == 2
    # resuming from it, a second crash just before the new checkpoint's rename must still leave
    # a checkpoint behind
    real_replace = checkpoint.os.replace

    def crash_on_final_rename(src, dst):
        if str(dst).endswith("/checkpoint"):
            raise KeyboardInterrupt("killed")
        real_replace(src, dst)

    checkpoint.os.replace = crash_on_final_rename
    try:
        checkpoint.save(tmp_path, _Saveable(3), _Saveable("tok"), {"step": 3})
    except KeyboardInterrupt:
        pass
    finally:
        checkpoint.os.replace = real_replace
    assert _step(tmp_path) == 2
    assert [p.name for p in tmp_path.glob(".checkpoint-tmp-*")]   # the killed save's leftover
    # and the next save succeeds, keeps the one before, and cleans up
    checkpoint.save(tmp_path, _Saveable(3), _Saveable("tok"), {"step": 3})
    assert _step(tmp_path) == 3
    assert checkpoint.load_state(tmp_path / "checkpoint-previous", {})["step"] == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint", "checkpoint-previous"]


def test_a_checkpoint_without_a_manifest_is_never_trusted(tmp_path):
    # the manifest is written last, so without one the write did not finish (issue 26, 1)
    legacy = tmp_path / ".checkpoint-old"
    legacy.mkdir()
    torch.save({"step": 5}, legacy / checkpoint.STATE_FILE)
    with pytest.raises(checkpoint.CheckpointError, match="manifest.json is missing"):
        checkpoint.find(tmp_path)
    assert (tmp_path / "checkpoint-old-damaged").is_dir()


def test_metrics_log_drops_steps_after_the_checkpoint_and_a_torn_last_line(tmp_path):
    log = checkpoint.MetricsLog(tmp_path / "m.jsonl")
    for step in (1, 2, 3):
        log.append({"step": step})
    with open(log.path, "a") as f:
        f.write('{"step": 4, "rew')  # a line cut by a crash
    assert [r["step"] for r in log.read()] == [1, 2, 3]
    log.truncate_after(2)
    assert [r["step"] for r in log.read()] == [1, 2]


def test_a_checkpoint_from_before_a_new_setting_resumes_at_that_settings_default(tmp_path):
    """Config gained `device` after runs existed; their checkpoints must still resume."""
    from course_utils.config import load_config
    config = load_config("smoke").to_dict()
    old = {k: v for k, v in config.items() if k != "device"}
    (tmp_path / checkpoint.STATE_FILE).parent.mkdir(parents=True, exist_ok=True)
    torch.save({"config": old}, tmp_path / checkpoint.STATE_FILE)
    assert checkpoint.load_state(tmp_path, config)["config"] == old
    with pytest.raises(checkpoint.CheckpointError, match="device: checkpoint 'auto' vs now 'cpu'"):
        checkpoint.load_state(tmp_path, {**config, "device": "cpu"})


# --- issue 14, findings 3 and 11: a damaged log is refused, JSON files are written atomically ---

def test_only_a_torn_last_line_of_the_metrics_log_is_tolerated(tmp_path):
    log = checkpoint.MetricsLog(tmp_path / "metrics.jsonl")
    for step in (1, 2, 3):
        log.append({"step": step})
    with open(log.path, "a") as f:
        f.write('{"step": 4, "rew')                     # a crash mid-write
    assert [r["step"] for r in log.read()] == [1, 2, 3]
    lines = log.path.read_text().splitlines()
    lines[1] = "garbage"                                 # damage in the middle
    log.path.write_text("\n".join(lines[:3]) + "\n")
    with pytest.raises(checkpoint.CheckpointError, match="line 2 of 3.*damaged"):
        log.read()


def test_json_files_are_replaced_whole_or_not_at_all(tmp_path, monkeypatch):
    path = tmp_path / "summary.json"
    checkpoint.write_json(path, {"before": 1})
    assert json.loads(path.read_text()) == {"before": 1}

    def torn(*args, **kwargs):
        raise OSError("disk full")
    monkeypatch.setattr(checkpoint.os, "fsync", torn)
    with pytest.raises(OSError):
        checkpoint.write_json(path, {"before": 1, "after": 2})
    assert json.loads(path.read_text()) == {"before": 1}     # the old file, whole
    assert [p.name for p in tmp_path.iterdir()] == ["summary.json"]  # no temporary left behind
