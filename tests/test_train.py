"""The training loop and the main job, end to end on the tiny model (seconds)."""
import itertools
import json
import os
import subprocess
import sys
import time

import pytest
import torch

from course_utils import checkpoint, cpu, train
from course_utils.config import load_config
from course_utils.data import Prompt


def _params(path):
    from safetensors.torch import load_file
    return load_file(str(path / "checkpoint" / "model.safetensors"))


def test_main_job_smoke_writes_a_complete_run(tmp_path):
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "course_utils.train", "--preset", "smoke",
                           "--out_dir", str(out), "--no-progress"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    for name in ("config.json", "metrics.jsonl", "curves.png", "report.md", "summary.json",
                 "checkpoint/model.safetensors", "checkpoint/trainer_state.pt"):
        assert (out / name).exists(), name
    records = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records] == [1, 2, 3]
    for key in ("reward_mean", "reward_std", "pass_length", "pass_digits", "pass_both", "adv_std",
                "entropy", "entropy_weight", "clip_fraction", "completion_tokens",
                "zero_std_frac", "step_time", "tokens_per_s"):
        assert key in records[0]
    assert records[0]["adv_std"] > 0  # the smoke preset must exercise a real update
    group_size = json.loads((out / "config.json").read_text())["group_size"]
    for r in records:   # the two-digit groups without spread are some of the groups without spread
        assert r["samples_two_digit"] == group_size * r["groups_two_digit"]
        assert 0 <= r["zero_std_two_digit"] <= min(r["groups_two_digit"], round(r["zero_std_frac"] * r["groups_sampled"]))
    assert "| mean reward |" in proc.stdout and "before (sampled)" in proc.stdout
    # which machine it ran on: the capability alone does not tell AMX from AVX512-BF16 (6.8)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["cpu"] == cpu.machine() and summary["cpu"]["model"]


def test_bad_config_fails_fast_with_the_field_named():
    proc = subprocess.run([sys.executable, "-m", "course_utils.train", "--preset", "smoke",
                           "--group_size", "1"], capture_output=True, text=True, timeout=60)
    assert proc.returncode != 0
    assert "group_size=1 is invalid" in proc.stderr and "Traceback" not in proc.stderr
    proc = subprocess.run([sys.executable, "-m", "course_utils.train", "--preset", "smoke",
                           "--lr", "fast"], capture_output=True, text=True, timeout=60)
    assert "--lr 'fast' is not a valid float" in proc.stderr


def test_resume_matches_an_uninterrupted_run_bitwise(tmp_path, monkeypatch):
    full = load_config("smoke", out_dir=str(tmp_path / "full"), max_steps=4, save_every=1)
    train.train(full, progress=False)
    part = load_config("smoke", out_dir=str(tmp_path / "part"), max_steps=2, save_every=1)
    first = train.train(part, progress=False)["seconds"]
    resumed = load_config("smoke", out_dir=str(tmp_path / "part"), max_steps=4, save_every=1)
    # a finished run extended by --resume reports the wall time of both invocations: under a
    # clock that ticks a millisecond per reading, the second adds more than nothing and no more
    # than every tick it read (no wall time is asserted)
    ticks = itertools.count(1)
    monkeypatch.setattr(train.time, "perf_counter", lambda: next(ticks) * 1e-3)
    extended = train.train(resumed, resume=True, progress=False)
    monkeypatch.undo()
    assert extended["resumed"] and first < extended["seconds"] <= first + next(ticks) * 1e-3
    a, b = _params(tmp_path / "full"), _params(tmp_path / "part")
    assert all(torch.equal(a[k], b[k]) for k in a)
    strip = lambda rs: [{k: v for k, v in r.items() if "time" not in k and k != "tokens_per_s"} for r in rs]
    ra = checkpoint.MetricsLog(tmp_path / "full" / "metrics.jsonl").read()
    rb = checkpoint.MetricsLog(tmp_path / "part" / "metrics.jsonl").read()
    assert strip(ra) == strip(rb) and [r["step"] for r in rb] == [1, 2, 3, 4]


