"""Checkers for the rest of the GRPO step by hand (lesson 6, exercises 6.4 and 6.5): the token
entropy of a policy from its logits, and the clipped GRPO loss of a batch reused for several
updates, with its clip fraction and a k3 KL to a reference model.

They work as those in ``exercises.py`` do: several seeded inputs of different shapes, the
library (``losses``) as the reference, values *and* gradients compared, padding that holds
values depending on the parameters (so a gradient leaking through it shows), inputs checked for
in-place changes, and the plausible mistakes recognized and named.
"""

from __future__ import annotations

import math
from typing import Callable

import torch
import torch.nn.functional as F

from . import losses
from .exercises import ExerciseError, _as_tensor, _close, _run

# ----------------------------------------------------------------------------------------------
# Exercise 6.4: token entropy
# ----------------------------------------------------------------------------------------------


def _reference_entropy(logits: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``losses.token_entropy`` in the input's own dtype (the library computes in float32, for
    bf16 models), 0 at padding."""
    logp = F.log_softmax(logits, -1)
    return torch.where(mask.bool(), -(logp.exp() * logp).sum(-1), 0.0)


def _entropy_mistakes(logits: torch.Tensor, mask: torch.Tensor) -> dict[str, torch.Tensor]:
    logp = F.log_softmax(logits, -1)
    p = logp.exp()
    H = -(p * logp).sum(-1)
    m = mask.bool()
    return {
        "the sign is flipped: H = -sum_a pi(a) log pi(a), which is >= 0": torch.where(m, -H, 0.0),
        "this is in bits (log base 2); the course, TRL and PyTorch measure entropy in nats "
        "(natural log)": torch.where(m, H / math.log(2), 0.0),
        "padding positions are not 0: set the entropy to 0 where mask is 0 (with torch.where, so "
        "that whatever the padding's logits hold cannot leak)": H,
        "this averages over the vocabulary; the entropy is a sum over it": torch.where(m, H / logits.shape[-1], 0.0),
        "this uses the logits where the log-probabilities belong: -sum_a pi(a) z_a misses the "
        "log-normalizer (log pi = z - logsumexp z)": torch.where(m, -(p * logits).sum(-1), 0.0),
    }


def check_token_entropy(fn: Callable) -> None:
    """``fn(logits, mask)`` -> [N, T]: the entropy of softmax(logits) at each real position
    (mask 1), in nats, and 0 at padding; numerically stable for extreme logits."""
    name = "token_entropy"
    gen = torch.Generator().manual_seed(11)
    # (N, T, V, scale of the logits, dtype): the last but one holds logits of size 1e4, where
    # softmax underflows to exact zeros and log(softmax) to -inf
    cases = [(2, 3, 5, 1.0, torch.float64), (4, 7, 64, 3.0, torch.float32),
             (3, 4, 11, 1e4, torch.float32), (1, 1, 2, 0.5, torch.float64)]
    for N, T, V, scale, dtype in cases:
        logits = (scale * torch.randn(N, T, V, generator=gen, dtype=dtype)).requires_grad_(True)
        lengths = torch.randint(1, T + 1, (N,), generator=gen)
        lengths[0] = T
        mask = (torch.arange(T) < lengths[:, None]).to(dtype)
        label = f"logits [{N}, {T}, {V}] of scale {scale:g} in {str(dtype).replace('torch.', '')}"
        got = _as_tensor(name, _run(name, fn, dict(logits=logits, mask=mask)))
        want = _reference_entropy(logits, mask)
        if got.shape != want.shape:
            hint = " (one value per position: sum over the vocabulary only)" if got.dim() != 2 else ""
            raise ExerciseError(f"{name}: on {label} the result has shape {tuple(got.shape)}, "
                                f"expected {tuple(want.shape)}{hint}")
        # an answer computed in float32 (as the library is, and exercise 6.1's .float()) is right
        # to float32's precision
        tol = 1e-9 if got.dtype == torch.float64 and dtype == torch.float64 else 2e-4
        if not torch.isfinite(got).all():
            raise ExerciseError(f"{name}: NaN or inf on {label}: softmax underflows to exact zeros "
                                f"there, log(0) = -inf and 0 * -inf = NaN. Compute log pi with "
                                f"torch.log_softmax (it subtracts the largest logit first) and "
                                f"pi as its exp")
        if not _close(got.detach(), want.detach(), tol):
            for message, value in _entropy_mistakes(logits.detach(), mask).items():
                if _close(got.detach(), value, tol):
                    raise ExerciseError(f"{name}: {message} (on {label})")
            diff = (got.detach() - want.detach()).abs().max().item()
            raise ExerciseError(f"{name}: differs from -sum_a pi(a) log pi(a) by up to {diff:.3g} on {label}")
        if not got.requires_grad:
            raise ExerciseError(f"{name}: the result carries no gradient; an entropy bonus needs "
                                f"one (do not detach or compute it under torch.no_grad)")
        weights = torch.randn(N, T, generator=gen, dtype=dtype)
        (g_got,) = torch.autograd.grad((got * weights).sum(), logits, retain_graph=True)
        (g_want,) = torch.autograd.grad((want * weights).sum(), logits)
        if not torch.isfinite(g_got).all():
            raise ExerciseError(f"{name}: the gradient is NaN or inf on {label}: where softmax is "
                                f"exactly 0 the gradient of log(softmax) is not finite; use "
                                f"torch.log_softmax")
        if not _close(g_got, g_want, 10 * tol):
            raise ExerciseError(f"{name}: the value is right but its gradient is not on {label} "
                                f"(is part of the computation detached?)")
    print(f"✓ {name}: correct (values and gradients, padding, logits up to 1e4)")


# ----------------------------------------------------------------------------------------------
# Exercise 6.5: the clipped loss over several updates, with a reference KL
# ----------------------------------------------------------------------------------------------


def reference_clipped_loss(logprobs, old_logprobs, ref_logprobs, advantages, mask, eps_low,
                           eps_high, beta):
    """The exercise's answer through the library: (loss, clip fraction, mean k3 KL)."""
    loss, stats = losses.grpo_loss(logprobs, old_logprobs, advantages, mask, loss_type="grpo",
                                   eps_low=eps_low, eps_high=eps_high, ref_logprobs=ref_logprobs,
                                   beta=beta)
    real = mask.bool()
    kl = losses.k3_kl(torch.where(real, logprobs, 0.0).detach(), torch.where(real, ref_logprobs, 0.0))
    return loss, stats["clip_fraction"], losses.masked_mean(kl, mask)


