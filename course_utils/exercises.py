"""Checkers for the lessons' exercises.

Each ``check_*`` function calls the learner's implementation on several seeded inputs of
different shapes and parameters (one value of a parameter would let a hard-coded answer
through), compares with the reference implementation in this library, and *raises*
``ExerciseError`` when they differ, so the notebook (and nbmake) stops at that cell. Before
giving a generic "differs" message, it tries the mistakes learners actually make (a flipped
sign, padding counted, the wrong normalization, ...) and, when the answer matches one, says
which. It also fails an answer that changes its inputs in place (the lesson's later cells
would then see wrong data) and, where the answer is a loss or feeds one, an answer whose
gradient is wrong or missing (a detached value passes a value check and breaks training).
"""

from __future__ import annotations

import math
from typing import Any, Callable

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


def _run(name: str, fn: Callable, args: dict[str, Any]):
    """Call ``fn`` with the checker's own tensors (not copies) and fail if it changed any."""
    before = {k: v.detach().clone() for k, v in args.items() if isinstance(v, torch.Tensor)}
    out = _call(name, fn, *args.values())
    for key, old in before.items():
        if not torch.equal(torch.nan_to_num(args[key].detach()), torch.nan_to_num(old)):
            raise ExerciseError(
                f"{name}: your function changed its input `{key}` in place (`{key} *= ...`, "
                f"`{key}[...] = ...` or a method ending in `_`), so every later cell sees wrong "
                f"data. Build a new tensor instead (`x = {key} * mask`), or start from "
                f"`{key}.clone()`.")
    return out


def _as_tensor(name: str, x) -> torch.Tensor:
    if not isinstance(x, torch.Tensor):
        raise ExerciseError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    return x


def _close(a: torch.Tensor, b: torch.Tensor, tol: float) -> bool:
    return (a.shape == b.shape and bool(torch.isfinite(a).all() == torch.isfinite(b).all())
            and torch.allclose(a.double(), b.double(), atol=tol, rtol=tol, equal_nan=True))


def _judge(name: str, got, want: torch.Tensor, mistakes: dict[str, torch.Tensor],
           tol: float = 1e-5, quiet: bool = False) -> None:
    got = _as_tensor(name, got).detach()
    want = want.detach()
    if got.shape != want.shape:
        raise ExerciseError(f"{name}: wrong shape {tuple(got.shape)}, expected {tuple(want.shape)}")
    if _close(got, want, tol):
        if not quiet:
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


def _judge_gradient(name: str, got: torch.Tensor, want: torch.Tensor,
                    inputs: dict[str, torch.Tensor], tol: float = 1e-5) -> None:
    """The value is right; now its gradient with respect to each input that needs one."""
    if not got.requires_grad:
        raise ExerciseError(f"{name}: the value is right but carries no gradient: something cut "
                            f"the graph (`.detach()`, `.item()`, `torch.no_grad()`, "
                            f"`torch.tensor(...)` of a result, or numpy), so training on it would "
                            f"fail or do nothing. Use torch operations on the inputs throughout.")
    weights = torch.randn(want.shape, generator=torch.Generator().manual_seed(7)).to(want.dtype)
    keys = list(inputs)
    g_got = torch.autograd.grad((got * weights).sum(), [inputs[k] for k in keys],
                                retain_graph=True, allow_unused=True)
    g_want = torch.autograd.grad((want * weights).sum(), [inputs[k] for k in keys],
                                 retain_graph=True, allow_unused=True)
    for key, a, b in zip(keys, g_got, g_want):
        a = torch.zeros_like(inputs[key]) if a is None else a
        b = torch.zeros_like(inputs[key]) if b is None else b
        if not _close(a, b, tol):
            raise ExerciseError(f"{name}: the value is right but its gradient with respect to "
                                f"`{key}` is not: part of the computation is detached or uses a "
                                f"constant where the formula has `{key}`.")