def test_resume_refuses_a_checkpoint_from_another_config(tmp_path):
    train.train(load_config("smoke", out_dir=str(tmp_path), max_steps=1), progress=False)
    with pytest.raises(checkpoint.CheckpointError, match="group_size: checkpoint 4 vs now 2"):
        train.train(load_config("smoke", out_dir=str(tmp_path), group_size=2), resume=True, progress=False)


@pytest.mark.parametrize("loss_type", ["grpo", "dapo", "dr_grpo"])
def test_gradient_accumulation_gives_the_full_batch_gradient(loss_type):
    grads = []
    for accum in (1, 2):
        cfg = load_config("smoke", grad_accum=accum, loss_type=loss_type, max_steps=1)
        policy = train.setup(cfg)
        policy.optimizer.step = lambda *a, **k: None  # keep the gradient, skip the update
        prompts = [Prompt(text=t, snippet=t, target_chars=48, target_digit_sum=5)
                   for t in ("One two three", "Four five six seven eight")]
        metrics = train.grpo_step(policy, prompts)
        assert metrics["adv_std"] > 0
        grads.append(torch.cat([p.grad.flatten() for p in policy.model.parameters()]))
    assert grads[0].abs().max() > 0
    assert torch.allclose(grads[0], grads[1], rtol=1e-4, atol=1e-8)


def test_bnpo_through_training_is_trls_mean_of_micro_batch_token_means(monkeypatch):
    """grpo_step with loss_type 'bnpo' and 2 micro-batches (one prompt each) gives the mean of
    the two prompts' own token-mean gradients (TRL 1.16's "bnpo"), which differs from the whole
    batch's token mean ('dapo') when the micro-batches hold different numbers of tokens."""
    prompts = [Prompt(text=t, snippet=t, target_chars=48, target_digit_sum=5)
               for t in ("One two three", "Four five six seven eight")]
    sampler = train.setup(load_config("smoke", max_steps=1))
    full = train.rollout(sampler.model, sampler.tokenizer, [p.text for p in prompts],
                         group_size=sampler.cfg.group_size, max_new_tokens=sampler.cfg.max_new_tokens,
                         eos_ids=sampler.eos_ids, generator=torch.Generator().manual_seed(3))
    # the random tiny model rarely stops early: cut the second prompt's completions shorter, so
    # the two micro-batches hold different numbers of tokens
    G = sampler.cfg.group_size
    full.completion_mask[G:, 5:] = 0
    full.logprobs.mul_(full.completion_mask)
    # every step below trains on these completions: a prompt's rows, whichever batch it is in
    fixed = lambda model, tokenizer, texts, **kw: full.select_groups([[p.text for p in prompts].index(x) for x in texts])
    monkeypatch.setattr(train, "rollout", fixed)

    def gradient(loss_type, accum, batch):
        policy = train.setup(load_config("smoke", grad_accum=accum, loss_type=loss_type,
                                         max_grad_norm=1e6, max_steps=1))
        policy.optimizer.step = lambda *a, **k: None   # keep the gradient, skip the update
        train.grpo_step(policy, batch)
        return torch.cat([p.grad.flatten() for p in policy.model.parameters()])

    tokens = [int(full.select_groups([g]).completion_mask.sum()) for g in (0, 1)]
    assert tokens[0] != tokens[1], "the test needs micro-batches of unequal token counts"
    bnpo = gradient("bnpo", 2, prompts)
    own = [gradient("bnpo", 1, [p]) for p in prompts]   # one micro-batch: its own token mean
    assert bnpo.abs().max() > 0
    assert torch.allclose(bnpo, (own[0] + own[1]) / 2, rtol=1e-4, atol=1e-8)
    assert torch.allclose(gradient("bnpo", 1, prompts), gradient("dapo", 2, prompts), rtol=1e-4, atol=1e-8)
    assert not torch.allclose(bnpo, gradient("dapo", 2, prompts), rtol=1e-3, atol=1e-6)


