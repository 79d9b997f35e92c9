"""Checkers for the trust-region lesson's exercises: the Fisher matrix, the importance-weighted
policy gradient, the clip fraction and TRL's importance weights (TRPO's step, exercise 4.2, is
checked by ``trpo_exercises.py``).

They work as those in ``exercises.py`` do: several seeded inputs of different shapes (softmax
bandits with 3 to 6 arms, near-deterministic ones included, and tabular sequence policies of 2
to 3 tokens), ``course_utils.trust`` as the reference, the plausible mistakes recognized and
named, inputs checked for in-place changes, and, for the estimator, the exact expectation of its
gradient compared with the exact gradient of the objective, by enumeration.
"""

from __future__ import annotations

import math
from typing import Callable

import torch

from . import trust
from .exercises import ExerciseError, _as_tensor, _close, _run


def _policies():
    """(name, log_prob_fn, theta): bandits and sequence policies, one of them near-deterministic."""
    g = torch.Generator().manual_seed(0)
    seq_small, seq = trust.SequencePolicy(T=2, V=2), trust.SequencePolicy(T=3, V=3)
    return [
        # one parameter: F is [1, 1], which a .squeeze() turns into a scalar
        ("a 2-armed bandit", trust.bandit_log_probs, torch.tensor([0.7], dtype=torch.float64)),
        ("a 3-armed bandit", trust.bandit_log_probs, torch.randn(2, generator=g, dtype=torch.float64)),
        ("a near-deterministic 6-armed bandit", trust.bandit_log_probs,
         torch.tensor([4.0, -1.0, 0.5, -2.0, 1.0], dtype=torch.float64)),
        ("a 2-token sequence policy", seq_small.log_probs,
         torch.randn(seq_small.n_params, generator=g, dtype=torch.float64)),
        ("a 3-token sequence policy over 3 symbols", seq.log_probs,
         0.7 * torch.randn(seq.n_params, generator=g, dtype=torch.float64)),
    ]


# ----------------------------------------------------------------------------------------------
# The Fisher matrix
# ----------------------------------------------------------------------------------------------


def _fisher_mistakes(log_prob_fn, theta) -> dict[str, torch.Tensor]:
    scores = torch.autograd.functional.jacobian(log_prob_fn, theta)
    logp = log_prob_fn(theta)
    p = logp.exp()
    F = scores.T @ (p[:, None] * scores)
    mean_score = p @ scores
    return {
        "every outcome counts the same: F is an *expectation*, sum_x pi(x) s(x) s(x)^T, so weight "
        "each outer product by the outcome's probability": scores.T @ scores,
        "the outer products are weighted by the log-probabilities; weight them by the "
        "probabilities pi(x) = exp(log pi(x))": scores.T @ (logp[:, None] * scores),
        "only the diagonal is kept: F couples the parameters, and the natural gradient needs the "
        "off-diagonal terms": torch.diag(torch.diag(F)),
        "the sign is flipped: F = -E[Hessian of log pi] = +E[s s^T], a positive semi-definite "
        "matrix": -F,
    }


