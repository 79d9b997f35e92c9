"""Nothing lost, round two (issue 26): each numbered finding of the second break-it session,
reproduced. Every test here failed before its fix. Runs use the smoke preset (a random tiny
model), so the file costs well under a minute."""
import json
import os
import shutil
import stat
import sys

import numpy as np
import pytest
import torch

from course_utils import checkpoint, interrupt, models, rewards, train
from course_utils.config import load_config


def _cfg(out, **overrides):
    return load_config("smoke", out_dir=str(out), **{"max_steps": 3, "save_every": 1, **overrides})


def _main(out, *args):
    return train.main(["--preset", "smoke", "--out_dir", str(out), "--max_steps", "3",
                       "--save_every", "1", "--no-progress", *args])


def _one_line_error(exc_info) -> str:
    message = str(exc_info.value.code if isinstance(exc_info.value, SystemExit) else exc_info.value)
    assert "\n" not in message, message
    return message


# --- 1: a checkpoint without its manifest is damaged, never "legacy" ---

@pytest.mark.parametrize("damage", ["weights", "state"])
def test_a_checkpoint_without_a_manifest_is_set_aside_and_the_previous_one_resumed(
        copy_run, tmp_path, damage, capsys):
    run = copy_run()
    newest = run / "checkpoint"
    (newest / checkpoint.MANIFEST).unlink()
    target = newest / ("model.safetensors" if damage == "weights" else checkpoint.STATE_FILE)
    target.write_bytes(target.read_bytes()[:100])   # and its files garbled
    found = checkpoint.find(run)
    assert found == run / "checkpoint-previous"
    assert (run / "checkpoint-damaged").is_dir()    # kept for inspection, never rotated out
    assert "manifest.json is missing" in capsys.readouterr().out


def test_a_finished_run_whose_only_checkpoint_lost_its_manifest_is_not_called_finished(
        copy_run, tmp_path):
    run = copy_run()
    shutil.rmtree(run / "checkpoint-previous")
    (run / "checkpoint" / checkpoint.MANIFEST).unlink()
    with pytest.raises(checkpoint.CheckpointError, match="no whole checkpoint is left"):
        train.train(_cfg(run), resume=True, progress=False)


# --- 2: the report and the curves are derived files, regenerated when missing ---

@pytest.mark.parametrize("missing", [["report.md"], ["curves.png"], ["report.md", "curves.png"]])
def test_resuming_a_finished_run_rewrites_a_missing_report_and_curves(copy_run, tmp_path,
                                                                        missing):
    run = copy_run()
    report = (run / "report.md").read_text()
    for name in missing:
        (run / name).unlink()
    train.train(_cfg(run), resume=True, progress=False)
    assert all((run / name).exists() for name in checkpoint.RUN_FILES)
    assert (run / "report.md").read_text() == report


# --- 3: damaged JSON files are one line naming the file ---

@pytest.mark.parametrize("name, content", [
    ("summary.json", ""), ("summary.json", '{"before": {"samp'), ("summary.json", "\x00\x01garbage"),
    ("summary.json", "[1, 2]"), ("config.json", ""), ("config.json", "null"),
    ("metrics.jsonl", None)])
def test_damaged_run_files_give_a_one_line_error_naming_the_file(copy_run, tmp_path, name,
                                                                   content):
    run = copy_run()
    if content is None:   # a null last line: JSON, but not a record
        with open(run / name, "a") as f:
            f.write("null\n")
    else:
        (run / name).write_text(content)
    if name == "config.json":   # read only when no checkpoint is left
        for d in ("checkpoint", "checkpoint-previous"):
            shutil.rmtree(run / d)
    with pytest.raises(SystemExit) as exc:
        _main(run, "--resume")
    message = _one_line_error(exc)
    assert message.startswith("error: ") and name in message, message


# --- 4: file-system errors are one line naming the path and the cause ---

