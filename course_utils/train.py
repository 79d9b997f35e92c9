"""The GRPO training loop shared by the notebooks and the command line.

    python -m course_utils.train --preset cpu             # the main job: offline, ~13 min on 2 cores
    python -m course_utils.train --preset cpu --lr 3e-5 --out_dir runs/mine
    python -m course_utils.train --preset cpu --resume    # continue a run from its checkpoint
    python -m course_utils.train --preset cpu --overwrite # replace the run in out_dir

Ctrl-C (or SIGTERM) stops after the step in flight, saves a checkpoint and prints the command
that continues the run; a second Ctrl-C stops at once.

One step: sample G completions for each of B prompts (no autograd) -> score them with the rule
checker -> group-relative advantages -> forward the completions with autograd -> GRPO loss ->
backward (micro-batch by micro-batch) -> clip the gradient norm -> AdamW step. Every step
appends one record to ``metrics.jsonl``; checkpoints are written every ``save_every`` steps.
"""

from __future__ import annotations

import argparse
import contextlib
import difflib
import json
import math
import os
import re
import shlex
import sys
import time
import typing
from dataclasses import dataclass, field
from pathlib import Path

import torch

from . import checkpoint, cpu, curriculum, data, interrupt, losses, mismatch, models, plan, rewards
from .config import Config, ConfigError, PRESETS, load_config, smoke_mode
from .rollout import NonFiniteLogits, Rollout, completion_logprobs, concat_rollouts, rollout


class RewardError(ValueError):
    """A reward function misbehaved; the message names the completion involved."""


# ---------------------------------------------------------------------------------------------
# Scoring
# ---------------------------------------------------------------------------------------------


def score(prompts: list[data.Prompt], texts: list[str], reward_name: str) -> dict[str, torch.Tensor]:
    """Rewards and the per-constraint flags for completions (``prompts`` already repeated G times)."""
    targets = dict(target_chars=[p.target_chars for p in prompts],
                   target_digit_sum=[p.target_digit_sum for p in prompts])
    reward_fn = rewards.get_reward_fn(reward_name)
    try:
        values = reward_fn(prompts=[p.text for p in prompts], completions=texts, **targets)
    except Exception as err:
        raise RewardError(f"reward function {reward_name!r} raised {type(err).__name__}: {err}"
                          f"{_first_failing(reward_fn, prompts, texts)}") from err
    if len(values) != len(texts):
        raise RewardError(f"reward function {reward_name!r} returned {len(values)} values for "
                          f"{len(texts)} completions")
    for text, value in zip(texts, values):
        if not isinstance(value, (int, float)) or not math.isfinite(value):
            raise RewardError(f"reward function {reward_name!r} returned {value!r} for the "
                              f"completion {text!r:.120}; rewards must be finite numbers")
    checks = rewards.check_all(texts, **targets)
    return dict(
        empty=torch.tensor([rewards.completion_text(t) == "" for t in texts], dtype=torch.float32),
        rewards=torch.tensor(values, dtype=torch.float32),
        length_ok=torch.tensor([c.length_ok for c in checks], dtype=torch.float32),
        digits_ok=torch.tensor([c.digits_ok for c in checks], dtype=torch.float32),
        passed=torch.tensor([c.passed for c in checks], dtype=torch.float32),
        chars_abs_error=torch.tensor([abs(c.n_chars - p.target_chars) for c, p in zip(checks, prompts)],
                                     dtype=torch.float32),
    )


def score_rollout(prompts: list[data.Prompt], ro: Rollout, cfg: Config) -> dict[str, torch.Tensor]:
    """``score`` of a rollout's texts, its truncation flags, and, with ``cfg.overlong_penalty``,
    DAPO's overlong punishment on its token counts added to 'rewards' (what the advantages
    see). 'passed' and the other flags stay the rule's alone."""
    s = score(prompts, ro.texts, cfg.reward)
    s["truncated"] = ro.truncated.float().cpu()
    if cfg.overlong_penalty > 0:
        punish = rewards.overlong_punishment(ro.lengths.tolist(), ro.truncated.tolist(),
                                             cfg.max_new_tokens, cfg.overlong_buffer)
        s["overlong"] = cfg.overlong_penalty * torch.tensor(punish, dtype=torch.float32)
        s["rewards"] = s["rewards"] + s["overlong"]
    return s


def _first_failing(reward_fn, prompts: list[data.Prompt], texts: list[str]) -> str:
    """Find the completion a reward function fails on, by scoring them one at a time."""
    for p, text in zip(prompts, texts):
        try:
            reward_fn(prompts=[p.text], completions=[text], target_chars=[p.target_chars],
                      target_digit_sum=[p.target_digit_sum])
        except Exception:
            return f" (on the completion {text!r:.120})"
    return " (no single completion fails alone: the error depends on the whole batch)"


# ---------------------------------------------------------------------------------------------
# Evaluation
# ---------------------------------------------------------------------------------------------


@torch.no_grad()
def evaluate(model, tokenizer, prompts: list[data.Prompt], cfg: Config, eos_ids: list[int], *,
             greedy: bool, batch_size: int = 16) -> dict:
    """One completion per held-out prompt, sampled at the training temperature or greedy.

    Uses its own generator seeded from the config, so evaluation is reproducible and does not
    move the training random stream.
    """
    generator = torch.Generator(device=next(model.parameters()).device).manual_seed(cfg.seed + 12345)
    texts, unscored = [], 0
    for start in range(0, len(prompts), batch_size):
        chunk = prompts[start:start + batch_size]
        try:
            out = rollout(model, tokenizer, [p.text for p in chunk], group_size=1,
                          max_new_tokens=cfg.max_new_tokens, eos_ids=eos_ids,
                          temperature=cfg.temperature, greedy=greedy, generator=generator,
                          fast=cfg.fast_kernels)
            texts.extend(out.texts)
        except NonFiniteLogits as err:   # fp16 overflow: these prompts count as failed, and say so
            unscored += len(chunk)
            texts.extend([""] * len(chunk))
            print(f"[course_utils] evaluation: {err}; {len(chunk)} prompts counted as failed "
                  f"({unscored} so far). If it repeats, evaluate with precision='fp32'.")
    s = score(prompts, texts, cfg.reward)
    checks = [rewards.check(t, p.target_chars, p.target_digit_sum) for t, p in zip(texts, prompts)]
    # A one-digit target can be met by copying it from the instruction; a two-digit one (10-12
    # in the cpu preset) needs digits that add up to it, which is harder, so report both kinds.
    one_digit = torch.tensor([p.target_digit_sum <= 9 for p in prompts])
    split = {f"pass_both_{kind}": float(s["passed"][sel].mean()) if sel.any() else float("nan")
             for kind, sel in (("one_digit", one_digit), ("two_digit", ~one_digit))}
    return dict(
        reward_mean=float(s["rewards"].mean()), pass_length=float(s["length_ok"].mean()),
        pass_digits=float(s["digits_ok"].mean()), pass_both=float(s["passed"].mean()), **split,
        n_one_digit=int(one_digit.sum()), n_two_digit=int((~one_digit).sum()),
        # a policy that writes one template for every snippet passes the checker without
        # continuing the text; the checker cannot see that, this count can
        distinct_completions=len(set(texts)), distinct_snippets=len({p.snippet for p in prompts}),
        chars_abs_error=float(s["chars_abs_error"].mean()), nonfinite_unscored=unscored,
        samples=[dict(snippet=p.snippet[-60:], target_chars=p.target_chars,
                      target_digit_sum=p.target_digit_sum, completion=t, n_chars=c.n_chars,
                      digit_sum=c.digit_sum) for p, t, c in zip(prompts, texts, checks)],
    )


