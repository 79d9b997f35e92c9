"""Checkers for the lessons' exercises.

Each ``check_*`` function calls the learner's implementation on seeded random inputs, compares
with the reference implementation in this library, and *raises* ``ExerciseError`` when they
differ, so the notebook (and nbmake) stops at that cell. Before giving a generic "differs"
message, it tries the mistakes learners actually make (a flipped sign, padding counted, the
wrong normalization, ...) and, when the answer matches one, says which.
"""

from __future__ import annotations

import math
from typing import Callable

import torch

from . import losses
from .rollout import completion_mask as reference_completion_mask


class ExerciseError(AssertionError):
    """The implementation is wrong; the message says how, when the checker can tell."""


def _call(name: str, fn: Callable, *args, **kwargs):
    try:
        return fn(*args, **kwargs)
    except NotImplementedError:
        raise ExerciseError(f"{name}: not implemented yet. Replace `raise NotImplementedError` "
                            f"with your code, then run this cell again.") from None


def _as_tensor(name: str, x) -> torch.Tensor:
    if not isinstance(x, torch.Tensor):
        raise ExerciseError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    return x


def _close(a: torch.Tensor, b: torch.Tensor, tol: float) -> bool:
    return (a.shape == b.shape and bool(torch.isfinite(a).all() == torch.isfinite(b).all())
            and torch.allclose(a.double(), b.double(), atol=tol, rtol=tol, equal_nan=True))


def _judge(name: str, got, want: torch.Tensor, mistakes: dict[str, torch.Tensor], tol: float = 1e-5):
    got = _as_tensor(name, got).detach()
    if got.shape != want.shape:
        raise ExerciseError(f"{name}: wrong shape {tuple(got.shape)}, expected {tuple(want.shape)}")
    if _close(got, want, tol):
        print(f"✓ {name}: correct")
        return
    for message, value in mistakes.items():
        if _close(got, value.detach(), tol):
            raise ExerciseError(f"{name}: {message}")
    if not torch.isfinite(got).all() and torch.isfinite(want).all():
        raise ExerciseError(f"{name}: your result has NaN or inf where the reference is finite")
    diff = (got.double() - want.double()).abs().max().item()
    raise ExerciseError(f"{name}: differs from the reference by up to {diff:.3g} on a seeded "
                        f"random input. Re-read the formula in the cell above.")


# ----------------------------------------------------------------------------------------------
# Lesson 1: the policy-gradient theorem
# ----------------------------------------------------------------------------------------------


def check_score_function_gradient(fn: Callable) -> None:
    """fn(theta [K], actions [n], rewards [n]) -> [K]: (1/n) sum_i r_i grad log pi(a_i)."""
    name = "Exercise 1.1 (score-function gradient)"
    g = torch.Generator().manual_seed(11)
    theta = torch.randn(5, generator=g)
    actions = torch.randint(0, 5, (64,), generator=g)
    rewards = torch.randn(64, generator=g)
    pi = torch.softmax(theta, -1)
    score = torch.nn.functional.one_hot(actions, 5).double() - pi.double()  # grad log pi(a)
    want = (rewards.double()[:, None] * score).mean(0)
    mistakes = {
        "sign flipped: you returned minus the gradient (that is a loss's gradient, not J's)": -want,
        "summed over samples instead of averaging: divide by the number of samples": want * 64,
        "used grad pi(a) instead of grad log pi(a): the log-derivative trick needs the log":
            (rewards.double()[:, None] * pi.double()[actions][:, None] * score).mean(0),
        "forgot to weight by the reward": score.mean(0),
    }
    _judge(name, _call(name, fn, theta.clone(), actions.clone(), rewards.clone()), want, mistakes)


def check_sequence_log_prob(fn: Callable) -> None:
    """fn(logits [N, T, V], tokens [N, T]) -> [N]: sum_t log softmax(logits_t)[token_t]."""
    name = "Exercise 1.2 (log-probability of a sequence)"
    g = torch.Generator().manual_seed(12)
    logits = torch.randn(4, 6, 7, generator=g)
    tokens = torch.randint(0, 7, (4, 6), generator=g)
    logp = torch.log_softmax(logits, -1).gather(-1, tokens.unsqueeze(-1)).squeeze(-1)
    want = logp.sum(-1)
    raw = logits.gather(-1, tokens.unsqueeze(-1)).squeeze(-1)
    mistakes = {
        "averaged over tokens: a sequence's log-probability is the SUM of its tokens' (chain rule)": logp.mean(-1),
        "used raw logits: normalize with log_softmax first": raw.sum(-1),
        "returned a probability, not a log-probability": logp.sum(-1).exp(),
        "off by one position: token t is scored by the logits at position t": torch.cat(
            [logp[:, :1] * 0, torch.log_softmax(logits, -1)[:, :-1].gather(-1, tokens[:, 1:].unsqueeze(-1)).squeeze(-1)], -1).sum(-1),
    }
    _judge(name, _call(name, fn, logits.clone(), tokens.clone()), want, mistakes)