def test_a_broken_reward_names_the_completion(monkeypatch):
    monkeypatch.setitem(train.rewards.REWARDS, "shaped", lambda prompts, completions, **kw: [float("nan")] * len(completions))
    p = Prompt(text="x", snippet="x", target_chars=3, target_digit_sum=1)
    with pytest.raises(train.RewardError, match="returned nan for the completion 'abc'"):
        train.score([p], ["abc"], "shaped")
    monkeypatch.setitem(train.rewards.REWARDS, "shaped", lambda prompts, completions, **kw: [1.0])
    with pytest.raises(train.RewardError, match="returned 1 values for 2 completions"):
        train.score([p, p], ["a", "b"], "shaped")


def test_the_gguf_file_declares_im_end_as_eos_and_pad():
    """The ids the conversion forces on every transformers version (older ones guess id 1)."""
    from course_utils import models
    ids = models.gguf_special_token_ids(models.gguf_path())
    assert ids == {"bos": 1, "eos": 2, "pad": 2}
    tok = models.load_tokenizer("smollm2-135m-instruct")
    assert tok.convert_ids_to_tokens([1, 2]) == ["<|im_start|>", "<|im_end|>"]
    assert tok.eos_token == tok.pad_token == "<|im_end|>"


def test_the_converted_model_cache_is_keyed_by_the_transformers_version(monkeypatch, tmp_path):
    import importlib.metadata

    from course_utils import models
    monkeypatch.setenv("COURSE_UTILS_CACHE", str(tmp_path))
    here = models.embedded_cache()
    assert here.parent == tmp_path and importlib.metadata.version("transformers") in here.name
    monkeypatch.setattr(models.importlib.metadata, "version", lambda name: "4.56.0")
    assert models.embedded_cache() != here and models.embedded_cache().name.endswith("4.56.0")


def test_embedded_smollm2_loads_offline_and_stops_at_eos():
    from course_utils import models, rollout
    tok = models.load_tokenizer("smollm2-135m-instruct")
    model = models.load_policy("smollm2-135m-instruct")
    assert tok.pad_token_id == tok.eos_token_id == 2  # the pad == EOS trap is real here
    assert sum(p.numel() for p in model.parameters()) == pytest.approx(134.5e6, rel=0.01)
    prompt = tok.apply_chat_template([{"role": "user", "content": "Say hi."}], tokenize=False,
                                     add_generation_prompt=True)
    ro = rollout.rollout(model, tok, [prompt], group_size=2, max_new_tokens=24, greedy=True,
                         eos_ids=models.eos_token_ids(model, tok))
    assert not ro.truncated.any()  # it answered and stopped
    last = ro.lengths - 1
    assert (ro.completion_ids[torch.arange(2), last] == 2).all()  # the EOS is inside the mask
    assert ro.texts[0] and "<|im_end|>" not in ro.texts[0]


@pytest.mark.parametrize("bonus, expect_gradient", [("none", False), ("inverse_variance", True)])
def test_equal_rewards_give_no_gradient_unless_the_entropy_bonus_is_on(monkeypatch, bonus, expect_gradient):
    # every completion gets the same reward: zero-std groups, zero advantages; only the entropy
    # bonus (a course extension, at its cap because the reward variance is 0) can move the policy
    monkeypatch.setitem(train.rewards.REWARDS, "shaped", lambda prompts, completions, **kw: [0.5] * len(completions))
    cfg = load_config("smoke", entropy_bonus=bonus, entropy_coef=1e-3 if bonus != "none" else 0.0)
    policy = train.setup(cfg)
    policy.optimizer.step = lambda *a, **k: None
    prompts = [Prompt(text=t, snippet=t, target_chars=48, target_digit_sum=5) for t in ("One two", "Three")]
    metrics = train.grpo_step(policy, prompts)
    assert metrics["zero_std_frac"] == 1.0 and metrics["adv_abs_mean"] == 0.0
    assert metrics["entropy_weight"] == (cfg.entropy_weight_max if expect_gradient else 0.0)
    norm = sum(float(p.grad.norm()) for p in policy.model.parameters() if p.grad is not None)
    assert (norm > 0) == expect_gradient