def _leaf(x: torch.Tensor) -> torch.Tensor:
    return x.detach().clone().requires_grad_()


# ----------------------------------------------------------------------------------------------
# Lesson 1: the policy-gradient theorem
# ----------------------------------------------------------------------------------------------


def check_score_function_gradient(fn: Callable) -> None:
    """fn(theta [K], actions [n], rewards [n]) -> [K]: (1/n) sum_i r_i grad log pi(a_i)."""
    name = "Exercise 1.1 (score-function gradient)"
    for case, (K, n) in enumerate([(5, 64), (3, 10), (8, 33)]):
        g = torch.Generator().manual_seed(11 + case)
        theta = torch.randn(K, generator=g)
        actions = torch.randint(0, K, (n,), generator=g)
        rewards = torch.randn(n, generator=g)
        pi = torch.softmax(theta, -1).double()
        score = torch.nn.functional.one_hot(actions, K).double() - pi  # grad log pi(a)
        want = (rewards.double()[:, None] * score).mean(0)
        mistakes = {
            "sign flipped: you returned minus the gradient (that is a loss's gradient, not J's)": -want,
            "summed over samples instead of averaging: divide by the number of samples": want * n,
            "used grad pi(a) instead of grad log pi(a): the log-derivative trick needs the log":
                (rewards.double()[:, None] * pi[actions][:, None] * score).mean(0),
            "forgot to weight by the reward": score.mean(0),
            "used the one-hot alone as the score: grad log softmax(theta)[a] = onehot(a) - pi":
                (rewards.double()[:, None] * torch.nn.functional.one_hot(actions, K).double()).mean(0),
        }
        got = _run(name, fn, dict(theta=theta, actions=actions, rewards=rewards))
        _judge(f"{name}, K={K}, n={n}", got, want, mistakes, quiet=True)
    print(f"✓ {name}: correct on 3 inputs (K = 5, 3, 8 actions)")


def check_sequence_log_prob(fn: Callable) -> None:
    """fn(logits [N, T, V], tokens [N, T]) -> [N]: sum_t log softmax(logits_t)[token_t]."""
    name = "Exercise 1.2 (log-probability of a sequence)"
    for case, (N, T, V) in enumerate([(4, 6, 7), (2, 3, 11), (5, 1, 4)]):
        g = torch.Generator().manual_seed(12 + case)
        logits = _leaf(torch.randn(N, T, V, generator=g) * 2)
        tokens = torch.randint(0, V, (N, T), generator=g)
        logp = torch.log_softmax(logits, -1).gather(-1, tokens.unsqueeze(-1)).squeeze(-1)
        want = logp.sum(-1)
        raw = logits.gather(-1, tokens.unsqueeze(-1)).squeeze(-1)
        shifted = torch.log_softmax(logits, -1)[:, :-1].gather(-1, tokens[:, 1:].unsqueeze(-1)).squeeze(-1)
        mistakes = {
            "averaged over tokens: a sequence's log-probability is the SUM of its tokens' (chain rule)": logp.mean(-1),
            "used raw logits: normalize with log_softmax first": raw.sum(-1),
            "returned a probability, not a log-probability": want.exp(),
            "used log(softmax) over the wrong dimension: normalize over the vocabulary (the last one)":
                torch.log_softmax(logits, 1).gather(-1, tokens.unsqueeze(-1)).squeeze(-1).sum(-1),
        }
        if T > 1:
            mistakes["off by one position: token t is scored by the logits at position t"] = shifted.sum(-1)
        got = _run(name, fn, dict(logits=logits, tokens=tokens))
        label = f"{name}, N={N}, T={T}, V={V}"
        _judge(label, got, want, mistakes, quiet=True)
        _judge_gradient(label, got, want, dict(logits=logits))
    print(f"✓ {name}: correct on 3 inputs, values and gradients")