def test_an_out_dir_that_is_a_file_or_under_a_file_is_one_line(tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("mine")
    for out, cause in ((afile, "not a folder"), (afile / "run", "is a file, not a folder")):
        with pytest.raises(SystemExit) as exc:
            _main(out)
        message = _one_line_error(exc)
        assert message.startswith("error: ") and cause in message and str(afile) in message, message
    assert afile.read_text() == "mine"


@pytest.mark.skipif(os.name == "nt" or (hasattr(os, "geteuid") and os.geteuid() == 0),
                    reason="root ignores folder permissions")
def test_an_unwritable_folder_and_a_read_only_finished_run_are_one_line(copy_run, tmp_path):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(stat.S_IRUSR | stat.S_IXUSR)
    run = copy_run()
    (run / ".lock").unlink(missing_ok=True)
    run.chmod(stat.S_IRUSR | stat.S_IXUSR)
    try:
        for out, extra in ((locked / "run", []), (run, ["--resume"])):
            with pytest.raises(SystemExit) as exc:
                _main(out, *extra)
            message = _one_line_error(exc)
            assert "permission denied" in message and str(out) in message, message
    finally:
        locked.chmod(stat.S_IRWXU)
        run.chmod(stat.S_IRWXU)


@pytest.mark.parametrize("error", [PermissionError(13, "Permission denied"),
                                   OSError(30, "Read-only file system"),
                                   OSError(28, "No space left on device")])
def test_file_system_refusals_are_one_line_for_root_too(tmp_path, monkeypatch, error):
    # root (CI's user) ignores folder permissions, so the refusal is injected where it happens
    def refuse(self):
        error.filename = str(self.path)
        raise error
    monkeypatch.setattr(checkpoint.RunLock, "__enter__", refuse)
    with pytest.raises(SystemExit) as exc:
        _main(tmp_path / "run")
    message = _one_line_error(exc)
    assert message.startswith("error: cannot write the run") and str(tmp_path / "run") in message
    assert checkpoint.FILESYSTEM_CAUSES[error.errno] in message


def test_a_full_disk_during_a_checkpoint_says_so_and_keeps_the_last_one(tmp_path, monkeypatch):
    class Full:
        def save_pretrained(self, path):
            raise RuntimeError("[enforce fail at inline_container.cc:603] . unexpected pos 64")
    (tmp_path / "checkpoint").mkdir()
    monkeypatch.setattr(checkpoint, "_free_bytes", lambda path: 3 * 2**20)
    with pytest.raises(checkpoint.CheckpointError, match="no space left on the device.*--resume"):
        checkpoint.save(tmp_path, Full(), Full(), {"step": 4})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint"]   # no half-written copy
    monkeypatch.setattr(checkpoint, "_free_bytes", lambda path: 2**40)   # plenty of space:
    with pytest.raises(RuntimeError, match="inline_container"):        # the error is not hidden
        checkpoint.save(tmp_path, Full(), Full(), {"step": 4})


def test_an_io_error_in_the_run_directory_is_one_line_too(tmp_path):
    err = OSError(5, "Input/output error", str(tmp_path / "run" / "metrics.jsonl"))
    assert "check the disk or the mounted drive" in str(checkpoint.filesystem_error(err, tmp_path / "run"))


def test_a_stop_during_a_checkpoint_write_is_never_called_a_full_disk(tmp_path, monkeypatch):
    class Stopped:
        def save_pretrained(self, path):
            raise interrupt.Interrupted("stopped on SIGINT", 2)
    monkeypatch.setattr(checkpoint, "_free_bytes", lambda path: 3 * 2**20)
    with pytest.raises(interrupt.Interrupted):
        checkpoint.save(tmp_path, Stopped(), Stopped(), {"step": 4})
    assert list(tmp_path.iterdir()) == []


def test_an_os_error_elsewhere_is_not_blamed_on_the_run_directory(tmp_path):
    err = FileNotFoundError(2, "No such file or directory", "/somewhere/else/model.gguf")
    assert checkpoint.filesystem_error(err, tmp_path / "run") is None
    err = PermissionError(13, "Permission denied", str(tmp_path / "run" / "summary.json"))
    assert "permission denied" in str(checkpoint.filesystem_error(err, tmp_path / "run"))


# --- 5: bad model directories are refused before the lock, in one line ---

def _model_dir(tmp_path, config=None, weights=True, tokenizer=True):
    d = tmp_path / "model"
    d.mkdir()
    if config is not None:
        (d / "config.json").write_text(config)
    if weights:
        (d / "model.safetensors").write_bytes(b"x")
    if tokenizer:
        (d / "tokenizer.json").write_text("{}")
    return d


@pytest.mark.parametrize("kind, expected", [
    ("empty config", "names no model_type"), ("garbled config", "not readable JSON"),
    ("no weights", "no weights"), ("no tokenizer", "no tokenizer files"),
    ("run folder", "a training run's folder"), ("long name", "longer than a file system allows")])
def test_bad_model_directories_are_refused_before_anything_is_written(finished_run, tmp_path, kind,
                                                                        expected):
    if kind == "run folder":
        model = finished_run
    elif kind == "long name":
        model = str(tmp_path / ("m" * 300))
    else:
        model = _model_dir(tmp_path, config={"empty config": "{}", "garbled config": "{not json"}.get(
            kind, '{"model_type": "qwen2"}'), weights=kind != "no weights",
            tokenizer=kind != "no tokenizer")
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as exc:
        _main(out, "--model", str(model))
    message = _one_line_error(exc)
    assert message.startswith("error: model") and expected in message, message
    assert not out.exists()


# --- 6: an error after the lock writes nothing, so the corrected command just works ---

def test_a_refused_set_up_leaves_nothing_behind_and_the_corrected_command_runs(tmp_path,
                                                                                 monkeypatch):
    out = tmp_path / "run"
    real = train.data.make_prompts

    def offline(cfg, tokenizer, held_out):
        raise train.data.DataUnavailable("no openwebtext source could be reached (offline)")
    monkeypatch.setattr(train.data, "make_prompts", offline)
    with pytest.raises(SystemExit, match="openwebtext"):
        _main(out)
    assert checkpoint.run_contents(out) == []
    monkeypatch.setattr(train.data, "make_prompts", real)
    assert _main(out) == 0                       # without --overwrite
    assert (out / "report.md").exists()


def test_a_failed_overwrite_keeps_the_run_it_would_have_replaced(copy_run, tmp_path,
                                                                 monkeypatch):
    run = copy_run()
    before = sorted(checkpoint.run_contents(run))

    def offline(cfg, tokenizer, held_out):
        raise train.data.DataUnavailable("no openwebtext source could be reached (offline)")
    monkeypatch.setattr(train.data, "make_prompts", offline)
    with pytest.raises(SystemExit):
        _main(run, "--overwrite")
    assert sorted(checkpoint.run_contents(run)) == before


# --- 7: the printed resume command is rebuilt from the parsed options ---

def test_the_resume_command_survives_abbreviated_options():
    args = train.build_parser().parse_args(["--preset", "smoke", "--overwr", "--lr", "1e-3",
                                            "--out_d", "runs/x y", "--no-progress"])
    command = train.resume_command(args)
    assert "--overwr" not in command and "--overwrite" not in command
    assert command.endswith("--resume") and "--lr 1e-3" in command
    again = train.build_parser().parse_args(train.shlex.split(command)[3:])
    assert again.resume and not again.overwrite and again.out_dir == "runs/x y" and again.lr == "1e-3"


# --- 8: --resume on a folder with no run says so ---

def test_resume_with_nothing_to_resume_says_it_starts_a_new_run(tmp_path, capsys):
    summary = train.train(_cfg(tmp_path / "new"), resume=True, progress=False)
    assert "holds no run to resume: starting a new one" in capsys.readouterr().out
    assert not summary["resumed"]


# --- 9: the metrics log's steps must be consecutive ---

@pytest.mark.parametrize("steps, problem", [([1, 2, 2, 3], "repeated"), ([1, 3, 4], "missing"),
                                            ([2, 3], "missing")])
def test_a_log_with_a_repeated_or_missing_step_is_refused(tmp_path, steps, problem):
    log = checkpoint.MetricsLog(tmp_path / "metrics.jsonl")
    for s in steps:
        log.append({"step": s})
    with pytest.raises(checkpoint.CheckpointError, match=problem):
        log.read()


# --- 10: argparse errors are one line, and a negative number is read as a value ---

@pytest.mark.parametrize("args, says", [
    (["--learning_rate", "1e-3"], "unrecognized arguments: --learning_rate"),
    (["--max-steps", "3"], "did you mean --max_steps"), (["--foo"], "unrecognized"),
    (["stray"], "unrecognized arguments: stray"), (["--lr"], "expected one argument"),
    (["--e", "1"], "ambiguous option"), (["--lr", "-1e-3"], "lr=-0.001 is invalid"),
    (["--kl_coef", "-.5"], "kl_coef"), (["--seed", "٣"], "--seed"), (["--seed", "1_0"], "--seed"),
    (["--lr", "１e-3"], "--lr"), (["--dataset", "me/owt"], "dataset")])
def test_command_line_mistakes_are_one_line_before_anything_is_written(tmp_path, args, says):
    out = tmp_path / "run"
    with pytest.raises(SystemExit) as exc:
        _main(out, *args)
    message = _one_line_error(exc)
    assert message.startswith("error: ") and says in message, message
    assert not out.exists()


# --- 11: a stop before the first checkpoint does not claim one stands ---

def test_an_immediate_stop_says_whether_a_checkpoint_stands():
    stop = interrupt.StopRequests("run: again")
    with pytest.raises(interrupt.Interrupted, match="during set-up; nothing .* changed: run the same command"):
        stop._handle(interrupt.signal.SIGTERM, None)   # an --overwrite still in set-up
    stop.started = True
    with pytest.raises(interrupt.Interrupted, match="no checkpoint had been written yet"):
        stop._handle(interrupt.signal.SIGTERM, None)
    stop.checkpoint_step = 4
    with pytest.raises(interrupt.Interrupted, match="the checkpoint at step 4 stands"):
        stop._handle(interrupt.signal.SIGTERM, None)


# --- 12: rewards refuse inputs of the wrong shape instead of scoring them ---

KW = dict(target_chars=[5], target_digit_sum=[3])


@pytest.mark.parametrize("completions, kwargs, says", [
    ([[{"role": "assistant", "text": "ab12c"}]], KW, "'content' key"),
    ([{"role": "assistant", "text": "ab12c"}], KW, "'content' key"),
    ({"role": "assistant", "content": "ab12c"}, KW, "must be a list of completions"),
    ((c for c in ["ab12c"]), KW, "must be a list of completions"),
    (None, KW, "must be a list of completions"),
    (["ab12c"], dict(target_chars={5: 1}, target_digit_sum=[3]), "'target_chars' must be a list"),
    (["ab12c"], dict(target_chars=None, target_digit_sum=[3]), "'target_chars' must be a list"),
    (["ab12c"], dict(target_chars=(x for x in [5]), target_digit_sum=[3]), "must be a list")])
def test_rewards_refuse_inputs_of_the_wrong_shape(completions, kwargs, says):
    for fn in rewards.REWARDS.values():
        with pytest.raises(TypeError, match=says):
            fn(prompts=["p"], completions=completions, **kwargs)


@pytest.mark.parametrize("targets", [dict(target_chars=np.array(5), target_digit_sum=torch.tensor(3)),
                                     dict(target_chars=np.array([5]), target_digit_sum=torch.tensor([3])),
                                     dict(target_chars=[np.int64(5)], target_digit_sum=(3,))])
def test_rewards_read_numpy_and_torch_targets_as_numbers(targets):
    assert rewards.binary_reward(prompts=["p"], completions=["ab12c"], **targets) == [1.0]
    assert rewards.binary_reward(prompts=["p"], completions=[[{"role": "assistant",
                                                                "content": None}]], **targets) == [0.0]


def test_no_progress_also_silences_transformers_bars(finished_run, tmp_path, capsys):
    from transformers.utils import logging as transformers_logging

    transformers_logging.enable_progress_bar()
    try:
        _main(tmp_path / "quiet")
        assert not transformers_logging.is_progress_bar_enabled()
        assert "Loading weights" not in capsys.readouterr().err
    finally:
        transformers_logging.enable_progress_bar()