def check_fisher_matrix(fn: Callable) -> None:
    """``fn(log_prob_fn, theta)`` -> F [d, d], where ``log_prob_fn(theta)`` returns the
    log-probability of every outcome [M] and F = sum_x pi(x) grad log pi(x) grad log pi(x)^T."""
    name = "fisher_matrix"
    for label, log_prob_fn, theta in _policies():
        got = _as_tensor(name, _run(name, fn, dict(log_prob_fn=log_prob_fn, theta=theta)))
        want = trust.fisher_matrix(log_prob_fn, theta)
        if got.shape != want.shape:
            squeezed = " (a .squeeze() drops both dimensions when d = 1)" if got.numel() == want.numel() else ""
            raise ExerciseError(f"{name}: on {label} (d = {len(theta)} parameters, "
                                f"{len(log_prob_fn(theta))} outcomes) the result has shape "
                                f"{tuple(got.shape)}; F is [d, d] = {tuple(want.shape)}{squeezed}")
        # theta is float64; an answer that builds F in float32 (a torch.zeros(d, d) made while
        # the default dtype is float32) is right to float32's precision, and is accepted as such
        tol = 1e-8 if got.dtype == torch.float64 else 1e-5
        if _close(got.detach(), want, tol):
            continue
        if float(got.detach().abs().max()) <= 1e-10 * float(want.abs().max()):   # zero up to rounding
            raise ExerciseError(f"{name}: F is all zeros on {label}. If this is the outer product "
                                f"of the *expected* score, that is zero because E[grad log pi] = 0; "
                                f"F is the expectation of the outer product, E[s s^T]. Otherwise, "
                                f"check that the scores (the Jacobian of log_prob_fn) reach F.")
        for message, value in _fisher_mistakes(log_prob_fn, theta).items():
            if _close(got.detach(), value, tol):
                raise ExerciseError(f"{name}: {message} (on {label})")
        diff = (got.detach() - want).abs().max().item()
        raise ExerciseError(f"{name}: differs from E[s s^T] by up to {diff:.3g} on {label}")
    print(f"✓ {name}: correct (bandits with 2, 3 and 6 arms, one near-deterministic; sequence "
          f"policies of 2 and 3 tokens)")


# ----------------------------------------------------------------------------------------------
# The importance-weighted policy gradient
# ----------------------------------------------------------------------------------------------


def _pad_rows(t: torch.Tensor, left: torch.Tensor, extra: int, fill: torch.Tensor) -> torch.Tensor:
    """Each row of ``t`` with ``left[i]`` padding slots before it and ``extra - left[i]`` after,
    filled with that row's ``fill`` value (``fill`` is [n, 1]; it may carry a gradient)."""
    rows = [torch.cat([fill[i].expand(int(left[i])), t[i], fill[i].expand(extra - int(left[i]))])
            for i in range(t.shape[0])]
    return torch.stack(rows)