# ---------------------------------------------------------------------------------------------
# One GRPO step
# ---------------------------------------------------------------------------------------------


@dataclass
class Policy:
    """Everything a step needs besides the data; built once by ``setup``."""
    cfg: Config
    model: typing.Any
    tokenizer: typing.Any
    optimizer: torch.optim.Optimizer
    scheduler: typing.Any
    accelerator: typing.Any
    eos_ids: list[int]
    generator: torch.Generator
    ref_model: typing.Any = None
    kl_schedule: typing.Any = None   # losses.RewardAwareKL when cfg.kl_schedule == "reward_aware"
    sampler: typing.Any = None       # a bf16 copy that samples, for bf16 on a CPU (sampling_model)
    entropy_control: typing.Any = None   # losses.AdaptiveEntropy when cfg.entropy_bonus == "adaptive"
    priority: typing.Any = None      # curriculum.TargetPriority when cfg.target_sampling == "prioritized"
    counters: dict = field(default_factory=lambda: {"nonfinite_skipped": 0})


def sampling_model(policy: Policy):
    """The network that samples completions: the policy itself, or for bf16 on a CPU a bf16 copy
    of it, refreshed from the fp32 weights on every call (a small share of sampling's time:
    benchmarks/RESULTS.md).

    Decoding is one token at a time, so its matrix products are thin and their cost is reading
    the weights: bf16 weights are half the bytes, and a bf16 copy decodes without autocast's
    per-call casts of every activation (benchmarks/RESULTS.md has both timings). The copy's
    log-probabilities differ from the trainer's slightly (its norms and residual sums are bf16
    too): the gap is measured in benchmarks/RESULTS.md."""
    if policy.sampler is None:
        return policy.model
    policy.sampler.load_state_dict(policy.accelerator.unwrap_model(policy.model).state_dict())
    return policy.sampler


def _skipped_sampling(policy: Policy, err: Exception, timer: "PhaseTimer", t0: float) -> dict:
    """A step whose sampler met NaN or inf logits: nothing to score or train on, so no update;
    the step is counted like a skipped update and the schedule moves on, as it does for one.
    Its metrics record holds what is known (the sampled quantities are absent: plots skip them)."""
    _skip_update(policy, f"logits in sampling ({err})")
    policy.model.eval()
    policy.scheduler.step()
    elapsed = time.perf_counter() - t0
    return dict(nonfinite_skipped=policy.counters["nonfinite_skipped"], sampling_skipped=1,
                lr=policy.scheduler.get_last_lr()[0], gen_time=timer.seconds["generation"],
                train_time=elapsed - timer.seconds["generation"], step_time=elapsed,
                **{f"time_{phase}": sec for phase, sec in timer.seconds.items()})


def _skip_update(policy: Policy, what: str) -> None:
    """Drop this update's gradients instead of training on NaN or inf, and say so."""
    policy.counters["nonfinite_skipped"] += 1
    policy.optimizer.zero_grad(set_to_none=True)
    print(f"[course_utils] non-finite {what} (NaN or inf): update skipped, "
          f"{policy.counters['nonfinite_skipped']} so far. With fp16 this usually means the "
          f"forward pass overflowed; if it repeats, use precision='fp32' or a lower lr.")


@torch.no_grad()
def reference_logprobs(policy: Policy, ro) -> torch.Tensor:
    """log pi_ref of the sampled completions, for the KL term. Under LoRA the reference is the
    policy with its adapters disabled: the frozen base weights *are* the pre-trained model."""
    args = (ro.prompt_ids, ro.prompt_mask, ro.completion_ids, ro.completion_mask)
    kwargs = dict(temperature=policy.cfg.temperature, group_size=policy.cfg.group_size,
                  fast=policy.cfg.fast_kernels)
    with cpu_autocast(policy.cfg):
        if policy.ref_model is not None:
            return completion_logprobs(policy.ref_model, *args, **kwargs)[0]
        with policy.accelerator.unwrap_model(policy.model).disable_adapter():
            return completion_logprobs(policy.model, *args, **kwargs)[0]


class PhaseTimer:
    """Seconds spent per phase of a step (generation, scoring, forward, ...), for the metrics
    and the benchmark."""

    def __init__(self):
        self.seconds: dict[str, float] = {}

    @contextlib.contextmanager
    def __call__(self, phase: str):
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[phase] = self.seconds.get(phase, 0.0) + time.perf_counter() - start


def _all_reduce_gradients(policy: Policy) -> None:
    """Several processes: each backward gave its own prompts' share of one global sum (the loss
    is normalized by global counts), so adding the shares gives the full batch's gradient."""
    for param in policy.model.parameters():
        if param.requires_grad:
            if param.grad is None:
                param.grad = torch.zeros_like(param)
            torch.distributed.all_reduce(param.grad, op=torch.distributed.ReduceOp.SUM)


def sample_batch(policy: Policy, prompts: list[data.Prompt],
                 refill: typing.Callable[[int], list[data.Prompt]] | None = None):
    """Sample G completions for each prompt; with ``cfg.dynamic_sampling`` (DAPO), keep only
    the groups with signal and sample further rounds of prompts from ``refill(round)`` until
    ``len(prompts)`` such groups are found or ``max_sampling_rounds`` rounds have run. A batch
    still short is filled with the first rounds' groups without signal, so the batch size (and
    with it every normalization in the loss) never changes.

    Returns (rollout, the prompts it continues, groups sampled in all, rounds run, the first
    round's pass rate). The batch trained on is *selected*, so its pass rate is not the
    policy's; the first round's, sampled before any selection, is.
    """
    cfg = policy.cfg
    G = cfg.group_size

    sampler = sampling_model(policy)

    def sample(batch):
        ro = rollout(sampler, policy.tokenizer, [p.text for p in batch], group_size=G,
                     max_new_tokens=cfg.max_new_tokens, eos_ids=policy.eos_ids,
                     temperature=cfg.temperature, generator=policy.generator,
                     fast=cfg.fast_kernels)
        return ro, score_rollout([p for p in batch for _ in range(G)], ro, cfg)

    ro, scores = sample(prompts)
    rewards, first_pass = scores["rewards"], float(scores["passed"].mean())
    if not cfg.dynamic_sampling:
        return ro, prompts, len(prompts), 1, first_pass
    if refill is None:
        raise ValueError("dynamic_sampling needs a source of fresh prompts (refill)")
    B = len(prompts)
    kept, spare = [], []   # (rollout, group index, prompt): groups with and without signal
    rounds, sampled = 0, 0
    batch = prompts
    while True:
        rounds += 1
        sampled += len(batch)
        for g, signal in enumerate((~losses.constant_groups(rewards, G)).squeeze(-1).tolist()):
            (kept if signal else spare).append((ro, g, batch[g]))
        if len(kept) >= B or rounds == cfg.max_sampling_rounds:
            break
        batch = refill(rounds)
        ro, scores = sample(batch)
        rewards = scores["rewards"]
    chosen = (kept + spare)[:B]
    parts = [part.select_groups([g]) for part, g, _ in chosen]
    return (concat_rollouts(parts, policy.tokenizer.pad_token_id), [p for _, _, p in chosen],
            sampled, rounds, first_pass)


