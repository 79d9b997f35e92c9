"""Bad input gets a one-line error naming the field, before a model loads and before anything
is written (issue 14: findings 5 to 8). Each case runs the command line in-process, so fifty
cases cost seconds; two run as real subprocesses to show no traceback reaches the user."""
import subprocess
import sys

import pytest

from course_utils import train

BAD = [  # (arguments, the field the message must name)
    (["--hard_first_steps", "-1"], "hard_first_steps"), (["--hard_first_steps", "5"], "hard_first_steps"),
    (["--target_sampling", "prioritized", "--hard_first_ramp", "true"], "hard_first_ramp"),
    (["--group_size", "abc"], "group_size"), (["--group_size", "1"], "group_size"),
    (["--group_size", "100000"], "group_size"), (["--group_size", "2.5"], "group_size"),
    (["--prompts_per_step", "0"], "prompts_per_step"), (["--prompts_per_step", "5000"], "prompts_per_step"),
    (["--max_new_tokens", "100000"], "max_new_tokens"), (["--max_new_tokens", "0"], "max_new_tokens"),
    (["--prompt_tokens", "-1"], "prompt_tokens"), (["--target_chars", "0"], "target_chars"),
    (["--train_prompts", "0"], "train_prompts"), (["--eval_prompts", "0"], "eval_prompts"),
    (["--epochs", "0"], "epochs"), (["--max_steps", "0"], "max_steps"),
    (["--max_steps", "abc"], "max_steps"), (["--grad_accum", "3"], "grad_accum"),
    (["--updates_per_batch", "0"], "updates_per_batch"), (["--updates_per_batch", "1000"], "updates_per_batch"),
    (["--seed", "-1"], "seed"), (["--seed", "99999999999999999999"], "seed"),
    (["--lr", "inf"], "lr"), (["--lr", "nan"], "lr"), (["--lr", "0"], "lr"), (["--lr", "-1"], "lr"),
    (["--lr", "fast"], "lr"), (["--temperature", "inf"], "temperature"),
    (["--temperature", "1e-30"], "temperature"), (["--temperature", "0"], "temperature"),
    (["--kl_coef", "inf"], "kl_coef"), (["--kl_coef", "-1"], "kl_coef"),
    (["--entropy_coef", "inf"], "entropy_coef"), (["--entropy_bonus", "constant"], "entropy_coef"),
    (["--weight_decay", "nan"], "weight_decay"), (["--max_grad_norm", "0"], "max_grad_norm"),
    (["--clip_eps_low", "1.5"], "clip_eps_low"), (["--clip_eps_high", "inf"], "clip_eps_high"),
    (["--loss_type", "mean"], "loss_type"), (["--reward", "dense"], "reward"),
    (["--advantage_center", "batch"], "advantage_scale"), (["--precision", "fp16"], "precision"),
    (["--digit_sum_min", "9", "--digit_sum_max", "3"], "digit_sum_min"),
    (["--prompt_style", "raw"], "digit_sum_max"), (["--dynamic_sampling", "maybe"], "dynamic_sampling"),
    (["--save_every", "0"], "save_every"), (["--lora_rank", "-4"], "lora_rank"),
    (["--device", "tpu"], "device"), (["--entropy_weight_max", "inf"], "entropy_weight_max"),
    (["--model", "./no-such-model"], "model"), (["--model", "a/b/c"], "model"),
    (["--model", "bad id!"], "model"), (["--model", ""], "model"),
]


def test_there_are_at_least_forty_cases():
    assert len(BAD) >= 40


@pytest.mark.parametrize("args, field", BAD, ids=lambda v: " ".join(v) if isinstance(v, list) else v)
def test_bad_input_is_one_line_naming_the_field_before_anything_is_written(tmp_path, args, field):
    out = tmp_path / "run"
    with pytest.raises(SystemExit) as exit_:
        train.main(["--preset", "smoke", "--out_dir", str(out), "--no-progress", *args])
    message = str(exit_.value.code)
    assert message.startswith("error: ") and "\n" not in message, message
    assert field in message, message
    assert not out.exists(), "the run directory was created before the input was refused"


@pytest.mark.parametrize("args", [["--group_size", "abc"], ["--model", "./no-such-model"]])
def test_no_traceback_reaches_the_user(tmp_path, args):
    proc = subprocess.run([sys.executable, "-m", "course_utils.train", "--preset", "smoke",
                           "--out_dir", str(tmp_path / "run"), *args],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode != 0 and "Traceback" not in proc.stderr
    assert proc.stderr.strip().count("\n") == 0 and proc.stderr.startswith("error: "), proc.stderr


def test_an_offline_hub_id_is_refused_before_anything_is_written(tmp_path):
    import os
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "course_utils.train", "--preset", "smoke",
                           "--out_dir", str(out), "--model", "no-such-owner/no-such-model"],
                          capture_output=True, text=True, timeout=120,
                          env={**os.environ, "HF_HUB_OFFLINE": "1"})
    assert proc.returncode != 0 and "Traceback" not in proc.stderr
    assert proc.stderr.startswith("error: model 'no-such-owner/no-such-model' cannot be loaded")
    assert proc.stderr.strip().count("\n") == 0 and "offline" in proc.stderr
    assert not out.exists()