def check_importance_weighted_surrogate(fn: Callable) -> None:
    """``fn(logp_new, logp_old, rewards, mask)`` -> [n]: per sequence, a surrogate whose gradient
    is w_i R_i grad log pi_new(tau_i), with w_i = pi_new(tau_i) / pi_old(tau_i) over the real
    tokens (mask). Checked exactly: every sequence of small tabular policies, each weighted by
    its probability under pi_old, must give the exact gradient of J at pi_new."""
    name = "importance_weighted_surrogate"
    gen = torch.Generator().manual_seed(2)
    # (T, V, padding slots per row, size of the policy change): the last case moves the policy
    # far, so that sequence log-weights span several nats and a clipped or truncated weight fails
    for case, (T, V, pad, move) in enumerate([(2, 2, 0, 0.4), (3, 3, 2, 0.4), (4, 2, 2, 1.5)]):
        policy = trust.SequencePolicy(T=T, V=V)
        theta_old = 0.5 * torch.randn(policy.n_params, generator=gen, dtype=torch.float64)
        theta = (theta_old + move * torch.randn(policy.n_params, generator=gen, dtype=torch.float64))
        theta.requires_grad_(True)
        reward = torch.rand(V ** T, generator=gen, dtype=torch.float64)
        logp_new = policy.token_log_probs(theta)
        logp_old = policy.token_log_probs(theta_old).detach()
        mask = torch.ones_like(logp_old)
        if pad:  # padding must be ignored: it sits left and right, as much per row as it likes,
            # and holds values that depend on theta, so a gradient through it shows
            left = torch.randint(0, pad + 1, (logp_new.shape[0],), generator=gen)
            logp_new = _pad_rows(logp_new, left, pad, 0.5 * logp_new.sum(-1, keepdim=True) - 1.0)
            logp_old = _pad_rows(logp_old, left, pad, torch.full_like(logp_old[:, :1], -3.0))
            mask = _pad_rows(mask, left, pad, torch.zeros_like(mask[:, :1]))
        args = dict(logp_new=logp_new, logp_old=logp_old, rewards=reward, mask=mask)
        got = _as_tensor(name, _run(name, fn, args))
        n = logp_new.shape[0]
        if got.shape != (n,):
            hint = (" Return one value per sequence (no mean): the checker weights them by "
                    "their probability under pi_old to take the exact expectation."
                    if got.dim() == 0 else "")
            raise ExerciseError(f"{name}: shape {tuple(got.shape)}, expected ({n},).{hint}")
        if not got.requires_grad:
            raise ExerciseError(f"{name}: the result carries no gradient: the weight may be "
                                f"detached, but log pi_new (logp_new) must not be")
        p_old = policy.log_probs(theta_old).exp()
        (grad,) = torch.autograd.grad((p_old * got).sum(), theta, retain_graph=True)
        exact = trust.exact_gradient(policy.log_probs, theta, reward)
        if _close(grad, exact, 1e-8):
            continue
        m = mask
        delta = (logp_new - logp_old) * m
        wrong = {
            "the weight is a sum of per-token ratios; a sequence's weight is their *product*, "
            "pi_new(tau) / pi_old(tau) = prod_t rho_t = exp(sum_t log rho_t). The per-token "
            "surrogate is the first-order approximation PPO uses, exact only at pi_new = pi_old":
                (torch.exp(delta) * m).sum(-1) * reward,
            "the weight is the mean of per-token ratios; a sequence's weight is their product, "
            "exp(sum_t (log pi_new - log pi_old))":
                (torch.exp(delta) * m).sum(-1) / m.sum(-1) * reward,
            "there is no importance weight: samples from pi_old estimate pi_old's gradient, not "
            "pi_new's; multiply by w = pi_new(tau) / pi_old(tau)":
                (logp_new * m).sum(-1) * reward,
            "the weight is inverted: w = pi_new / pi_old, the density of the distribution you "
            "want over the one you sampled from": torch.exp(-delta.sum(-1)) * reward,
            "padding is counted: sum the log-ratios over real tokens only (the mask)":
                torch.exp((logp_new - logp_old).sum(-1)) * reward,
        }
        for message, value in wrong.items():
            (g_wrong,) = torch.autograd.grad((p_old * value).sum(), theta, retain_graph=True)
            if _close(grad, g_wrong, 1e-8):
                raise ExerciseError(f"{name}: {message}")
        diff = (grad - exact).abs().max().item()
        raise ExerciseError(f"{name}: the gradient's exact expectation under pi_old differs from "
                            f"the exact grad J at pi_new by up to {diff:.3g} (a {T}-token policy "
                            f"over {V} symbols)")
    print(f"✓ {name}: correct (its gradient, averaged exactly over pi_old, is grad J at pi_new; "
          f"three sequence policies, padding ignored)")


# ----------------------------------------------------------------------------------------------
# The clip fraction
# ----------------------------------------------------------------------------------------------