def grpo_step(policy: Policy, prompts: list[data.Prompt],
              refill: typing.Callable[[int], list[data.Prompt]] | None = None) -> dict:
    """Sample, score, and update once on ``prompts`` (the global batch). Returns the metrics.

    With several processes (``accelerate launch``), process k samples and trains prompts
    k*B/W ... (k+1)*B/W - 1: whole groups, so per-group statistics are exact. Rewards are
    gathered from every process before the advantages and the entropy weight are computed, so
    batch-level options see the whole batch too, and every count in the loss is global.

    ``refill(round)`` gives fresh prompts for dynamic sampling (``cfg.dynamic_sampling``);
    ``train`` draws them from a stream seeded by the step, so a resumed run sees the same ones.
    """
    cfg, model, acc = policy.cfg, policy.model, policy.accelerator
    G, W, rank = cfg.group_size, acc.num_processes, acc.process_index
    if cfg.dynamic_sampling and W > 1:
        raise ValueError("dynamic_sampling runs in one process only: each process would keep "
                         "different groups; launch without accelerate, or turn it off")
    if len(prompts) % W:
        raise ValueError(f"{len(prompts)} prompts per step cannot be split over {W} processes: "
                         f"set prompts_per_step to a multiple of {W}")
    per_process = len(prompts) // W
    if per_process % cfg.grad_accum:
        raise ValueError(f"{per_process} prompts per process cannot be split into grad_accum="
                         f"{cfg.grad_accum} micro-batches of whole groups: make prompts_per_step "
                         f"a multiple of {W * cfg.grad_accum}")
    local = prompts[rank * per_process:(rank + 1) * per_process]
    timer = PhaseTimer()
    t0 = time.perf_counter()
    with timer("generation"):
        try:
            sampled = sample_batch(policy, local, refill)
        except NonFiniteLogits as err:
            sampled, sampling_error = None, err
    if W > 1:  # every process must agree to skip (a step that others train would hang)
        agreed = acc.reduce(torch.tensor(float(sampled is not None), device=acc.device), "sum") == W
        if sampled is not None and not agreed:
            sampled, sampling_error = None, NonFiniteLogits("another process's sampler met non-finite logits")
    if sampled is None:
        return _skipped_sampling(policy, sampling_error, timer, t0)
    ro, local, groups_sampled, rounds, first_pass = sampled
    with timer("scoring"):
        s = score_rollout([p for p in local for _ in range(G)], ro, cfg)
        if W > 1:  # everyone's rewards and flags, in process order (= the global batch order)
            s = {k: acc.gather(v.to(acc.device)).cpu() for k, v in s.items()}
        advantages, zero_std = losses.group_advantages(s["rewards"], G, cfg.advantage_center,
                                                       cfg.advantage_scale)
        ent_weight = policy.entropy_control.weight() if policy.entropy_control else \
            losses.entropy_weight(s["rewards"], cfg.entropy_bonus, cfg.entropy_coef,
                                  cfg.entropy_weight_max)
        if policy.priority:   # the running pass rate per target, from the groups trained on
            policy.priority.observe(local if W == 1 else prompts, s["passed"], G)
        mine = slice(rank * per_process * G, (rank + 1) * per_process * G)
        advantages_local = advantages[mine].to(ro.completion_ids.device)
    mask = ro.completion_mask  # the tokens that get a loss
    if cfg.overlong_filter:  # a truncated completion's tokens get none (DAPO)
        mask = mask * (~ro.truncated).to(mask.dtype).unsqueeze(-1)
    n_local = mask.shape[0]
    n_seq = n_local * W
    n_tok = int(acc.reduce(mask.sum().to(acc.device), "sum")) if W > 1 else int(mask.sum())

    beta = policy.kl_schedule.coefficient(s["rewards"]) if policy.kl_schedule else cfg.kl_coef
    ref_logprobs = None
    if cfg.kl_coef > 0:
        with timer("reference"):
            ref_logprobs = reference_logprobs(policy, ro)

    rows_per_micro = n_local // cfg.grad_accum  # whole groups per micro-batch (checked by validate)
    # transformers checkpoints activations only in train mode; sampling stays in eval mode (with
    # checkpointing on, train mode would switch off the KV cache). Dropout is off either way.
    model.train(cfg.gradient_checkpointing)
    stats_sum: dict[str, float] = {}
    loss_total, grad_norm = 0.0, float("nan")
    # With bf16 on a CPU (a separate bf16 sampler, or under LoRA fp32 sampling while training
    # runs under autocast), pi_old is scored by the trainer itself: the first update's
    # log-probs (taken before any weight moves), so the ratio measures the policy's change and
    # not the two networks' rounding (the sampler-trainer gap: benchmarks/RESULTS.md).
    # (also the trainer's side of the sampler-trainer gap and of the mismatch's correction)
    trainer_first: dict[int, torch.Tensor] = {}
    skipped_before = policy.counters["nonfinite_skipped"]
    for _ in range(cfg.updates_per_batch):
        policy.optimizer.zero_grad(set_to_none=True)
        step_ok = True
        for start in range(0, n_local, rows_per_micro):
            rows = slice(start, start + rows_per_micro)
            with timer("forward"), cpu_autocast(cfg):
                logprobs, entropy = completion_logprobs(
                    model, ro.prompt_ids[rows], ro.prompt_mask[rows], ro.completion_ids[rows],
                    ro.completion_mask[rows], temperature=cfg.temperature, with_entropy=True,
                    entropy_grad=ent_weight > 0,
                    group_size=G if cfg.shares_prompt_in_training else 1, fast=cfg.fast_kernels)
                # One update per batch: pi_old is the current policy, so the ratio is exactly 1
                # and the step is REINFORCE with a group baseline. More: pi_old is the sampler's
                # log-probs, or with a bf16 sampler the trainer's own first ones (above).
                if cfg.updates_per_batch == 1:
                    old = logprobs.detach()
                elif not cpu_bf16(cfg) and cfg.is_correction == "none":
                    old = ro.logprobs[rows]   # pi_old: the sampler's log-probs, same numerics
                    # (with the correction on, pi_old is the trainer's, as in TRL, so the
                    # weights below carry the mismatch once, not the ratio as well)
                else:
                    old = trainer_first.setdefault(start, logprobs.detach())   # kept from update 0
                weights, first = None, None
                if cpu_bf16(cfg) or cfg.is_correction != "none":   # two numerics, or a correction
                    # the trainer's log-probs before any weight moves (update 0), as TRL takes
                    # them from pi_old's forward, against the sampler's on the same tokens
                    first = trainer_first.setdefault(start, logprobs.detach())
                if cfg.is_correction != "none":   # weights pi_trainer / pi_sampler
                    weights = mismatch.importance_weights(first, ro.logprobs[rows], mask[rows],
                                                          cfg.is_correction, cfg.is_clip_max)
                loss, stats = losses.grpo_loss(
                    logprobs, old, advantages_local[rows], mask[rows], loss_type=cfg.loss_type,
                    eps_low=cfg.clip_eps_low, eps_high=cfg.clip_eps_high,
                    ref_logprobs=None if ref_logprobs is None else ref_logprobs[rows],
                    beta=beta, entropy=entropy, entropy_weight=ent_weight,
                    max_completion_length=cfg.max_new_tokens, total_sequences=n_seq,
                    total_tokens=n_tok, micro_batches=cfg.grad_accum * W,
                    sampling_weights=weights, top_entropy_quantile=cfg.top_entropy_quantile)
                if first is not None:
                    # the sampler-trainer gap per token on this batch (benchmarks/RESULTS.md
                    # measures it once; this logs how it moves as the policy trains)
                    real = ro.completion_mask[rows]   # every sampled token, filtered or not
                    gap = torch.where(real.bool(), first - ro.logprobs[rows], 0.0).abs()
                    stats["sampler_gap_abs"] = losses.masked_mean(gap, real)
            if not torch.isfinite(loss):
                step_ok = False
                break
            with timer("backward"):
                acc.backward(loss)
            loss_total += float(loss.detach()) / cfg.updates_per_batch
            for k, v in stats.items():  # token-weighted average over micro-batches
                stats_sum[k] = stats_sum.get(k, 0.0) + v * float(mask[rows].sum()) / max(n_tok, 1) / cfg.updates_per_batch
        if W > 1:  # every process must agree to skip, and then reduce together
            step_ok = bool(acc.reduce(torch.tensor(float(step_ok), device=acc.device), "sum") == W)
            if step_ok:
                with timer("backward"):
                    _all_reduce_gradients(policy)
        if not step_ok:
            _skip_update(policy, "loss")
            continue
        with timer("optimizer"):
            grad_norm = float(acc.clip_grad_norm_(model.parameters(), cfg.max_grad_norm))
            if not math.isfinite(grad_norm) and cfg.precision != "fp16":
                _skip_update(policy, "gradient")
                continue
            # With fp16, accelerate's gradient scaler skips a step whose gradients overflowed
            # and lowers its scale (it must see the step to do so); count those skips too.
            if policy.kl_schedule:
                policy.kl_schedule.observe_gradient(grad_norm)
            policy.optimizer.step()
            if acc.optimizer_step_was_skipped:
                policy.counters["nonfinite_skipped"] += 1
    model.eval()
    policy.scheduler.step()
    if W > 1:  # the loss and the token statistics are each process's share of a global sum
        shares = acc.reduce(torch.tensor([loss_total, *stats_sum.values()], device=acc.device), "sum")
        loss_total, stats_sum = float(shares[0]), dict(zip(stats_sum, shares[1:].tolist()))
    # the adaptive entropy weight reads the whole batch's entropy (after the reduce, so every
    # process moves its coefficient alike), and only from a step that ran in full on some tokens
    if policy.entropy_control and "entropy" in stats_sum and n_tok > 0 and \
            policy.counters["nonfinite_skipped"] == skipped_before:
        policy.entropy_control.observe(stats_sum["entropy"])
    t_end = time.perf_counter()
    lengths = ro.completion_mask.sum(-1).float()
    # two-digit targets (10 and up) need more than a digit copied from the instruction
    two_digit_groups = torch.tensor([p.target_digit_sum >= 10 for p in (local if W == 1 else prompts)])
    two_digit = two_digit_groups.repeat_interleave(G)
    # the groups without spread among the two-digit ones: whether those prompts lack signal
    # (lesson 7, 6.8) is read from this, not from zero_std_frac over the whole batch
    constant = losses.constant_groups(s["rewards"], G).squeeze(-1)
    total_tokens = (int(ro.prompt_mask.sum()) + int(lengths.sum())) * W
    return dict(
        reward_mean=float(s["rewards"].mean()), reward_std=float(s["rewards"].std()),
        pass_length=float(s["length_ok"].mean()), pass_digits=float(s["digits_ok"].mean()),
        pass_both=float(s["passed"].mean()), samples_two_digit=int(two_digit.sum()),
        passes_two_digit=int(s["passed"][two_digit].sum()), groups_two_digit=int(two_digit_groups.sum()),
        zero_std_two_digit=int(constant[two_digit_groups].sum()), chars_abs_error=float(s["chars_abs_error"].mean()),
        adv_mean=float(advantages.mean()), adv_std=float(advantages.std()),
        adv_abs_mean=float(advantages.abs().mean()), zero_std_frac=zero_std / len(prompts),
        groups_sampled=groups_sampled * W, sampling_rounds=rounds, first_round_pass_both=first_pass,
        distinct_frac=len(set(ro.texts)) / len(ro.texts),
        prompt_len_max=int(ro.prompt_mask.sum(-1).max()),   # tokens, template included
        entropy_weight=ent_weight, kl_coef=beta, completion_tokens=float(lengths.mean()),
        truncated_frac=float(s["truncated"].mean()), empty_frac=float(s["empty"].mean()),
        loss=loss_total, grad_norm=grad_norm,
        lr=policy.scheduler.get_last_lr()[0], nonfinite_skipped=policy.counters["nonfinite_skipped"],
        gen_time=timer.seconds["generation"], train_time=t_end - t0 - timer.seconds["generation"],
        step_time=t_end - t0, tokens_per_s=total_tokens / (t_end - t0),
        **{f"time_{phase}": sec for phase, sec in timer.seconds.items()}, **stats_sum,
        # the punishment's share of reward_mean, logged only where it is on (older logs stay as they were)
        **({"overlong_mean": float(s["overlong"].mean())} if "overlong" in s else {}),
    )