def check_surrogate_loss(fn: Callable) -> None:
    """fn(seq_logprobs [N] with grad, rewards [N]) -> scalar loss whose gradient is minus the
    REINFORCE estimate: d loss / d logp_i = -r_i / N."""
    name = "Exercise 1.3 (surrogate loss)"
    for case, N in enumerate([8, 3, 17]):
        g = torch.Generator().manual_seed(13 + case)
        logp = _leaf(-torch.rand(N, generator=g) * 5)
        rewards = torch.randn(N, generator=g)
        loss = _as_tensor(name, _run(name, fn, dict(logp=logp, rewards=rewards)))
        if loss.dim() != 0:
            raise ExerciseError(f"{name}: the loss must be a scalar, got shape {tuple(loss.shape)}")
        if not loss.requires_grad:
            raise ExerciseError(f"{name}: the loss carries no gradient; did you detach the log-probs?")
        (grad,) = torch.autograd.grad(loss, logp)
        want = -rewards / N
        mistakes = {
            "sign flipped: minimizing this loss must INCREASE the log-probability of high-reward samples": -want,
            "summed instead of averaged over samples": want * N,
            "used probabilities where the loss needs log-probabilities: -mean(r * exp(logp)) has "
            "the gradient -r * p / N, not -r / N": -rewards * logp.detach().exp() / N,
        }
        _judge(f"{name} gradient, N={N}", grad, want, mistakes, quiet=True)
    print(f"✓ {name} gradient: correct on 3 inputs")


# ----------------------------------------------------------------------------------------------
# Lesson 2: REINFORCE on token sequences
# ----------------------------------------------------------------------------------------------


def check_returns_to_go(fn: Callable) -> None:
    """fn(rewards [N, T], gamma) -> [N, T]: G_t = sum_{k >= t} gamma^(k - t) r_k."""
    name = "Exercise 2.1 (returns-to-go)"
    for case, ((N, T), gamma) in enumerate([((3, 6), 1.0), ((3, 6), 0.9), ((5, 4), 0.5), ((1, 1), 0.7)]):
        g = torch.Generator().manual_seed(21 + case)
        rewards = torch.randn(N, T, generator=g)
        want = losses.returns_to_go(rewards, gamma)
        mistakes = {"summed the PAST rewards (k <= t); the return-to-go sums the future (k >= t)":
                    torch.flip(losses.returns_to_go(torch.flip(rewards, [-1]), gamma), [-1])}
        if gamma != 1.0:  # these mistakes coincide with the right answer when gamma = 1
            powers = gamma ** torch.arange(T, dtype=torch.float32)
            mistakes["discounted by gamma^k from the start; it must be gamma^(k - t), relative to t"] = \
                torch.flip(torch.cumsum(torch.flip(rewards * powers, [-1]), -1), [-1])
            mistakes["ignored gamma"] = losses.returns_to_go(rewards, 1.0)
        got = _run(name, fn, dict(rewards=rewards, gamma=gamma))
        _judge(f"{name}, shape {N}x{T}, gamma={gamma}", got, want, mistakes, quiet=True)
    print(f"✓ {name}: correct on 4 inputs (gamma = 1, 0.9, 0.5, 0.7)")


def _masks(g: torch.Generator, N: int, T: int) -> torch.Tensor:
    """Right-padded 0/1 masks of lengths 1..T, with one full row and one of length 1."""
    lengths = torch.randint(1, T + 1, (N,), generator=g)
    lengths[0], lengths[-1] = T, 1
    return (torch.arange(T)[None] < lengths[:, None]).long()