def _clipped_loss_mistakes(lp, old, ref, A, mask, eps_low, eps_high, beta):
    """(message, per-token loss, aggregation) of each plausible mistake; None keeps 'grpo'."""
    rho = torch.exp(lp - old)
    kl = losses.k3_kl(lp, ref)
    surrogate = torch.maximum(-rho * A, -rho.clamp(1 - eps_low, 1 + eps_high) * A)
    return [
        ("the clip is missing: the loss is -rho A. Take the pessimistic minimum of rho A and "
         "clip(rho, 1 - eps_low, 1 + eps_high) A", -rho * A + beta * kl, None),
        ("the ratio is taken against the current policy, exp(log pi - sg[log pi]), which is 1: after "
         "the first update the batch's tokens were sampled by old_logprobs' policy, and the ratio "
         "must use them", -torch.exp(lp - lp.detach()) * A + beta * kl, None),
        ("only the clipped branch is used: clip(rho) A alone has zero gradient wherever the ratio "
         "is outside the range, on both sides. The loss is -min(rho A, clip(rho) A)",
         -rho.clamp(1 - eps_low, 1 + eps_high) * A + beta * kl, None),
        ("the optimistic maximum: this takes max(rho A, clip(rho) A); PPO's objective takes the "
         "minimum, so the clip only ever removes an incentive",
         torch.minimum(-rho * A, -rho.clamp(1 - eps_low, 1 + eps_high) * A) + beta * kl, None),
        ("eps_low is used on both sides; the upper bound is 1 + eps_high",
         torch.maximum(-rho * A, -rho.clamp(1 - eps_low, 1 + eps_low) * A) + beta * kl, None),
        ("the KL is measured against old_logprobs; the penalty is toward the reference: k3 with "
         "r = pi_ref / pi, from ref_logprobs", surrogate + beta * losses.k3_kl(lp, old), None),
        ("the ratio is taken against ref_logprobs; rho = pi_theta / pi_old uses old_logprobs",
         torch.maximum(-torch.exp(lp - ref) * A, -torch.exp(lp - ref).clamp(1 - eps_low, 1 + eps_high) * A)
         + beta * kl, None),
        ("eps_high is used on both sides; the lower bound is 1 - eps_low",
         torch.maximum(-rho * A, -rho.clamp(1 - eps_high, 1 + eps_high) * A) + beta * kl, None),
        ("eps_low and eps_high are swapped: the bounds are 1 - eps_low and 1 + eps_high",
         torch.maximum(-rho * A, -rho.clamp(1 - eps_high, 1 + eps_low) * A) + beta * kl, None),
        ("the KL term has the wrong sign: it is a penalty, + beta * KL in the loss",
         surrogate - beta * kl, None),
        ("the KL is the k1 estimate log pi - log pi_ref, which is unbiased but often negative per "
         "token; use k3: pi_ref/pi - log(pi_ref/pi) - 1",
         surrogate + beta * (lp - ref), None),
        ("the k3 estimate is written the other way round (log pi - log pi_ref inside); k3 uses "
         "r = pi_ref / pi: r - log r - 1", surrogate + beta * losses.k3_kl(ref, lp), None),
        ("this is the 'dapo' aggregation (one mean over every token of the batch); the exercise "
         "asks for 'grpo': the mean over each completion's tokens, then over completions",
         surrogate + beta * kl, "dapo"),
        ("padding is counted: each completion's mean is over its real tokens only (the mask)",
         surrogate + beta * kl, "padded"),
    ]