# ---------------------------------------------------------------------------------------------
# Set-up, the run, and the report
# ---------------------------------------------------------------------------------------------


def runs_on_cpu(cfg: Config) -> bool:
    """Whether a run computes on the CPU: asked for, or no accelerator (CUDA, Apple's MPS) there
    for accelerate to pick."""
    mps = getattr(torch.backends, "mps", None)
    return cfg.device == "cpu" or not (torch.cuda.is_available() or (mps is not None and mps.is_available()))


def effective_precision(cfg: Config) -> str:
    """The precision a run computes in: cfg.precision, with 'auto' resolved for this machine
    (bf16 on a CPU with native bf16 matrix units, fp32 on any other CPU and on a GPU)."""
    if cfg.precision != "auto":
        return cfg.precision
    return "bf16" if runs_on_cpu(cfg) and cpu.native_bf16() else "fp32"


def cpu_bf16(cfg: Config) -> bool:
    """A bf16 run on the CPU: trained under ``cpu_autocast``, sampled by a bf16 copy (or, under
    LoRA, by the fp32 policy), so sampler and trainer score tokens in different numerics."""
    return runs_on_cpu(cfg) and effective_precision(cfg) == "bf16"


def cpu_autocast(cfg: Config):
    """bf16 autocast for a CPU run's training forward, entered once around a whole micro-batch.

    Autocast casts each fp32 weight to bf16 when an op first uses it and keeps the cast until
    the outermost autocast block exits, so the weights are cast once per micro-batch; the
    master weights, their gradients and AdamW stay fp32. (accelerate's mixed precision wraps
    every forward call in its own block, which re-casts every weight at each call; on a CPU the
    course does it here instead. On a GPU accelerate's autocast is kept.) Sampling uses a bf16
    copy instead (``sampling_model``)."""
    if cpu_bf16(cfg):
        return torch.autocast("cpu", dtype=torch.bfloat16)
    return contextlib.nullcontext()