def check_masked_reinforce_loss(fn: Callable) -> None:
    """fn(logprobs [N, T], returns [N, T], mask [N, T]) -> scalar:
    -(1/N) sum_i sum_t mask_it * logprob_it * return_it."""
    name = "Exercise 2.2 (masked REINFORCE loss)"
    for case, (N, T) in enumerate([(4, 5), (2, 7), (6, 3)]):
        g = torch.Generator().manual_seed(22 + case)
        logp = _leaf(-torch.rand(N, T, generator=g) * 3)
        returns = torch.randn(N, T, generator=g)
        mask = _masks(g, N, T)
        want = -(logp * returns * mask).sum(-1).mean()
        mistakes = {
            "padding tokens counted: multiply by the mask": -(logp * returns).sum(-1).mean(),
            "sign flipped: the loss is MINUS the objective": -want,
            "averaged over tokens; the spec sums over a sequence's tokens and averages over sequences":
                -(logp * returns * mask).sum() / mask.sum(),
            "averaged over each sequence's tokens; the spec SUMS over a sequence's tokens":
                -((logp * returns * mask).sum(-1) / mask.sum(-1)).mean(),
            "summed over sequences too: average over the N sequences": want * N,
        }
        got = _run(name, fn, dict(logprobs=logp, returns=returns, mask=mask))
        label = f"{name}, N={N}, T={T}"
        _judge(label, got, want, mistakes, quiet=True)
        _judge_gradient(label, _as_tensor(name, got), want, dict(logprobs=logp))
    print(f"✓ {name}: correct on 3 inputs, values and gradients")


def _token_rows(g: torch.Generator, eos: int, vocab: int, T: int) -> torch.Tensor:
    """Rows of ids with the EOS at the start, in the middle, twice, never, and then padding."""
    other = [t for t in range(vocab) if t != eos]
    def word(n):
        return torch.tensor(other)[torch.randint(0, len(other), (n,), generator=g)]
    rows = [torch.cat([word(2), torch.full((T - 2,), eos)]),          # stops, pad == EOS after
            torch.full((T,), eos),                                     # stops at once
            word(T),                                                   # truncated: no EOS
            torch.cat([word(1), torch.tensor([eos]), word(1), torch.full((T - 3,), eos)]),  # EOS, text, EOS
            torch.cat([word(T - 1), torch.tensor([eos])])]             # EOS as the last token
    return torch.stack(rows)


def check_completion_mask(fn: Callable) -> None:
    """fn(ids [N, T], eos_id) -> [N, T] 0/1: 1 up to and including the first EOS."""
    name = "Exercise 2.3 (completion mask with pad == EOS)"
    for case, (eos, vocab, T) in enumerate([(2, 10, 5), (12, 13, 6), (0, 7, 8)]):
        g = torch.Generator().manual_seed(23 + case)
        ids = _token_rows(g, eos, vocab, T)
        want = reference_completion_mask(ids, [eos])
        kept = want.sum(-1, keepdim=True)                  # tokens kept per row
        has_eos = (ids == eos).any(-1, keepdim=True)
        pos = torch.arange(T)
        last_eos = T - 1 - torch.flip(ids == eos, [-1]).int().argmax(-1, keepdim=True)
        mistakes = {
            "built from ids != pad_id: with pad == EOS that drops the real EOS, so the model is never "
            "trained to stop": (ids != eos).long(),
            "excluded the EOS token itself; it must be in the mask (stopping is an action too)":
                torch.where(has_eos, (pos < kept - 1).long(), want),
            "a row without EOS (truncated) must be all ones": torch.where(has_eos, want, torch.zeros_like(want)),
            "kept tokens after a later EOS: the mask ends at the FIRST EOS":
                torch.where(has_eos, (pos <= last_eos).long(), want),
        }
        if eos != 2:
            mistakes["used EOS id 2 instead of the eos_id argument (here the EOS is "
                     f"{eos}; the toy policy's is 12)"] = reference_completion_mask(ids, [2])
        got = _as_tensor(name, _run(name, fn, dict(ids=ids, eos_id=eos)))
        if got.dtype.is_floating_point and not torch.isin(got, torch.tensor([0.0, 1.0])).all():
            raise ExerciseError(f"{name}: a mask holds only 0 and 1")
        _judge(f"{name}, eos_id={eos}", got.long(), want, mistakes, quiet=True)
    print(f"✓ {name}: correct on 3 inputs (eos_id = 2, 12, 0)")