def check_clip_fraction(fn: Callable) -> None:
    """``fn(logp_new, logp_old, advantages, mask, eps_low, eps_high)`` -> float: the fraction of
    real tokens whose gradient the clip removes (rho > 1 + eps_high with A > 0, or
    rho < 1 - eps_low with A < 0)."""
    name = "clip_fraction"
    gen = torch.Generator().manual_seed(3)
    # sizes large enough that two different counting mistakes rarely give the same fraction
    # the second case has neither bound at 0.2, so bounds typed in as 0.2 are told apart from
    # eps_low used on both sides
    for N, T, eps_low, eps_high in [(24, 16, 0.2, 0.2), (20, 27, 0.1, 0.3), (32, 21, 0.2, 0.28)]:
        logp_old = -torch.rand(N, T, generator=gen) * 3
        logp_new = logp_old + 0.4 * torch.randn(N, T, generator=gen)
        advantages = torch.randn(N, generator=gen)
        advantages[0] = 0.0                                   # a group without signal
        lengths = torch.randint(1, T + 1, (N,), generator=gen)
        lengths[1] = T
        mask = (torch.arange(T) < lengths[:, None]).float()
        args = dict(logp_new=logp_new, logp_old=logp_old, advantages=advantages, mask=mask,
                    eps_low=eps_low, eps_high=eps_high)
        got = _run(name, fn, args)
        try:
            got = float(got)
        except (TypeError, ValueError, RuntimeError):
            raise ExerciseError(f"{name}: return one number (a float), got {type(got).__name__}") from None
        want = trust.clip_fraction(logp_new, logp_old, advantages, mask, eps_low, eps_high)
        if abs(got - want) < 1e-6:
            continue
        ratio = torch.exp(logp_new - logp_old)
        A = advantages[:, None]

        def frac(flags, over=mask):
            return float((flags.float() * over).sum() / over.sum())

        wrong = {
            "every ratio outside [1 - eps, 1 + eps] is counted; the clip removes a token's "
            "gradient only on the side the advantage pushes towards: rho > 1 + eps_high with "
            "A > 0, rho < 1 - eps_low with A < 0":
                frac((ratio > 1 + eps_high) | (ratio < 1 - eps_low)),
            "tokens with A = 0 are counted: they have no gradient for the clip to remove":
                frac(((A >= 0) & (ratio > 1 + eps_high)) | ((A <= 0) & (ratio < 1 - eps_low))),
            "padding is counted: average over real tokens (the mask) only":
                frac(((A > 0) & (ratio > 1 + eps_high)) | ((A < 0) & (ratio < 1 - eps_low)),
                     torch.ones_like(mask)),
            "the bounds are typed in (0.2 on both sides) instead of taken from eps_low and "
            "eps_high":
                frac(((A > 0) & (ratio > 1.2)) | ((A < 0) & (ratio < 0.8))),
            "eps_low is used on both sides; the upper bound is 1 + eps_high (DAPO's clip-higher "
            "makes them differ)":
                frac(((A > 0) & (ratio > 1 + eps_low)) | ((A < 0) & (ratio < 1 - eps_low))),
            "the log-ratio is compared with the bounds; the clip is on the ratio rho = "
            "exp(log pi_new - log pi_old)":
                frac(((A > 0) & (ratio.log() > 1 + eps_high)) | ((A < 0) & (ratio.log() < 1 - eps_low))),
        }
        for message, value in wrong.items():
            if abs(got - value) < 1e-6 and abs(value - want) > 1e-6:
                raise ExerciseError(f"{name}: {message}")
        raise ExerciseError(f"{name}: {got:.4f}, expected {want:.4f} ({N} sequences of up to {T} "
                            f"tokens, eps_low {eps_low}, eps_high {eps_high})")
    print(f"✓ {name}: correct (asymmetric bounds, advantages of both signs and zero, padding)")


# ----------------------------------------------------------------------------------------------
# The training-inference mismatch: TRL's importance weights
# ----------------------------------------------------------------------------------------------


def _weight_mistakes(lp, lq, mask, mode, clip_max) -> dict[str, torch.Tensor]:
    from .mismatch import importance_weights

    other = {"token_truncate": "token_mask", "token_mask": "token_truncate",
             "sequence_truncate": "sequence_mask", "sequence_mask": "sequence_truncate"}[mode]
    level = "token" if mode.startswith("token") else "sequence"
    flipped = f"{'sequence' if level == 'token' else 'token'}_{mode.split('_')[1]}"
    ratio = torch.exp(((lp - lq) * mask).sum(-1, keepdim=True)).expand_as(mask) if level == "sequence" \
        else torch.exp((lp - lq) * mask)
    return {
        "the ratio is inverted: the weight is pi_train / pi_sampler, the distribution you want over "
        "the one that drew the samples": importance_weights(lq, lp, mask, mode, clip_max),
        f"this is '{other}'; '{mode}' {'clips the ratio at' if mode.endswith('truncate') else 'sets to 0 a ratio above'} clip_max":
            importance_weights(lp, lq, mask, other, clip_max),
        f"this is the {'sequence' if level == 'token' else 'token'}-level weight; '{mode}' "
        + ("uses each token's own ratio" if level == "token" else
           "uses the whole sequence's ratio, the product over its real tokens, for every token"):
            importance_weights(lp, lq, mask, flipped, clip_max),
        "padding is counted in the sequence's ratio: multiply the log-ratios by the mask before "
        "summing them": torch.exp((lp - lq).sum(-1, keepdim=True)).expand_as(mask).clamp(max=clip_max) * mask
        if mode == "sequence_truncate" else torch.zeros(0),
        "padding positions are not 0: multiply the weights by the mask":
            _capped(torch.exp((lp - lq) * mask) if level == "token" else ratio, mode, clip_max),
        "padding positions are not 0 (they hold their own ratios): multiply the weights by the mask":
            importance_weights(lp, lq, torch.ones_like(mask), mode, clip_max) if level == "token"
            else torch.zeros(0),
        "the cap is typed in (3.0) instead of taken from clip_max": importance_weights(lp, lq, mask, mode, 3.0),
    }