def setup(cfg: Config, init_from: str | Path | None = None) -> Policy:
    """Load tokenizer, policy (and reference model if kl_coef > 0), optimizer and scheduler."""
    from accelerate import Accelerator
    from accelerate.state import AcceleratorState, PartialState

    torch.manual_seed(cfg.seed)
    precision = effective_precision(cfg)
    on_cpu = runs_on_cpu(cfg)
    # a CPU run's bf16 is cpu_autocast's (see there), so accelerate is told "no"
    mixed = "no" if precision == "fp32" or (precision == "bf16" and on_cpu) else precision
    if cfg.precision == "auto":
        print(f"[course_utils] precision auto: {precision} "
              f"({'bf16 matrix units found' if precision == 'bf16' else 'no native bf16 on this machine'})")
    if on_cpu:
        cpu.keep_freed_memory()
    cpu_only = cfg.device == "cpu"
    device_changed = PartialState._shared_state.get("_cpu", cpu_only) != cpu_only
    if AcceleratorState._shared_state.get("_mixed_precision", mixed) != mixed or device_changed:
        # accelerate keeps one configuration per process; without this, a notebook that trains
        # again with another precision or device would be told to restart its runtime.
        AcceleratorState._reset_state(reset_partial_state=device_changed)
    accelerator = Accelerator(mixed_precision=mixed, cpu=cpu_only)
    tokenizer = models.load_tokenizer(cfg.model)
    if cfg.lora_rank:  # the base weights always come from cfg.model; a checkpoint holds adapters
        model = models.load_policy(cfg.model, seed=cfg.seed)
    else:
        model = (models.load_policy(str(init_from)) if init_from else
                 models.load_policy(cfg.model, seed=cfg.seed))
    if cfg.gradient_checkpointing:
        models.enable_checkpointing(model)
    if cfg.lora_rank:
        model = models.add_lora(model, cfg.lora_rank, cfg.lora_alpha, adapter_dir=init_from)
    ref_model = None
    if cfg.kl_coef > 0 and not cfg.lora_rank:
        # No reference model at all when beta = 0 (it would only cost memory); under LoRA the
        # reference is the same network with its adapters switched off (see reference_logprobs).
        ref_model = models.load_policy(cfg.model, seed=cfg.seed).to(accelerator.device)
        ref_model.requires_grad_(False)
    trainable = [p for p in model.parameters() if p.requires_grad]  # all, or LoRA's adapters
    if cfg.optimizer == "adamw_8bit":  # availability checked by Config.validate
        import bitsandbytes as bnb
        optimizer = bnb.optim.AdamW8bit(trainable, lr=cfg.lr, weight_decay=cfg.weight_decay)
    else:
        # fused: one pass over each weight instead of a dozen elementwise kernels, several times
        # faster on the CPU (benchmarks/RESULTS.md, from kernels.py). The GPU keeps the default,
        # whose interplay with fp16's gradient scaler is the one the T4 recipe was checked with.
        optimizer = torch.optim.AdamW(trainable, lr=cfg.lr, weight_decay=cfg.weight_decay,
                                      fused=True if on_cpu and cfg.fast_kernels else None)
    warmup = max(cfg.warmup_steps, 0)
    scheduler = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda step: min(1.0, (step + 1) / (warmup + 1)) if warmup else 1.0)
    # No DistributedDataParallel wrapper, even with several processes: grpo_step adds the
    # processes' gradients itself (one all-reduce per update), which also keeps the shared-prompt
    # forward (two model calls per backward) simple. evaluation_mode still places the model on
    # the device and applies the mixed-precision autocast to its forward.
    sampler = None
    if cpu_bf16(cfg) and not cfg.lora_rank:
        import copy

        sampler = copy.deepcopy(model).to(torch.bfloat16).requires_grad_(False)
        # Training forwards whole sequences: there, on a CPU, eager attention's plain matrix
        # products beat the SDPA kernel's backward at these short lengths; the sampler decodes
        # one token at a time and keeps SDPA (timed by benchmarks/kernels.py, in RESULTS.md).
        model.set_attn_implementation("eager")
    model = accelerator.prepare_model(model, evaluation_mode=True)
    optimizer = accelerator.prepare_optimizer(optimizer)
    # one sampling stream per process (process 0's is the single-process run's)
    generator = torch.Generator(device=accelerator.device).manual_seed(
        cfg.seed + 1_000_003 * accelerator.process_index)
    return Policy(cfg=cfg, model=model, tokenizer=tokenizer, optimizer=optimizer,
                  scheduler=scheduler, accelerator=accelerator,
                  eos_ids=models.eos_token_ids(accelerator.unwrap_model(model), tokenizer),
                  generator=generator, ref_model=ref_model, sampler=sampler,
                  kl_schedule=losses.RewardAwareKL(cfg.kl_coef) if cfg.kl_schedule == "reward_aware" else None,
                  entropy_control=losses.AdaptiveEntropy(cfg.entropy_target, cfg.entropy_coef,
                                                         cfg.entropy_weight_max)
                  if cfg.entropy_bonus == "adaptive" else None)


def batch_for_step(step: int, prompts: list[data.Prompt], cfg: Config) -> list[data.Prompt]:
    """The prompts of global step ``step``: a seeded shuffle per epoch, so a resumed run sees
    exactly the batches an uninterrupted one would."""
    epoch, index = divmod(step, cfg.steps_per_epoch)
    order = torch.randperm(len(prompts), generator=torch.Generator().manual_seed(cfg.seed * 1000 + epoch))
    B = cfg.prompts_per_step
    return [prompts[int(order[k % len(prompts)])] for k in range(index * B, (index + 1) * B)]


def refill_batch(step: int, round: int, prompts: list[data.Prompt], cfg: Config) -> list[data.Prompt]:
    """Fresh prompts for round ``round`` (1, 2, ...) of dynamic sampling at global step ``step``:
    a draw seeded by (seed, step, round), so a resumed run samples exactly the same ones."""
    g = torch.Generator().manual_seed((cfg.seed * 1_000_003 + step) * 1_009 + round)
    order = torch.randperm(len(prompts), generator=g)
    return [prompts[int(order[k % len(prompts)])] for k in range(cfg.prompts_per_step)]


def _generator_states(policy: Policy) -> torch.Tensor:
    """Every process's sampling-generator state, one row per process (called by all of them)."""
    state = policy.generator.get_state()
    acc = policy.accelerator
    if acc.num_processes == 1:
        return state[None]
    return acc.gather(state.to(acc.device)[None]).cpu()


def _trainer_state(policy: Policy, step: int, generators: torch.Tensor) -> dict:
    return dict(step=step, optimizer=policy.optimizer.state_dict(),
                scheduler=policy.scheduler.state_dict(), generator=generators,
                torch_rng=torch.get_rng_state(), counters=dict(policy.counters),
                kl_schedule=policy.kl_schedule.state_dict() if policy.kl_schedule else None,
                entropy_control=policy.entropy_control.state_dict() if policy.entropy_control else None,
                priority=policy.priority.state_dict() if policy.priority else None,
                config=policy.cfg.to_dict())


NOTEBOOK_RESUME = "run train.train(cfg, resume=True) again (in a notebook: run the training cell again)"