# ----------------------------------------------------------------------------------------------
# Lesson 3: baselines
# ----------------------------------------------------------------------------------------------


def check_leave_one_out_baseline(fn: Callable) -> None:
    """fn(rewards [N], group_size G) -> [N]: mean of the other G - 1 rewards of the group."""
    name = "Exercise 3.1 (leave-one-out baseline)"
    for case, (groups, G) in enumerate([(3, 4), (4, 2), (2, 5)]):
        g = torch.Generator().manual_seed(31 + case)
        rewards = torch.randn(groups * G, generator=g)
        want = losses.leave_one_out_baseline(rewards, G)
        r = rewards.view(-1, G)
        mistakes = {
            "included the sample's own reward (that is the group mean, which is biased)":
                r.mean(-1, keepdim=True).expand_as(r).reshape(-1),
            "divided by G instead of G - 1": ((r.sum(-1, keepdim=True) - r) / G).reshape(-1),
            "used the whole batch instead of the group": (rewards.sum() - rewards) / (len(rewards) - 1),
            "returned the advantage r - b; the exercise asks for the baseline b": rewards - want,
        }
        got = _run(name, fn, dict(rewards=rewards, group_size=G))
        _judge(f"{name}, G={G}", got, want, mistakes, quiet=True)
    print(f"✓ {name}: correct on 3 inputs (G = 4, 2, 5)")


def check_self_baseline_factor(fn: Callable) -> None:
    """fn(N) -> float: E[estimate with b = mean of all N rewards] / true gradient."""
    name = "Exercise 3.2 (bias of a baseline that includes the sample)"
    for n in (2, 3, 5, 16, 100):
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
    print(f"✓ {name}: correct for N = 2, 3, 5, 16, 100")


def check_actor_critic_advantage(fn: Callable) -> None:
    """fn(rewards [N], values [N] with grad) -> [N]: r - V(s), with no gradient into the critic."""
    name = "Exercise 3.3 (advantage from a learned value baseline)"
    for case, N in enumerate([6, 1, 9]):
        g = torch.Generator().manual_seed(33 + case)
        rewards = torch.randn(N, generator=g)
        values = torch.randn(N, generator=g).requires_grad_()
        got = _as_tensor(name, _run(name, fn, dict(rewards=rewards, values=values)))
        want = rewards - values.detach()
        if got.requires_grad:
            raise ExerciseError(f"{name}: the advantage still carries the critic's gradient: detach "
                                f"the values, or the policy loss will train the critic to shrink it")
        _judge(f"{name}, N={N}", got, want, {"sign flipped: the advantage is reward minus baseline": -want},
               quiet=True)
    print(f"✓ {name}: correct on 3 inputs")


# ----------------------------------------------------------------------------------------------
# Lesson 5: GRPO
# ----------------------------------------------------------------------------------------------


def _group_rewards(g: torch.Generator, groups: int, G: int) -> torch.Tensor:
    """Rewards with every kind of group: spread out, binary, and all equal (no signal)."""
    spread = torch.randn(max(groups - 2, 1) * G, generator=g)
    binary = (torch.rand(G, generator=g) < 0.5).float()
    binary[0], binary[1] = 1.0, 0.0                    # mixed, so its std is not 0
    return torch.cat([spread, binary, torch.full((G,), 0.5)])