def check_surrogate_loss(fn: Callable) -> None:
    """fn(seq_logprobs [N] with grad, rewards [N]) -> scalar loss whose gradient is minus the
    REINFORCE estimate: d loss / d logp_i = -r_i / N."""
    name = "Exercise 1.3 (surrogate loss)"
    g = torch.Generator().manual_seed(13)
    logp = torch.randn(8, generator=g).requires_grad_()
    rewards = torch.randn(8, generator=g)
    loss = _call(name, fn, logp, rewards.clone())
    loss = _as_tensor(name, loss)
    if loss.dim() != 0:
        raise ExerciseError(f"{name}: the loss must be a scalar, got shape {tuple(loss.shape)}")
    if not loss.requires_grad:
        raise ExerciseError(f"{name}: the loss carries no gradient; did you detach the log-probs?")
    (grad,) = torch.autograd.grad(loss, logp)
    want = -rewards / 8
    mistakes = {
        "sign flipped: minimizing this loss must INCREASE the log-probability of high-reward samples": -want,
        "summed instead of averaged over samples": want * 8,
    }
    _judge(name + " gradient", grad, want, mistakes)


# ----------------------------------------------------------------------------------------------
# Lesson 2: REINFORCE on token sequences
# ----------------------------------------------------------------------------------------------


def check_returns_to_go(fn: Callable) -> None:
    """fn(rewards [N, T], gamma) -> [N, T]: G_t = sum_{k >= t} gamma^(k - t) r_k."""
    name = "Exercise 2.1 (returns-to-go)"
    g = torch.Generator().manual_seed(21)
    rewards = torch.randn(3, 6, generator=g)
    for gamma in (1.0, 0.9):
        want = losses.returns_to_go(rewards, gamma)
        mistakes = {"summed the PAST rewards (k <= t); the return-to-go sums the future (k >= t)":
                    torch.flip(losses.returns_to_go(torch.flip(rewards, [-1]), gamma), [-1])}
        if gamma != 1.0:  # these two mistakes coincide with the right answer when gamma = 1
            powers = gamma ** torch.arange(rewards.shape[-1], dtype=torch.float32)
            mistakes["discounted by gamma^k from the start; it must be gamma^(k - t), relative to t"] = \
                torch.flip(torch.cumsum(torch.flip(rewards * powers, [-1]), -1), [-1])
            mistakes["ignored gamma"] = losses.returns_to_go(rewards, 1.0)
        _judge(f"{name}, gamma={gamma}", _call(name, fn, rewards.clone(), gamma), want, mistakes)


def check_masked_reinforce_loss(fn: Callable) -> None:
    """fn(logprobs [N, T], returns [N, T], mask [N, T]) -> scalar:
    -(1/N) sum_i sum_t mask_it * logprob_it * return_it."""
    name = "Exercise 2.2 (masked REINFORCE loss)"
    g = torch.Generator().manual_seed(22)
    logp = -torch.rand(4, 5, generator=g) * 3
    returns = torch.randn(4, 5, generator=g)
    mask = torch.tensor([[1, 1, 1, 1, 1], [1, 1, 1, 0, 0], [1, 0, 0, 0, 0], [1, 1, 0, 0, 0]])
    want = -(logp * returns * mask).sum(-1).mean()
    mistakes = {
        "padding tokens counted: multiply by the mask": -(logp * returns).sum(-1).mean(),
        "sign flipped: the loss is MINUS the objective": -want,
        "averaged over tokens; the spec sums over a sequence's tokens and averages over sequences":
            -(logp * returns * mask).sum() / mask.sum(),
        "summed over sequences too: average over the N sequences": want * 4,
    }
    _judge(name, _call(name, fn, logp.clone(), returns.clone(), mask.clone()), want, mistakes)