def train(cfg: Config, resume: bool = False, progress: bool = True, overwrite: bool = False,
          how_to_resume: str = NOTEBOOK_RESUME) -> dict:
    """The main job: evaluate, train with GRPO, evaluate again; write everything to out_dir.

    A fresh run refuses a directory that already holds a run unless ``overwrite``; ``resume``
    continues from the last whole checkpoint (or starts a run that stopped before its first
    one). SIGINT or SIGTERM stops after the step in flight with a checkpoint saved, and raises
    ``interrupt.Interrupted`` whose message ends with ``how_to_resume``."""
    started = time.perf_counter()
    cfg.validate()
    if resume and overwrite:
        raise ConfigError("resume and overwrite contradict each other: resume continues the run "
                          "in out_dir, overwrite deletes it; choose one")
    models.check_available(cfg.model)           # fail before anything slow or written happens
    plan.check_fits(cfg, models.architecture(cfg.model), *device_memory(cfg))
    run_dir = Path(cfg.out_dir)
    # The lock comes first: nothing in run_dir is read or written without it. Under accelerate
    # every process runs this function on the same run_dir; the first one (rank 0) holds it.
    first_process = os.environ.get("RANK", "0") == "0"
    try:
        with checkpoint.RunLock(run_dir) if first_process else contextlib.nullcontext():
            with interrupt.StopRequests(how_to_resume) as stop:
                return _train_in(run_dir, cfg, resume, overwrite, progress, started, stop)
    except OSError as err:   # out_dir a file, read-only, full, ...: the path and the cause
        readable = checkpoint.filesystem_error(err, run_dir)
        if readable is None:
            raise
        raise readable from None


def device_memory(cfg: Config) -> tuple[int | None, str]:
    """The memory of the device the run will use, in bytes (None if unknown), and its name."""
    if cfg.device in ("auto", "cuda") and torch.cuda.is_available():
        return torch.cuda.get_device_properties(0).total_memory, torch.cuda.get_device_name(0)
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"), "this machine's RAM"
    except (ValueError, OSError, AttributeError):  # pragma: no cover - no sysconf (Windows)
        return None, "this machine"


def _open_run(run_dir: Path, cfg: Config, resume: bool,
              overwrite: bool) -> tuple[Path | None, dict | None]:
    """Make ``run_dir`` ready for this invocation; return the checkpoint to resume from and its
    trainer state (loaded once here: with the optimizer's moments it is the largest file).

    Refuses, rather than guesses, whenever the directory's contents do not fit the request:
    a fresh run over an existing one (without ``overwrite``), or a resume whose checkpoint,
    log and summary do not belong together."""
    run_dir.mkdir(parents=True, exist_ok=True)
    checkpoint.remove_leftovers(run_dir)
    contents = checkpoint.run_contents(run_dir)
    if not resume:
        if contents and not overwrite:
            raise checkpoint.CheckpointError(
                f"{run_dir} already holds a run ({', '.join(contents)}): continue it with --resume "
                f"(resume=True), replace it with --overwrite (overwrite=True), or choose another "
                f"out_dir")
        return None, None   # cleared by _train_in once the model and prompts are ready
    if not contents:
        print(f"[course_utils] {run_dir} holds no run to resume: starting a new one there")
        return None, None
    fix = "restore the file, or start over with --overwrite (overwrite=True)"
    log = checkpoint.MetricsLog(run_dir / "metrics.jsonl")
    logged = log.read()
    last_logged = logged[-1]["step"] if logged else 0
    summary_path = run_dir / "summary.json"
    summary = checkpoint.read_json(summary_path, fix) if summary_path.exists() else {}
    found = checkpoint.find(run_dir)
    if found is None:
        # only a run that stopped before its first checkpoint may start again from step 0 (its
        # log may hold that step: the record is appended before the checkpoint is written)
        saved_path = run_dir / "config.json"
        saved = checkpoint.read_json(saved_path, fix) if saved_path.exists() else None
        different = checkpoint.config_differences(saved, cfg.to_dict()) if saved else ""
        first_save = (saved or {}).get("save_every", cfg.save_every)
        why = ("its config.json is another run's (" + different + ")" if different else
               "it is a finished run" if "after" in summary else
               f"its metrics reach step {last_logged}, past the first checkpoint at step "
               f"{first_save}" if last_logged > first_save else "")
        if why:
            raise checkpoint.CheckpointError(
                f"{run_dir} has no checkpoint to resume from, and starting it again would overwrite "
                f"it: {why}. Start over with --overwrite (overwrite=True), or use another out_dir")
        print(f"[course_utils] {run_dir} stopped before its first checkpoint: starting it again")
        return None, None
    state = checkpoint.load_state(found, cfg.to_dict())
    step = state["step"]
    if "before" not in summary:
        raise checkpoint.CheckpointError(
            f"{summary_path} is missing or has no before-training evaluation, so the run's "
            f"before/after comparison cannot be completed: restore the file, or start over with "
            f"--overwrite (overwrite=True)")
    if last_logged < step:
        raise checkpoint.CheckpointError(
            f"{log.path} ends at step {last_logged} but the checkpoint is at step {step}: steps are "
            f"missing from the log. Restore it, or start over with --overwrite (overwrite=True)")
    return found, state