def test_the_log_counts_the_two_digit_groups_without_spread(monkeypatch):
    """zero_std_two_digit: of the two-digit groups (targets 10 and up), those whose rewards are all
    equal. Here the target-11 and target-10 groups are constant, the target-12 and target-5
    groups are not."""
    def reward(prompts, completions, target_digit_sum, **kw):
        return [0.5 if s in (10, 11) else 0.1 * i for i, s in enumerate(target_digit_sum)]
    monkeypatch.setitem(train.rewards.REWARDS, "shaped", reward)
    policy = train.setup(load_config("smoke"))
    policy.optimizer.step = lambda *a, **k: None
    prompts = [Prompt(text=t, snippet=t, target_chars=48, target_digit_sum=s)
               for t, s in (("One two", 5), ("Three", 11), ("Four five", 12), ("Six", 10))]
    metrics = train.grpo_step(policy, prompts)
    assert (metrics["groups_two_digit"], metrics["zero_std_two_digit"]) == (3, 2)
    assert metrics["zero_std_frac"] == 0.5
    assert metrics["samples_two_digit"] == 3 * policy.cfg.group_size


def test_top_entropy_quantile_reaches_the_loss_and_is_logged():
    # the step trains the policy term on about the top quarter of its tokens by entropy (ties at
    # the threshold are all kept, so the share can exceed 0.25) and logs the share it kept
    prompts = [Prompt(text=t, snippet=t, target_chars=48, target_digit_sum=5) for t in ("One two", "Three")]
    metrics = train.grpo_step(train.setup(load_config("smoke", top_entropy_quantile=0.25)), prompts)
    assert 0.2 <= metrics["high_entropy_frac"] < 1
    assert "high_entropy_frac" not in train.grpo_step(train.setup(load_config("smoke")), prompts)


def test_kl_to_the_reference_starts_at_zero_and_several_updates_clip():
    cfg = load_config("smoke", kl_coef=0.1, updates_per_batch=3, lr=1e-2, grad_accum=1)
    policy = train.setup(cfg)
    assert policy.ref_model is not None
    prompts = [Prompt(text=t, snippet=t, target_chars=48, target_digit_sum=5) for t in ("One two", "Three")]
    metrics = train.grpo_step(policy, prompts)
    assert metrics["kl"] > 0            # averaged over 3 updates: after the first, the policy moved
    assert metrics["clip_fraction"] > 0  # and the later updates hit the clip
    no_ref = train.setup(load_config("smoke"))
    assert no_ref.ref_model is None     # beta = 0: no reference model is loaded at all
    first = train.grpo_step(train.setup(load_config("smoke", kl_coef=0.1)), prompts)
    assert first["kl"] == pytest.approx(0.0, abs=1e-6)  # one update: measured before it, pi == pi_ref


def test_bf16_autocast_runs_on_the_cpu(tmp_path):
    summary = train.train(load_config("smoke", precision="bf16", max_steps=1, out_dir=str(tmp_path)),
                          progress=False)
    assert "after" in summary
    for p in torch.load(tmp_path / "checkpoint" / "trainer_state.pt", weights_only=True)["optimizer"]["state"].values():
        assert p["exp_avg"].dtype == torch.float32  # fp32 master weights and optimizer state


def test_a_non_finite_loss_skips_the_update_and_is_counted(monkeypatch, capsys):
    # what fp16 overflow in the forward pass looks like from the loop: NaN log-probabilities
    policy = train.setup(load_config("smoke"))
    before = [p.detach().clone() for p in policy.model.parameters()]
    real = train.completion_logprobs

    def overflowing(*args, **kwargs):
        logprobs, entropy = real(*args, **kwargs)
        return logprobs * float("nan"), entropy

    monkeypatch.setattr(train, "completion_logprobs", overflowing)
    prompts = [Prompt(text=t, snippet=t, target_chars=48, target_digit_sum=5) for t in ("One two", "Three")]
    metrics = train.grpo_step(policy, prompts)
    assert metrics["nonfinite_skipped"] == 1
    assert "non-finite loss" in capsys.readouterr().out
    after = list(policy.model.parameters())
    assert all(torch.equal(a, b) for a, b in zip(before, after))
    assert all(torch.isfinite(p).all() for p in after)