def check_completion_mask(fn: Callable) -> None:
    """fn(ids [N, T], eos_id) -> [N, T] 0/1: 1 up to and including the first EOS."""
    name = "Exercise 2.3 (completion mask with pad == EOS)"
    eos = 2
    ids = torch.tensor([[5, 6, eos, eos, eos], [7, eos, eos, eos, eos], [eos, eos, eos, eos, eos],
                        [5, 6, 7, 8, 9], [5, eos, 6, eos, eos]])
    want = reference_completion_mask(ids, [eos])
    kept = want.sum(-1, keepdim=True)                  # tokens kept per row
    has_eos = (ids == eos).any(-1, keepdim=True)
    pos = torch.arange(ids.shape[1])
    mistakes = {
        "built from ids != pad_id: with pad == EOS that drops the real EOS, so the model is never "
        "trained to stop": (ids != eos).long(),
        "excluded the EOS token itself; it must be in the mask (stopping is an action too)":
            torch.where(has_eos, (pos < kept - 1).long(), want),
        "a row without EOS (truncated) must be all ones": torch.where(has_eos, want, torch.zeros_like(want)),
        "kept tokens after a later EOS: the mask ends at the FIRST EOS":
            torch.where(has_eos, (pos <= (ids.shape[1] - 1 - torch.flip(ids == eos, [-1]).int().argmax(-1, keepdim=True))).long(), want),
    }
    got = _call(name, fn, ids.clone(), eos)
    _judge(name, _as_tensor(name, got).long(), want, mistakes)


# ----------------------------------------------------------------------------------------------
# Lesson 3: baselines
# ----------------------------------------------------------------------------------------------


def check_leave_one_out_baseline(fn: Callable) -> None:
    """fn(rewards [N], group_size G) -> [N]: mean of the other G - 1 rewards of the group."""
    name = "Exercise 3.1 (leave-one-out baseline)"
    g = torch.Generator().manual_seed(31)
    rewards = torch.randn(12, generator=g)
    G = 4
    want = losses.leave_one_out_baseline(rewards, G)
    r = rewards.view(-1, G)
    mistakes = {
        "included the sample's own reward (that is the group mean, which is biased)":
            r.mean(-1, keepdim=True).expand_as(r).reshape(-1),
        "divided by G instead of G - 1": ((r.sum(-1, keepdim=True) - r) / G).reshape(-1),
        "used the whole batch instead of the group": (rewards.sum() - rewards) / (len(rewards) - 1),
    }
    _judge(name, _call(name, fn, rewards.clone(), G), want, mistakes)


def check_self_baseline_factor(fn: Callable) -> None:
    """fn(N) -> float: E[estimate with b = mean of all N rewards] / true gradient."""
    name = "Exercise 3.2 (bias of a baseline that includes the sample)"
    for n in (2, 5, 16):
        got = _call(name, fn, n)
        try:
            got = float(got)
        except (TypeError, ValueError):
            raise ExerciseError(f"{name}: return a number, got {got!r}") from None
        want = (n - 1) / n
        if math.isclose(got, want, rel_tol=1e-6):
            continue
        hints = {1.0: "a baseline that contains r_i is NOT independent of a_i: the estimate is biased",
                 n / (n - 1): "inverted: the bias shrinks the gradient",
                 1 / n: "that is the share of r_i in the mean, not what is left of the gradient"}
        for value, message in hints.items():
            if math.isclose(got, value, rel_tol=1e-6):
                raise ExerciseError(f"{name}: N={n}: {message}")
        raise ExerciseError(f"{name}: N={n}: got {got}; work out E[grad log pi(a_i) (r_i - mean)]")
    print(f"✓ {name}: correct")


def check_actor_critic_advantage(fn: Callable) -> None:
    """fn(rewards [N], values [N] with grad) -> [N]: r - V(s), with no gradient into the critic."""
    name = "Exercise 3.3 (advantage from a learned value baseline)"
    g = torch.Generator().manual_seed(33)
    rewards = torch.randn(6, generator=g)
    values = torch.randn(6, generator=g).requires_grad_()
    got = _as_tensor(name, _call(name, fn, rewards.clone(), values))
    want = rewards - values.detach()
    if got.requires_grad:
        raise ExerciseError(f"{name}: the advantage still carries the critic's gradient: detach the "
                            f"values, or the policy loss will train the critic to shrink it")
    _judge(name, got, want, {"sign flipped: the advantage is reward minus baseline": -want})


# ----------------------------------------------------------------------------------------------
# Lesson 4: GRPO
# ----------------------------------------------------------------------------------------------