def check_group_advantages(fn: Callable) -> None:
    """fn(rewards [N], G) -> [N]: (r - group mean) / (group std (Bessel) + eps).

    Any small eps is accepted (TRL uses 1e-4, CS336 1e-6), and so is an exact 0 for a group
    whose rewards are all equal: the checker compares to a relative 1e-3, and its groups'
    stds are far larger than any such eps."""
    name = "Exercise 5.1 (group-relative advantages)"
    for case, (groups, G) in enumerate([(3, 4), (4, 3), (3, 8)]):
        g = torch.Generator().manual_seed(41 + case)
        rewards = _group_rewards(g, groups, G)
        want, _ = losses.group_advantages(rewards, G)
        r = rewards.view(-1, G)
        centred = r - r.mean(-1, keepdim=True)
        mistakes = {
            "used the whole batch's mean and std; GRPO standardizes within each prompt's group":
                (rewards - rewards.mean()) / (rewards.std() + 1e-4),
            "used the population std (unbiased=False); use the sample std, as DeepSeekMath and TRL do":
                (centred / (r.std(-1, unbiased=False, keepdim=True) + 1e-4)).reshape(-1),
            "no epsilon in the denominator: a group of equal rewards divides 0 by 0":
                (centred / r.std(-1, keepdim=True)).reshape(-1),
            "forgot to divide by the std": centred.reshape(-1),
            "divided by the variance, not the std": (centred / (r.var(-1, keepdim=True) + 1e-4)).reshape(-1),
            "centred on the group mean but divided by the whole batch's std":
                (centred / (rewards.std() + 1e-4)).reshape(-1),
        }
        got = _run(name, fn, dict(rewards=rewards, group_size=G))
        _judge(f"{name}, G={G}", got, want, mistakes, tol=1e-3, quiet=True)
    print(f"✓ {name}: correct on 3 inputs (G = 4, 3, 8), an all-equal group in each")


def check_clipped_surrogate(fn: Callable) -> None:
    """fn(logp, old_logp, advantages [N], eps_low, eps_high) -> per-token loss [N, T]."""
    name = "Exercise 5.2 (clipped surrogate)"
    for case, ((N, T), eps_low, eps_high) in enumerate([((6, 5), 0.2, 0.28), ((4, 3), 0.1, 0.1),
                                                         ((5, 7), 0.3, 0.2)]):
        g = torch.Generator().manual_seed(42 + case)
        old = -torch.rand(N, T, generator=g) * 2
        logp = _leaf(old + torch.randn(N, T, generator=g) * 0.4)
        adv = torch.randn(N, generator=g)
        adv[-1] = 0.0                                  # a zero-advantage sequence
        want, _ = losses.clipped_surrogate(logp, old, adv, eps_low, eps_high)
        ratio = (logp - old).exp()
        A = adv[:, None]
        lo, hi = 1 - eps_low, 1 + eps_high
        mistakes = {
            "took the max of the objectives (the min of the losses): the clip must be pessimistic":
                torch.minimum(-ratio * A, -ratio.clamp(lo, hi) * A),
            "no clipping at all": -ratio * A,
            "sign flipped: the loss is minus the objective": -want,
            "clipped the objective but dropped the unclipped branch": -ratio.clamp(lo, hi) * A,
            "used the log-ratio where the ratio belongs: rho = exp(logp - old_logp)":
                torch.maximum(-(logp - old) * A, -(logp - old).clamp(lo, hi) * A),
        }
        if eps_low != eps_high:
            mistakes["used eps_low on both sides: the upper clip is 1 + eps_high"] = \
                losses.clipped_surrogate(logp, old, adv, eps_low, eps_low)[0]
            mistakes["swapped eps_low and eps_high"] = \
                losses.clipped_surrogate(logp, old, adv, eps_high, eps_low)[0]
        args = dict(logp=logp, old_logp=old, advantages=adv, eps_low=eps_low, eps_high=eps_high)
        got = _run(name, fn, args)
        label = f"{name}, eps_low={eps_low}, eps_high={eps_high}"
        _judge(label, got, want, mistakes, quiet=True)
        _judge_gradient(label, _as_tensor(name, got), want, dict(logp=logp))
    print(f"✓ {name}: correct on 3 inputs, values and gradients (clipped tokens get none)")