def test_an_infinite_gradient_norm_skips_the_update(capsys):
    policy = train.setup(load_config("smoke"))
    before = [p.detach().clone() for p in policy.model.parameters()]
    policy.accelerator.clip_grad_norm_ = lambda *a, **k: torch.tensor(float("inf"))
    prompts = [Prompt(text=t, snippet=t, target_chars=48, target_digit_sum=5) for t in ("One two", "Three")]
    assert train.grpo_step(policy, prompts)["nonfinite_skipped"] == 1
    assert "non-finite gradient" in capsys.readouterr().out
    assert all(torch.equal(a, b) for a, b in zip(before, policy.model.parameters()))


def test_gradient_checkpointing_is_engaged_and_exact(monkeypatch):
    seen, grads = [], []
    real = train.completion_logprobs

    def spy(model, *args, **kwargs):
        seen.append((model.training, model.is_gradient_checkpointing))
        return real(model, *args, **kwargs)

    monkeypatch.setattr(train, "completion_logprobs", spy)
    prompts = [Prompt(text=t, snippet=t, target_chars=48, target_digit_sum=5) for t in ("One two", "Three")]
    for ckpt in (False, True):
        policy = train.setup(load_config("smoke", gradient_checkpointing=ckpt))
        policy.optimizer.step = lambda *a, **k: None
        train.grpo_step(policy, prompts)
        assert not policy.model.training  # back in eval mode for sampling
        grads.append(torch.cat([p.grad.flatten() for p in policy.model.parameters()]))
    assert seen[-1] == (True, True) and seen[0] == (False, False)
    assert torch.allclose(grads[0], grads[1], rtol=1e-4, atol=1e-8)


def test_reward_aware_kl_moves_the_coefficient_and_resumes_exactly(resume_pair):
    (ra, rb), (a, b) = resume_pair(kl_coef=0.05, kl_schedule="reward_aware")
    coefs = [r["kl_coef"] for r in ra]
    assert coefs[0] == pytest.approx(0.05) and len(set(coefs)) > 1   # it reacts to the batches
    assert coefs == [r["kl_coef"] for r in rb]                         # its state is checkpointed
    assert all(torch.equal(a[k], b[k]) for k in a)
    with pytest.raises(Exception, match="kl_schedule"):
        load_config("smoke", kl_schedule="reward_aware")                 # needs kl_coef > 0


def test_the_report_counts_the_steps_taken_and_refuses_a_different_held_out_set(tmp_path):
    """Issue 14, finding 10: resuming a step-4 checkpoint with max_steps 2 reports 4 steps (the
    model's), and a resume may not change eval_prompts, whose "before" score it keeps."""
    train.train(load_config("smoke", out_dir=str(tmp_path), max_steps=4), progress=False)
    summary = train.train(load_config("smoke", out_dir=str(tmp_path), max_steps=2), resume=True,
                          progress=False)
    assert summary["steps"] == 4 and "4 GRPO steps" in (tmp_path / "report.md").read_text()
    with pytest.raises(checkpoint.CheckpointError, match="eval_prompts: checkpoint 4 vs now 2"):
        train.train(load_config("smoke", out_dir=str(tmp_path), eval_prompts=2), resume=True,
                    progress=False)


@pytest.mark.skipif(os.name == "nt", reason="pauses the first run with SIGSTOP")
def test_a_second_run_on_a_live_run_directory_is_refused_and_the_first_finishes_intact(tmp_path):
    """Issue 14, finding 1: two runs on one out_dir. The second is refused, naming the process
    that holds the directory, and the first run's log and checkpoint come out whole."""
    import signal
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "course_utils.train", "--preset", "smoke", "--out_dir", str(out),
           "--no-progress"]
    first = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while not (out / ".lock").exists() or not (out / ".lock").read_text().startswith("process"):
        assert time.time() < deadline and first.poll() is None, "the first run never took the lock"
        time.sleep(0.05)
    # pause the first run while it holds the directory, so the two surely overlap
    os.kill(first.pid, signal.SIGSTOP)
    try:
        second = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    finally:
        os.kill(first.pid, signal.SIGCONT)
    assert second.returncode != 0 and "Traceback" not in second.stderr
    assert f"is in use by process {first.pid}" in second.stderr, second.stderr
    assert first.wait(timeout=300) == 0, first.stderr.read()[-2000:]
    steps = [r["step"] for r in checkpoint.MetricsLog(out / "metrics.jsonl").read()]
    assert steps == [1, 2, 3]
    assert checkpoint.find(out).name == "checkpoint"