def check_group_advantages(fn: Callable) -> None:
    """fn(rewards [N], G) -> [N]: (r - group mean) / (group std (Bessel) + 1e-4)."""
    name = "Exercise 4.1 (group-relative advantages)"
    g = torch.Generator().manual_seed(41)
    rewards = torch.cat([torch.randn(8, generator=g), torch.full((4,), 0.5)])  # last group: all equal
    G = 4
    want, _ = losses.group_advantages(rewards, G)
    r = rewards.view(-1, G)
    mistakes = {
        "used the whole batch's mean and std; GRPO standardizes within each prompt's group":
            (rewards - rewards.mean()) / (rewards.std() + 1e-4),
        "used the population std (unbiased=False); use the sample std, as DeepSeekMath and TRL do":
            ((r - r.mean(-1, keepdim=True)) / (r.std(-1, unbiased=False, keepdim=True) + 1e-4)).reshape(-1),
        "no epsilon in the denominator: a group of equal rewards divides 0 by 0":
            ((r - r.mean(-1, keepdim=True)) / r.std(-1, keepdim=True)).reshape(-1),
        "forgot to divide by the std": (r - r.mean(-1, keepdim=True)).reshape(-1),
    }
    _judge(name, _call(name, fn, rewards.clone(), G), want, mistakes)


def check_clipped_surrogate(fn: Callable) -> None:
    """fn(logp, old_logp, advantages [N], eps_low, eps_high) -> per-token loss [N, T]."""
    name = "Exercise 4.2 (clipped surrogate)"
    g = torch.Generator().manual_seed(42)
    old = -torch.rand(6, 5, generator=g) * 2
    logp = old + torch.randn(6, 5, generator=g) * 0.4
    adv = torch.randn(6, generator=g)
    want, _ = losses.clipped_surrogate(logp, old, adv, 0.2, 0.28)
    ratio = (logp - old).exp()
    A = adv[:, None]
    mistakes = {
        "took the max of the objectives (the min of the losses): the clip must be pessimistic":
            torch.minimum(-ratio * A, -ratio.clamp(0.8, 1.28) * A),
        "used eps_low on both sides: the upper clip is 1 + eps_high": losses.clipped_surrogate(logp, old, adv, 0.2, 0.2)[0],
        "no clipping at all": -ratio * A,
        "sign flipped: the loss is minus the objective": -want,
        "clipped the objective but dropped the unclipped branch": -ratio.clamp(0.8, 1.28) * A,
    }
    _judge(name, _call(name, fn, logp.clone(), old.clone(), adv.clone(), 0.2, 0.28), want, mistakes)


def check_k3_kl(fn: Callable) -> None:
    """fn(logp, ref_logp) -> per-token k3 estimate of KL(pi || pi_ref)."""
    name = "Exercise 4.3 (k3 KL estimate)"
    g = torch.Generator().manual_seed(43)
    logp = -torch.rand(4, 6, generator=g) * 3
    ref = logp + torch.randn(4, 6, generator=g) * 0.5
    want = losses.k3_kl(logp, ref)
    d = ref - logp
    mistakes = {
        "that is k1 = log(pi / pi_ref): unbiased but often negative per token": -d,
        "ratio upside down: k3 uses pi_ref / pi_theta": (-d).exp() + d - 1,
        "that is k2 = (log ratio)^2 / 2": 0.5 * d ** 2,
    }
    _judge(name, _call(name, fn, logp.clone(), ref.clone()), want, mistakes)


def check_aggregate(fn: Callable) -> None:
    """fn(per_token [N, T], mask [N, T], loss_type) -> scalar, for "grpo" and "dapo"."""
    name = "Exercise 4.4 (loss aggregation)"
    per_token = torch.tensor([[1.0, 2.0, 3.0, 9.0], [4.0, 9.0, 9.0, 9.0], [0.5, 0.5, 0.5, 0.5]])
    mask = torch.tensor([[1, 1, 1, 0], [1, 0, 0, 0], [1, 1, 1, 1]])
    for loss_type in ("grpo", "dapo"):
        want = losses.aggregate(per_token, mask, loss_type)
        other = losses.aggregate(per_token, mask, "dapo" if loss_type == "grpo" else "grpo")
        mistakes = {
            "padding counted: only real tokens enter the average": per_token.mean(-1).mean()
            if loss_type == "grpo" else per_token.mean(),
            f"that is the other aggregation: '{loss_type}' is "
            + ("the mean per sequence, then over sequences" if loss_type == "grpo"
               else "the sum over all real tokens divided by their count"): other,
        }
        _judge(f"{name}, {loss_type}", _call(name, fn, per_token.clone(), mask.clone(), loss_type),
               want, mistakes)