def _aggregate(per_token, mask, how):
    m = mask.to(per_token.dtype)
    per_token = torch.where(mask.bool(), per_token, 0.0)
    if how == "dapo":
        return per_token.sum() / m.sum()
    if how == "padded":
        return per_token.mean(-1).mean()
    return (per_token.sum(-1) / m.sum(-1).clamp(min=1)).mean()


def check_clipped_loss(fn: Callable) -> None:
    """``fn(logprobs, old_logprobs, ref_logprobs, advantages, mask, eps_low, eps_high, beta)`` ->
    (loss, clip_fraction, kl): GRPO's clipped loss with a k3 KL penalty, aggregated as 'grpo',
    the share of real tokens whose gradient the clip removes, and the mean k3 KL over real
    tokens (floats for the last two). The clip fraction counts the tokens whose *surrogate*
    gradient the clip removes; with beta > 0 the KL term's gradient still reaches them."""
    name = "clipped_loss"
    gen = torch.Generator().manual_seed(12)
    # (N, T, eps_low, eps_high, beta, how far the policy moved since sampling)
    cases = [(6, 5, 0.2, 0.2, 0.04, 0.3), (8, 9, 0.2, 0.28, 0.1, 0.5), (4, 3, 0.1, 0.3, 0.0, 0.4)]
    for N, T, eps_low, eps_high, beta, move in cases:
        label = f"{N} completions of up to {T} tokens, eps {eps_low}/{eps_high}, beta {beta}"
        theta = torch.randn(N, T, generator=gen, dtype=torch.float64).requires_grad_(True)
        old = -3 * torch.rand(N, T, generator=gen, dtype=torch.float64)
        # log pi_theta: the sampler's, moved; a function of theta at every position, padding too
        logprobs = (old + move * theta).clamp(max=-1e-3)
        ref = old + 0.3 * torch.randn(N, T, generator=gen, dtype=torch.float64)
        advantages = torch.randn(N, 1, generator=gen, dtype=torch.float64)
        advantages[0] = 0.0                         # a group without signal
        lengths = torch.randint(1, T + 1, (N,), generator=gen)
        lengths[1] = T
        mask = (torch.arange(T) < lengths[:, None]).to(torch.float64)
        args = dict(logprobs=logprobs, old_logprobs=old, ref_logprobs=ref, advantages=advantages,
                    mask=mask, eps_low=eps_low, eps_high=eps_high, beta=beta)
        out = _run(name, fn, args)
        if not (isinstance(out, tuple) and len(out) == 3):
            raise ExerciseError(f"{name}: return three things, (loss, clip_fraction, kl)")
        loss, clip_fraction, kl = out
        loss = _as_tensor(name, loss)
        want_loss, want_clip, want_kl = reference_clipped_loss(logprobs, old, ref, advantages, mask,
                                                               eps_low, eps_high, beta)
        if loss.dim() != 0:
            raise ExerciseError(f"{name}: the loss must be one number (a 0-dimensional tensor), got "
                                f"shape {tuple(loss.shape)}")
        if not loss.requires_grad:
            raise ExerciseError(f"{name}: the loss carries no gradient (logprobs must not be detached)")
        (g_got,) = torch.autograd.grad(loss, theta, retain_graph=True)
        (g_want,) = torch.autograd.grad(want_loss, theta, retain_graph=True)
        tol = 1e-9 if loss.dtype == torch.float64 else 2e-5   # an answer computed in float32 is right to its precision
        if not (_close(loss.detach(), want_loss.detach(), tol) and _close(g_got, g_want, tol)):
            for message, per_token, how in _clipped_loss_mistakes(logprobs, old, ref, advantages, mask,
                                                                 eps_low, eps_high, beta):
                wrong = _aggregate(per_token, mask, how)
                (g_wrong,) = torch.autograd.grad(wrong, theta, retain_graph=True)
                # a mistake may change only the value (a wrong bound where the gradient is 0
                # anyway) or only the gradient: it is named when both match the answer's
                matches = _close(loss.detach(), wrong.detach(), 1e-9) and _close(g_got, g_wrong, 1e-9)
                if matches and not (_close(wrong.detach(), want_loss.detach(), 1e-9) and _close(g_wrong, g_want, 1e-9)):
                    raise ExerciseError(f"{name}: {message} (on {label})")
            if _close(loss.detach(), want_loss.detach(), 1e-9):
                raise ExerciseError(f"{name}: the loss's value is right but its gradient is not on "
                                    f"{label}: is a gradient flowing through padding, or is part of "
                                    f"the loss detached?")
            raise ExerciseError(f"{name}: the loss differs from GRPO's on {label} by "
                                f"{abs(float(loss.detach()) - float(want_loss)):.2e} ({float(loss.detach()):.6f}, "
                                f"expected {float(want_loss):.6f})")
        for what, got, want in (("clip_fraction", clip_fraction, want_clip), ("kl", kl, want_kl)):
            try:
                got = float(got)
            except (TypeError, ValueError, RuntimeError):
                raise ExerciseError(f"{name}: return {what} as one number, got {type(got).__name__}") from None
            if abs(got - want) > 1e-6:   # the library counts in float32
                hints = {"clip_fraction": " Count a real token only where the clipped branch is the "
                                          "active one (rho > 1 + eps_high with A > 0, rho < 1 - eps_low "
                                          "with A < 0), and average over real tokens.",
                         "kl": " Average the per-token k3 KL over real tokens only, whatever beta is."}
                raise ExerciseError(f"{name}: {what} is {got:.5f}, expected {want:.5f} on {label}.{hints[what]}")
    print(f"✓ {name}: correct (values and gradients; asymmetric clip, a zero advantage, padding, "
          f"the KL with and without its penalty)")