def check_k3_kl(fn: Callable) -> None:
    """fn(logp, ref_logp) -> per-token k3 estimate of KL(pi || pi_ref)."""
    name = "Exercise 5.3 (k3 KL estimate)"
    for case, (N, T) in enumerate([(4, 6), (1, 3), (3, 9)]):
        g = torch.Generator().manual_seed(43 + case)
        logp = _leaf(-torch.rand(N, T, generator=g) * 3)
        ref = logp.detach() + torch.randn(N, T, generator=g) * 0.5
        want = losses.k3_kl(logp, ref)
        d = ref - logp
        mistakes = {
            "that is k1 = log(pi / pi_ref): its value is unbiased but often negative per token, and "
            "as a loss term its gradient is zero on average (section 4 enumerates it)": -d,
            "ratio upside down: k3 uses pi_ref / pi_theta": (-d).exp() + d - 1,
            "that is k2 = (log ratio)^2 / 2": 0.5 * d ** 2,
            "forgot the -1: k3 = r - log r - 1 with r = pi_ref / pi_theta": d.exp() - d,
        }
        got = _run(name, fn, dict(logp=logp, ref_logp=ref))
        label = f"{name}, shape {N}x{T}"
        _judge(label, got, want, mistakes, quiet=True)
        _judge_gradient(label, _as_tensor(name, got), want, dict(logp=logp))
    print(f"✓ {name}: correct on 3 inputs, values and gradients")


def check_aggregate(fn: Callable) -> None:
    """fn(per_token [N, T], mask [N, T], loss_type) -> scalar, for "grpo" and "dapo"."""
    name = "Exercise 5.4 (loss aggregation)"
    for case, (N, T) in enumerate([(3, 4), (5, 6), (2, 9)]):
        g = torch.Generator().manual_seed(44 + case)
        mask = _masks(g, N, T)
        per_token = _leaf(torch.rand(N, T, generator=g) + 0.5)
        # a zero-advantage sequence has an exactly-zero loss on every token, and padding holds
        # junk that a correct answer never reads
        with torch.no_grad():
            per_token[1] = 0.0
            per_token[0, 0] = 0.0                      # a real token whose loss happens to be 0
            per_token.masked_fill_(mask == 0, 9.0)
        for loss_type in ("grpo", "dapo"):
            want = losses.aggregate(per_token, mask, loss_type)
            m = mask.to(per_token.dtype)
            nonzero = (per_token * m != 0).to(per_token.dtype)
            mistakes = {
                "padding counted: only real tokens enter the average": per_token.mean(-1).mean()
                if loss_type == "grpo" else per_token.mean(),
                f"that is the other aggregation: '{loss_type}' is "
                + ("the mean per sequence, then over sequences" if loss_type == "grpo"
                   else "the sum over all real tokens divided by their count"):
                    losses.aggregate(per_token, mask, "dapo" if loss_type == "grpo" else "grpo"),
                "counted tokens as the non-zero losses: a token whose loss is exactly 0 (every "
                "token of a zero-advantage group) is still a real token; count the mask":
                    ((per_token * m).sum(-1) / nonzero.sum(-1).clamp(min=1)).mean()
                    if loss_type == "grpo" else (per_token * m).sum() / nonzero.sum(),
            }
            if loss_type == "dapo":
                mistakes["divided the sum over real tokens by the number of sequences N; 'dapo' "
                         "divides by the number of real tokens"] = (per_token * m).sum() / N
            else:
                mistakes["summed each sequence's tokens without dividing by its length"] = \
                    (per_token * m).sum(-1).mean()
            got = _run(name, fn, dict(per_token=per_token, mask=mask, loss_type=loss_type))
            label = f"{name}, {loss_type}, N={N}, T={T}"
            _judge(label, got, want, mistakes, quiet=True)
            _judge_gradient(label, _as_tensor(name, got), want, dict(per_token=per_token))
    print(f"✓ {name}: correct on 3 inputs for 'grpo' and 'dapo', values and gradients")