@pytest.mark.parametrize("native, expected", [(True, "bf16"), (False, "fp32")])
def test_auto_precision_takes_bf16_only_where_the_cpu_has_bf16_units(monkeypatch, native, expected):
    monkeypatch.setattr(train.cpu, "native_bf16", lambda: native)
    assert train.effective_precision(load_config("smoke", precision="auto", device="cpu")) == expected
    assert train.effective_precision(load_config("smoke", precision="fp32", device="cpu")) == "fp32"


def test_the_bf16_sampler_is_a_copy_refreshed_from_the_fp32_weights():
    policy = train.setup(load_config("smoke", precision="bf16", device="cpu"))
    assert policy.sampler is not None and policy.sampler is not policy.model
    with torch.no_grad():
        for p in policy.model.parameters():
            p.add_(0.01)                      # as an optimizer step would
    sampler = train.sampling_model(policy)
    for (name, p), q in zip(policy.model.named_parameters(), sampler.parameters()):
        assert q.dtype == torch.bfloat16 and p.dtype == torch.float32, name
        assert torch.equal(q, p.detach().to(torch.bfloat16)), name
    assert train.setup(load_config("smoke")).sampler is None   # fp32 samples with the policy


def test_several_updates_with_a_bf16_sampler_take_pi_old_from_the_trainer():
    # With a (practically) zero learning rate the policy never moves, so pi_theta / pi_old must be
    # exactly 1 at every update. A clip range of 1e-6 turns any gap into clipped tokens: the
    # bf16 sampler's own log-probs as pi_old would clip most of them.
    cfg = load_config("smoke", precision="bf16", device="cpu", updates_per_batch=3, lr=1e-12,
                      clip_eps_low=1e-6, clip_eps_high=1e-6, grad_accum=2)
    policy = train.setup(cfg)
    prompts = [Prompt(text=t, snippet=t, target_chars=48, target_digit_sum=5)
               for t in ("One two", "Three", "Four five six", "Seven")]
    metrics = train.grpo_step(policy, prompts)
    assert metrics["adv_abs_mean"] > 0        # tokens with an advantage, so clipping could show
    assert metrics["clip_fraction"] == 0.0


@pytest.mark.parametrize("mode, updates", [("token_truncate", 1), ("sequence_mask", 2)])
def test_the_mismatch_correction_weights_the_bf16_samplers_tokens(mode, updates, monkeypatch):
    # The weights are pi_trainer / pi_sampler on the sampled tokens: the trainer's side is its
    # first forward of the batch (update 0, kept for every update), the sampler's the rollout's
    # own log-probs, in that order; the step's mean weight and gap are what they give.
    from course_utils import mismatch
    cfg = load_config("smoke", precision="bf16", device="cpu", is_correction=mode, is_clip_max=1.5,
                      updates_per_batch=updates)
    policy = train.setup(cfg)
    prompts = [Prompt(text=t, snippet=t, target_chars=48, target_digit_sum=5) for t in ("One two", "Three")]
    seen, forwards, rollouts = [], [], []
    real, real_forward, real_rollout = mismatch.importance_weights, train.completion_logprobs, train.rollout
    monkeypatch.setattr(train.mismatch, "importance_weights",
                        lambda *a, **k: seen.append(a) or real(*a, **k))
    monkeypatch.setattr(train, "completion_logprobs",
                        lambda *a, **k: forwards.append(real_forward(*a, **k)) or forwards[-1])
    monkeypatch.setattr(train, "rollout", lambda *a, **k: rollouts.append(real_rollout(*a, **k)) or rollouts[-1])
    metrics = train.grpo_step(policy, prompts)
    micro = cfg.grad_accum
    assert len(seen) == micro * updates and len(rollouts) == 1
    ro = rollouts[0]
    n = ro.completion_ids.shape[0] // micro
    for i, (trainer_lp, sampler_lp, mask, got_mode, clip) in enumerate(seen):
        k = i % micro   # the micro-batch; update i // micro
        assert (got_mode, clip) == (mode, 1.5)
        assert torch.equal(trainer_lp, forwards[k][0].detach())          # update 0's forward
        assert torch.equal(sampler_lp, ro.logprobs[k * n:(k + 1) * n])   # the sampler's, second
    assert not torch.equal(seen[0][0] * seen[0][2], seen[0][1] * seen[0][2])   # a real gap
    weights = torch.cat([real(*a) for a in seen[:micro]])
    masks = torch.cat([a[2] for a in seen[:micro]])
    gaps = torch.cat([(a[0] - a[1]).abs() * a[2] for a in seen[:micro]])
    assert metrics["is_weight_mean"] == pytest.approx(float((weights * masks).sum() / masks.sum()), rel=1e-5)
    assert metrics["sampler_gap_abs"] == pytest.approx(float(gaps.sum() / masks.sum()), rel=1e-5)