def _train_in(run_dir: Path, cfg: Config, resume: bool, overwrite: bool, progress: bool,
              started: float, stop: interrupt.StopRequests) -> dict:
    """``train``'s body, run while the run directory is locked."""
    from tqdm.auto import tqdm

    if int(os.environ.get("WORLD_SIZE", "1")) == 1:
        found, state = _open_run(run_dir, cfg, resume, overwrite)
    else:  # accelerate launch: the first process readies run_dir; the others then only look
        from accelerate.state import PartialState

        first = os.environ.get("RANK") == "0"
        found, state = _open_run(run_dir, cfg, resume, overwrite) if first else (None, None)
        PartialState(cpu=cfg.device == "cpu").wait_for_everyone()
        if not first and resume:
            found = checkpoint.find(run_dir)
            state = checkpoint.load_state(found, cfg.to_dict()) if found else None
    summary_path = run_dir / "summary.json"
    summary = checkpoint.read_json(summary_path, "restore the file, or start over with --overwrite "
                                   "(overwrite=True)") if (state and summary_path.exists()) else {}
    if state and state["step"] >= cfg.total_steps and "after" in summary:
        # a re-run cell or command on a finished run: nothing to train. The report and the
        # curves are derived from summary.json and metrics.jsonl, so a run killed between
        # writing those and them (or whose copies were deleted) gets them back here.
        missing = [n for n in ("report.md", "curves.png") if not (run_dir / n).exists()]
        if missing and os.environ.get("RANK", "0") == "0":
            _write_report(run_dir, summary, cfg)
            print(f"[course_utils] {run_dir} is finished; rewrote {' and '.join(missing)}")
        else:
            print(f"[course_utils] {run_dir} is finished ({summary.get('steps', state['step'])} "
                  f"steps): nothing to do")
        return summary

    stop.checkpoint_step = state["step"] if state else None
    policy = setup(cfg, init_from=found)
    # With several processes (accelerate launch) all of them train; only the main one evaluates
    # and writes files (the model is the same on every process after each step).
    main = policy.accelerator.is_main_process
    log = checkpoint.MetricsLog(run_dir / "metrics.jsonl")
    start_step = 0
    if state:
        policy.optimizer.load_state_dict(state["optimizer"])
        policy.scheduler.load_state_dict(state["scheduler"])
        generators = state["generator"]
        if generators.dim() == 1:  # a checkpoint written before states were kept per process
            generators = generators[None]
        if len(generators) != policy.accelerator.num_processes:
            raise checkpoint.CheckpointError(
                f"the checkpoint in {found} was written by {len(generators)} process(es); resume "
                f"it with the same number ({policy.accelerator.num_processes} now)")
        policy.generator.set_state(generators[policy.accelerator.process_index].clone())
        torch.set_rng_state(state["torch_rng"])
        policy.counters.update(state["counters"])
        if policy.kl_schedule:
            policy.kl_schedule.load_state_dict(state["kl_schedule"])
        if policy.entropy_control:
            policy.entropy_control.load_state_dict(state["entropy_control"])
        start_step = state["step"]
        if main:
            log.truncate_after(start_step)
            print(f"[course_utils] resumed from {found} at step {start_step}")

    train_prompts = data.make_prompts(cfg, policy.tokenizer, held_out=False)
    eval_prompts = data.make_prompts(cfg, policy.tokenizer, held_out=True)
    # Only now, with the model and the prompts ready, is a run's file replaced: a run refused
    # above (a dataset offline, a model that does not load) or stopped during set-up leaves the
    # directory's run as it was, so the corrected command runs without --overwrite, and
    # --overwrite does not delete a run for a command that fails while setting up.
    if main and state is None:
        checkpoint.clear(run_dir)
    if main:
        checkpoint.write_json(run_dir / "config.json", cfg.to_dict())
    stop.started = True
    if cfg.target_sampling == "prioritized":
        policy.priority = curriculum.TargetPriority(train_prompts)
        if state:
            policy.priority.load_state_dict(state["priority"])
    model = policy.model

    if "before" not in summary and main:
        sampler = sampling_model(policy)   # refreshed once for both evaluations
        summary["before"] = {mode: evaluate(sampler, policy.tokenizer, eval_prompts, cfg,
                                            policy.eos_ids, greedy=mode == "greedy")
                             for mode in ("sampled", "greedy")}
        checkpoint.write_json(summary_path, summary)
        _print_eval("before training", summary["before"])

    total = cfg.total_steps
    bar = tqdm(range(start_step, total), initial=start_step, total=total, desc="GRPO",
               disable=not (progress and main))
    for step in bar:
        stop.deferring = True   # a signal from here on ends this step first (see interrupt.py)
        if policy.priority:   # hardest targets first for the curriculum's steps
            if step < cfg.hard_first_steps:
                scale = step / cfg.hard_first_steps if cfg.hard_first_ramp else 0.0
                batch = policy.priority.batch(cfg.seed, step, cfg.prompts_per_step,
                                              only=policy.priority.hardest(), others_scale=scale)
            else:
                batch = policy.priority.batch(cfg.seed, step, cfg.prompts_per_step)
        else:
            batch = batch_for_step(step, train_prompts, cfg)
        metrics = grpo_step(policy, batch,
                            refill=lambda k, step=step: refill_batch(step, k, train_prompts, cfg))
        record = dict(step=step + 1, epoch=step // cfg.steps_per_epoch, **metrics)
        if cfg.eval_every and (step + 1) % cfg.eval_every == 0 and step + 1 < total and main:
            ev = evaluate(sampling_model(policy), policy.tokenizer, eval_prompts, cfg, policy.eos_ids,
                          greedy=False)
            record.update({f"eval_{k}": v for k, v in ev.items() if k != "samples"})
        if main:
            log.append(record)
        if "reward_mean" in metrics:   # absent from a step skipped for non-finite sampling logits
            bar.set_postfix(reward=f"{metrics['reward_mean']:.3f}", len_ok=f"{metrics['pass_length']:.2f}",
                            both=f"{metrics['pass_both']:.2f}")
        saved = (step + 1) % cfg.save_every == 0 or step + 1 == total
        if saved:
            _save(run_dir, policy, step + 1)
            stop.checkpoint_step = step + 1
        if _agree(policy, stop.requested):   # every process stops after the same step
            if not saved:
                _save(run_dir, policy, step + 1)
                stop.checkpoint_step = step + 1
            bar.close()
            raise stop.stopped(step + 1, total)
        stop.deferring = False
    if not main:
        return {}

    sampler = sampling_model(policy)
    summary["after"] = {mode: evaluate(sampler, policy.tokenizer, eval_prompts, cfg,
                                       policy.eos_ids, greedy=mode == "greedy")
                        for mode in ("sampled", "greedy")}
    # the steps the model has taken: a checkpoint resumed with a smaller max_steps is past it
    summary["steps"] = max(start_step, total)
    # wall time, evaluation included, summed over the invocations that finished: a run that
    # finished and was then extended (--resume with a larger --max_steps) adds this one's time
    # to the first; an invocation that crashed wrote no time, so its lost work is not counted
    summary["seconds"] = summary.get("seconds", 0.0) + time.perf_counter() - started
    summary["resumed"] = bool(state)
    # what 'auto' resolved to, and the CPU kernels torch picked: runs on two machines compare
    # only when these agree (lesson 7, section 6.5)
    summary["precision"] = effective_precision(cfg)
    summary["cpu_capability"] = torch.backends.cpu.get_cpu_capability()
    summary["cpu"] = cpu.machine()   # the capability alone does not tell AMX from AVX512-BF16
    checkpoint.write_json(summary_path, summary)
    print(_write_report(run_dir, summary, cfg))
    return summary


def _write_report(run_dir: Path, summary: dict, cfg: Config) -> str:
    """The files derived from summary.json and metrics.jsonl: curves.png and report.md (the
    report last and atomically, so its presence means both were written)."""
    from .plots import plot_metrics

    plot_metrics(checkpoint.MetricsLog(run_dir / "metrics.jsonl").read(), run_dir / "curves.png")
    report = before_after_report(summary, cfg)
    checkpoint.write_text(run_dir / "report.md", report)
    return report


def _save(run_dir: Path, policy: Policy, step: int) -> None:
    generators = _generator_states(policy)  # a collective: every process takes part
    if policy.accelerator.is_main_process:
        checkpoint.save(run_dir, policy.accelerator.unwrap_model(policy.model), policy.tokenizer,
                        _trainer_state(policy, step, generators))


def _agree(policy: Policy, requested: bool) -> bool:
    """Whether any process was asked to stop (with one process: whether this one was)."""
    if policy.accelerator.num_processes == 1:
        return requested
    flag = torch.tensor([float(requested)], device=policy.accelerator.device)
    return bool(policy.accelerator.reduce(flag, reduction="sum").item() > 0)


def _print_eval(title: str, result: dict) -> None:
    for mode, r in result.items():
        print(f"[course_utils] {title} ({mode}): reward {r['reward_mean']:.3f}, length pass "
              f"{r['pass_length']:.1%}, digit pass {r['pass_digits']:.1%}, both {r['pass_both']:.1%}, "
              f"mean |chars - target| {r['chars_abs_error']:.1f}")


def before_after_report(summary: dict, cfg: Config, n_samples: int = 6) -> str:
    """A Markdown before/after table of held-out metrics and sample completions."""
    first = summary["before"]["greedy"]
    rows = [("mean reward", "reward_mean", "{:.3f}"), ("length pass rate", "pass_length", "{:.1%}"),
            ("digit-sum pass rate", "pass_digits", "{:.1%}"), ("both (recipe pass rate)", "pass_both", "{:.1%}"),
            (f"both, one-digit targets ({first.get('n_one_digit', '?')} prompts)", "pass_both_one_digit", "{:.1%}"),
            (f"both, two-digit targets ({first.get('n_two_digit', '?')} prompts)", "pass_both_two_digit", "{:.1%}"),
            ("distinct completions", "distinct_completions", "{}"),
            ("mean abs(chars - target)", "chars_abs_error", "{:.1f}")]
    n_eval = len(summary["before"]["sampled"]["samples"])
    n_snippets = first.get("distinct_snippets", "?")
    lines = [f"## Held-out evaluation: {n_eval} prompts ({n_snippets} distinct held-out snippets, "
             f"each with its own drawn digit-sum targets), {summary.get('steps', '?')} GRPO steps, "
             f"model {cfg.model}, reward '{cfg.reward}'", "",
             "| metric | before (sampled) | after (sampled) | before (greedy) | after (greedy) |",
             "|---|---|---|---|---|"]
    for label, key, fmt in rows:
        vals = [fmt.format(summary[when][mode][key]) if key in summary[when][mode] else "n/a"
                for mode in ("sampled", "greedy") for when in ("before", "after")]
        lines.append(f"| {label} | " + " | ".join(vals) + " |")
    lines += ["", "### Sample completions (greedy), targets: characters / digit sum", "",
              "| target | before | chars / sum | after | chars / sum |", "|---|---|---|---|---|"]
    before, after = summary["before"]["greedy"]["samples"], summary["after"]["greedy"]["samples"]
    for b, a in list(zip(before, after))[:n_samples]:
        def cell(t: str) -> str:
            return t.replace("|", "\\|").replace("\n", " ")[:80]
        lines.append(f"| {b['target_chars']} / {b['target_digit_sum']} | {cell(b['completion'])} | "
                     f"{b['n_chars']} / {b['digit_sum']} | {cell(a['completion'])} | "
                     f"{a['n_chars']} / {a['digit_sum']} |")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------------------------


def _parse(raw: str, annotation: str, name: str):
    """Turn a command-line string into the field's type (the annotations are strings)."""
    if "None" in annotation and raw.lower() == "none":
        return None
    try:
        if annotation.startswith("bool"):
            if raw.lower() in {"1", "true", "yes"}:
                return True
            if raw.lower() in {"0", "false", "no"}:
                return False
            raise ValueError
        # int() and float() also read other scripts' digits ("٣" is 3) and "1_000": a number on
        # the command line is written in ASCII, as everywhere else in a run's files
        if annotation.startswith("int"):
            if not re.fullmatch(r"[+-]?[0-9]+", raw.strip()):
                raise ValueError
            return int(raw)
        if annotation.startswith("float"):
            if not raw.strip().isascii() or "_" in raw:
                raise ValueError
            return float(raw)
    except ValueError:
        raise ConfigError(f"--{name} {raw!r} is not a valid {annotation.split(' ')[0]}") from None
    return raw


class _OneLineParser(argparse.ArgumentParser):
    """argparse, with its errors as the one-line ``error:`` every config error gets (not a
    33-line usage dump), and a close match suggested for a misspelt option."""

    def error(self, message: str):
        unknown = re.search(r"unrecognized arguments: (\S+)", message)
        if unknown:
            options = [o for a in self._actions for o in a.option_strings]
            guess = unknown.group(1).split("=")[0].replace("-", "_").lstrip("_")
            close = difflib.get_close_matches("--" + guess, options, n=1)
            message += f" (did you mean {close[0]}?)" if close else ""
        raise SystemExit(f"error: {message}; see python -m course_utils.train --help")


def _join_negative_values(argv: list[str]) -> list[str]:
    """``--lr -1e-3`` as ``--lr=-1e-3``: argparse reads a value that starts with '-' and is not
    a plain decimal as an option and says "expected one argument", hiding the real problem (a
    negative learning rate), which the config check then names."""
    fields = {f"--{name}" for name in Config.__dataclass_fields__}
    out, i = [], 0
    while i < len(argv):
        if argv[i] in fields and i + 1 < len(argv) and re.fullmatch(r"-[0-9.][0-9.eE+-]*|-inf|-nan",
                                                                     argv[i + 1]):
            out.append(f"{argv[i]}={argv[i + 1]}")
            i += 2
        else:
            out.append(argv[i])
            i += 1
    return out


def build_parser() -> argparse.ArgumentParser:
    parser = _OneLineParser(
        prog="python -m course_utils.train",
        description="GRPO on the rule-following task: evaluate, train, evaluate again.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--preset", default="smoke" if smoke_mode() else "cpu",
                        help=f"one of {', '.join(PRESETS)} (smoke when COURSE_SMOKE=1)")
    parser.add_argument("--resume", action="store_true", help="continue from out_dir's checkpoint")
    parser.add_argument("--overwrite", action="store_true",
                        help="delete the run already in out_dir and start a new one")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    for f in Config.__dataclass_fields__.values():
        parser.add_argument(f"--{f.name}", default=None, metavar=str(f.type).split(" ")[0].upper(),
                            help=f.metadata.get("help", ""))
    return parser


def resume_command(args: argparse.Namespace) -> str:
    """The command that continues this run, rebuilt from the parsed arguments (so an abbreviated
    ``--overwr`` or ``--res`` never survives into it): the preset, every option given, and
    --resume."""
    again = ["python", "-m", "course_utils.train", "--preset", args.preset]
    for name in Config.__dataclass_fields__:
        value = getattr(args, name)
        if value is not None:
            again += [f"--{name}={value}"] if value.startswith("-") else [f"--{name}", value]
    if args.no_progress:
        again.append("--no-progress")
    return shlex.join(again + ["--resume"])


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(_join_negative_values(argv))
    try:  # a value that is not of its field's type is a config error like any other: one line
        overrides = {name: _parse(getattr(args, name), str(f.type), name)
                     for name, f in Config.__dataclass_fields__.items() if getattr(args, name) is not None}
        cfg = load_config(args.preset, **overrides)
    except ConfigError as err:
        raise SystemExit(f"error: {err}") from None
    print(f"[course_utils] preset {args.preset}: {cfg.total_steps} steps of {cfg.prompts_per_step} "
          f"prompts x {cfg.group_size} completions, model {cfg.model}, writing to {cfg.out_dir}")
    how_to_resume = "run: " + resume_command(args)
    if args.no_progress:   # transformers' own bars too ("Loading weights", "Writing model shards")
        from transformers.utils import logging as transformers_logging

        transformers_logging.disable_progress_bar()
    try:
        train(cfg, resume=args.resume, progress=not args.no_progress, overwrite=args.overwrite,
              how_to_resume=how_to_resume)
    except (models.ModelNotAvailable, data.DataUnavailable, checkpoint.CheckpointError,
            RewardError, ConfigError) as err:
        raise SystemExit(f"error: {err}") from None
    except interrupt.Interrupted as stopped:
        print(f"[course_utils] {stopped}", file=sys.stderr)
        return stopped.exit_code
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