def _capped(ratio: torch.Tensor, mode: str, clip_max: float) -> torch.Tensor:
    return ratio.clamp(max=clip_max) if mode.endswith("truncate") else torch.where(ratio > clip_max, 0.0, ratio)


def check_importance_weights(fn: Callable) -> None:
    """``fn(logp_train, logp_sampler, mask, mode, clip_max)`` -> [n, T] weights, TRL's
    ``vllm_importance_sampling_mode``: the ratio pi_train / pi_sampler per token ('token_*') or
    per sequence ('sequence_*', broadcast to its tokens), clipped at clip_max ('*_truncate') or set
    to 0 above it ('*_mask'); constants, 0 on padding (``mismatch.importance_weights``)."""
    from .mismatch import MODES, importance_weights

    name = "importance_weights"
    gen = torch.Generator().manual_seed(9)
    # caps: TRL's default, one that binds often, and none at all (the lesson's "full weight")
    cases = [(mode, n, T, cap) for (mode, cap), (n, T) in
             zip([(m, c) for c in (3.0, 1.7, math.inf) for m in MODES], [(6, 4), (5, 7), (8, 3), (4, 5)] * 3)]
    for mode, n, T, clip_max in cases:
        label = f"mode {mode!r}, clip_max {clip_max}, {n} sequences of up to {T} tokens"
        lq = -2 * torch.rand(n, T, generator=gen, dtype=torch.float64)
        # per-token log-ratios of up to about +-0.7: sequence ratios above and below the caps
        lp = (lq + 0.45 * torch.randn(n, T, generator=gen, dtype=torch.float64)).requires_grad_(True)
        lengths = torch.randint(1, T + 1, (n,), generator=gen)
        lengths[0] = T
        mask = (torch.arange(T) < lengths[:, None]).to(torch.float64)
        args = dict(logp_train=lp, logp_sampler=lq, mask=mask, mode=mode, clip_max=clip_max)
        got = _as_tensor(name, _run(name, fn, args))
        want = importance_weights(lp, lq, mask, mode, clip_max)
        if got.shape != want.shape:
            raise ExerciseError(f"{name}: on {label} the result has shape {tuple(got.shape)}, expected "
                                f"{tuple(want.shape)} (one weight per token; a sequence's weight is "
                                f"repeated on its tokens)")
        if got.requires_grad:
            raise ExerciseError(f"{name}: the weights carry a gradient. They are constants (TRL computes "
                                f"them from log-probs without one): detach, or the weight's own "
                                f"derivative enters the policy gradient")
        # 1e-6: a cap built as a float32 tensor (1.7 is 1.70000005 there) is right, not a mistake
        if _close(got, want, 1e-6):
            continue
        if not torch.isfinite(got).all():
            raise ExerciseError(f"{name}: NaN or inf weights on {label}; with no cap (clip_max = inf) "
                                f"arithmetic like cap * (ratio > cap) gives inf * 0 = NaN: use "
                                f"clamp or torch.where")
        for message, value in _weight_mistakes(lp.detach(), lq, mask, mode, clip_max).items():
            if value.numel() and _close(got, value, 1e-6) and not _close(value, want, 1e-6):
                raise ExerciseError(f"{name}: {message} (on {label})")
        diff = (got - want).abs().max().item()
        raise ExerciseError(f"{name}: differs from TRL's weights by up to {diff:.3g} on {label}")
    print(f"✓ {name}: correct (the four modes of TRL's correction, three caps, padding)")