def test_without_the_correction_the_bf16_step_logs_the_gap_and_no_weights():
    cfg = load_config("smoke", precision="bf16", device="cpu")
    prompts = [Prompt(text=t, snippet=t, target_chars=48, target_digit_sum=5) for t in ("One two", "Three")]
    metrics = train.grpo_step(train.setup(cfg), prompts)
    assert "is_weight_mean" not in metrics and metrics["sampler_gap_abs"] > 0
    fp32 = train.grpo_step(train.setup(load_config("smoke", device="cpu")), prompts)
    assert "is_weight_mean" not in fp32 and "sampler_gap_abs" not in fp32


def test_an_apple_gpu_is_not_taken_for_a_cpu(monkeypatch):
    # accelerate picks MPS when it is there, so neither the CPU's bf16 autocast nor its bf16
    # sampler may be used then; asking for the CPU is the CPU everywhere
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: True)
    assert not train.runs_on_cpu(load_config("smoke"))
    assert train.runs_on_cpu(load_config("smoke", device="cpu"))
    monkeypatch.setattr(train.cpu, "native_bf16", lambda: True)
    assert train.effective_precision(load_config("smoke", precision="auto")) == "fp32"
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: False)
    assert train.runs_on_cpu(load_config("smoke"))


def test_adaptive_entropy_and_prioritized_targets_resume_exactly(resume_pair, monkeypatch):
    """Both carry state from step to step (the entropy coefficient, the pass rate per target):
    a run stopped and resumed must draw the same batches and weights as one that never stopped.
    The tiny model never passes, so 'passed' is made the upper half of each batch's rewards:
    pass rates then differ by target, and a resume that lost them would draw other batches."""
    score = train.score

    def half_pass(prompts, texts, reward_name):
        s = score(prompts, texts, reward_name)
        s["passed"] = (s["rewards"] > s["rewards"].median()).float()
        return s

    monkeypatch.setattr(train, "score", half_pass)
    seen = []
    observe = train.curriculum.TargetPriority.observe
    monkeypatch.setattr(train.curriculum.TargetPriority, "observe",
                        lambda self, *a, **k: (observe(self, *a, **k), seen.append(dict(self.pass_rate))))
    (ra, rb), (a, b) = resume_pair(entropy_bonus="adaptive", entropy_coef=0.01, entropy_target=20.0,
                                   target_sampling="prioritized")
    assert any(0 < v < 1 for rates in seen for v in rates.values())   # the state is not trivial
    weights = [r["entropy_weight"] for r in ra]
    assert weights[0] == 0.0 and weights[1] == pytest.approx(0.01) and weights[2] == pytest.approx(0.02)
    for key in ("entropy_weight", "reward_mean", "samples_two_digit", "loss"):
        assert [r[key] for r in ra] == [r[key] for r in rb], key
    assert all(torch.equal(a[k], b[k]) for k in a)
