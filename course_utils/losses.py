"""Policy-gradient estimators and losses, named after the math they implement.

Shapes: N sequences (N = B prompts x G completions, grouped so that rows g*G ... g*G+G-1 are
the G completions of prompt g), T completion tokens. ``mask`` is 1 on real completion tokens
(up to and including the first end-of-sequence token) and 0 on padding.

Conventions. A "loss" here is a *surrogate*: a scalar whose gradient is the (negated) policy
gradient estimate. Its value is not a measure of how well the policy does; plot the reward.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

# ---------------------------------------------------------------------------------------------
# REINFORCE
# ---------------------------------------------------------------------------------------------


def returns_to_go(rewards: torch.Tensor, gamma: float = 1.0) -> torch.Tensor:
    """G_t = sum_{k >= t} gamma^(k - t) r_k along the last dimension.

    With a terminal-only reward R (r_T = R, all other r_t = 0) and gamma = 1, G_t = R for
    *every* t: every token gets the same credit. (Not "only the last token", as is sometimes
    claimed.) With gamma < 1, earlier tokens get less: G_t = gamma^(T - t) R.
    """
    out = torch.zeros_like(rewards)
    running = torch.zeros_like(rewards[..., 0])
    for t in reversed(range(rewards.shape[-1])):
        running = rewards[..., t] + gamma * running
        out[..., t] = running
    return out


def terminal_rewards(sequence_rewards: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Per-token rewards that are 0 everywhere except R_i on sequence i's last real token."""
    lengths = mask.long().sum(-1)
    per_token = torch.zeros(mask.shape, dtype=sequence_rewards.dtype, device=mask.device)
    rows = torch.arange(mask.shape[0], device=mask.device)
    has_tokens = lengths > 0
    per_token[rows[has_tokens], lengths[has_tokens] - 1] = sequence_rewards[has_tokens]
    return per_token


def reinforce_loss(logprobs: torch.Tensor, weights: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """-1/N sum_i sum_t log pi(a_t|s_t) * w_t, whose gradient is minus the REINFORCE estimate.

    ``weights`` is per token ([N, T]: returns-to-go, possibly minus a baseline) or per sequence
    ([N]: the same weight for every token of a sequence).
    """
    if weights.dim() == 1:
        weights = weights.unsqueeze(-1)
    return -(logprobs * weights.detach() * mask).sum(-1).mean()


# ---------------------------------------------------------------------------------------------
# Baselines: b must not depend on the action it is subtracted from, or the estimate is biased.
# ---------------------------------------------------------------------------------------------


def batch_mean_baseline(rewards: torch.Tensor) -> torch.Tensor:
    """b_i = mean of all N rewards. Includes r_i itself, so it is slightly biased: in
    expectation it scales the gradient by (N - 1) / N."""
    return rewards.mean().expand_as(rewards)


def leave_one_out_baseline(rewards: torch.Tensor, group_size: int) -> torch.Tensor:
    """b_i = mean of the *other* G - 1 rewards of i's group (RLOO): exactly unbiased."""
    r = rewards.view(-1, group_size)
    return ((r.sum(-1, keepdim=True) - r) / (group_size - 1)).reshape(rewards.shape)


class RunningMeanBaseline:
    """An exponential moving average of past batches' mean reward.

    ``__call__`` returns the baseline for the current batch *before* folding the batch in, so
    the baseline never depends on the actions it is applied to (hence no bias).
    """

    def __init__(self, momentum: float = 0.9, initial: float = 0.0):
        if not 0 <= momentum < 1:
            raise ValueError(f"momentum must be in [0, 1), got {momentum}")
        self.momentum, self.value = momentum, initial

    def __call__(self, rewards: torch.Tensor) -> torch.Tensor:
        baseline = torch.full_like(rewards, self.value)
        self.value = self.momentum * self.value + (1 - self.momentum) * rewards.mean().item()
        return baseline


# ---------------------------------------------------------------------------------------------
# GRPO
# ---------------------------------------------------------------------------------------------


def constant_groups(rewards: torch.Tensor, group_size: int) -> torch.Tensor:
    """[n_groups, 1] True where a group's G rewards are all equal: no signal, advantage 0."""
    r = rewards.view(-1, group_size)
    return r.max(-1, keepdim=True).values == r.min(-1, keepdim=True).values


def group_advantages(rewards: torch.Tensor, group_size: int, center: str = "group",
                     scale: str = "group", eps: float = 1e-4) -> tuple[torch.Tensor, int]:
    """Group-relative advantages A_i = (r_i - mean) / (std + eps), and the zero-std group count.

    center="group", scale="group": DeepSeekMath's GRPO, statistics over the G completions of
    the same prompt. scale="none" with center="group": Dr. GRPO (no std division).
    center="batch", scale="batch": the seed text's whole-batch standardization.
    The std is Bessel-corrected and eps = 1e-4, as in TRL, so results match it.

    A group whose G rewards are all equal has std 0 and, when centred on its own mean,
    advantage 0 for every member: it carries no learning signal. Their count is returned.
    """
    if rewards.dim() != 1 or rewards.numel() % group_size:
        raise ValueError(f"rewards must be 1-D with a multiple of group_size={group_size} "
                         f"entries, got shape {tuple(rewards.shape)}")
    if center == "batch" and scale == "group":
        raise ValueError("center='batch' with scale='group' divides an all-equal group's "
                         "batch-centred rewards by its std of 0 (+ eps); use scale='batch' (the "
                         "seed's whole-batch standardization) or scale='none'")
    r = rewards.view(-1, group_size)
    constant = constant_groups(rewards, group_size)
    zero_std_groups = int(constant.sum())
    if center == "group":
        # exactly 0 for an all-equal group: r - mean(r) can be a rounding error (the mean of
        # seven copies of x need not be x), and dividing that by std + eps would blow it up
        centred = torch.where(constant, 0.0, r - r.mean(-1, keepdim=True))
    elif center == "batch":
        centred = r - rewards.mean() if rewards.max() > rewards.min() else torch.zeros_like(r)
    else:
        raise ValueError(f"center must be 'group' or 'batch', got {center!r}")
    if scale == "group":
        std = r.std(-1, keepdim=True)
    elif scale == "batch":
        std = rewards.std()
    elif scale == "none":
        return centred.reshape(-1), zero_std_groups
    else:
        raise ValueError(f"scale must be 'group', 'batch' or 'none', got {scale!r}")
    return (centred / (std + eps)).reshape(-1), zero_std_groups


def clipped_surrogate(logprobs: torch.Tensor, old_logprobs: torch.Tensor,
                      advantages: torch.Tensor, eps_low: float = 0.2,
                      eps_high: float = 0.2) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-token PPO/GRPO clipped loss  -min(rho A, clip(rho, 1 - eps_low, 1 + eps_high) A).

    rho = pi_theta / pi_old per token. Returns (per-token loss [N, T], bool mask of tokens
    where the clipped branch is the active one, i.e. whose gradient is zero).
    """
    if advantages.dim() == 1:
        advantages = advantages.unsqueeze(-1)
    ratio = torch.exp(logprobs - old_logprobs)
    pg_loss1 = -ratio * advantages
    pg_loss2 = -torch.clamp(ratio, 1 - eps_low, 1 + eps_high) * advantages
    return torch.maximum(pg_loss1, pg_loss2), pg_loss2 > pg_loss1


def k3_kl(logprobs: torch.Tensor, ref_logprobs: torch.Tensor) -> torch.Tensor:
    """Per-token k3 estimate of KL(pi_theta || pi_ref): pi_ref/pi_theta - log(pi_ref/pi_theta) - 1.

    Always >= 0 (x - log x - 1 >= 0), and unbiased when the token was sampled from pi_theta.
    """
    delta = ref_logprobs - logprobs
    # expm1(d) - d, not exp(d) - d - 1: the same value, without the cancellation that makes the
    # latter slightly negative (about -1e-16) when d is tiny; the clamp catches what rounding is left
    return (torch.expm1(delta) - delta).clamp(min=0)


def token_entropy(logits: torch.Tensor) -> torch.Tensor:
    """H(pi(.|s_t)) = -sum_a pi(a) log pi(a) for each position, computed in float32."""
    logp = F.log_softmax(logits.float(), dim=-1)
    return -(logp.exp() * logp).sum(-1)


def high_entropy_mask(entropy: torch.Tensor, mask: torch.Tensor, top_quantile: float) -> torch.Tensor:
    """1 at the real tokens whose entropy is at or above the (1 - rho) quantile of the real
    tokens' entropies (rho = ``top_quantile``), else 0: the "forking" tokens of Wang et al.
    (2025, "Beyond the 80/20 rule"), where a reply can still go several ways. TRL's
    ``get_high_entropy_mask`` (which first gathers the entropies from every process):
    ``torch.quantile``'s linear interpolation, then ``>=``, so every token tied at the threshold
    is kept and rho = 1 keeps every real token. No gradient: the mask only chooses which tokens
    the policy term trains."""
    if not 0 < top_quantile <= 1:
        raise ValueError(f"top_quantile must be in (0, 1], got {top_quantile}")
    real = mask.bool()
    values = entropy.detach()[real].float()
    if values.numel() == 0:
        return torch.zeros_like(mask, dtype=entropy.dtype)
    threshold = torch.quantile(values, 1.0 - top_quantile)
    return ((entropy.detach().float() >= threshold) & real).to(entropy.dtype)


def entropy_weight(rewards: torch.Tensor, mode: str, coef: float, max_weight: float) -> float:
    """Weight of the entropy bonus. A course extension: GRPO itself has no entropy term.

    "none": 0. "constant": coef. "inverse_variance" (the seed text's idea): coef / Var(r) over
    the batch (population variance), capped at ``max_weight`` so a batch of equal rewards
    (Var = 0) gives the cap instead of infinity.
    """
    if mode == "none":
        return 0.0
    if mode == "constant":
        return coef
    if mode == "inverse_variance":
        var = rewards.float().var(unbiased=False).item()
        return max_weight if var <= coef / max_weight else coef / var
    raise ValueError(f"unknown entropy bonus mode {mode!r}")


class AdaptiveEntropy:
    """An entropy-bonus weight that holds the policy's entropy near a target (Skywork-OR1's
    adaptive entropy control, arXiv 2505.22312, sec. 3.2; TRL 1.16's ``use_adaptive_entropy``):

        c_{k+1} = clip(c_k + delta * sign(H_target - H_k), 0, c_max)
        weight_{k+1} = c_{k+1} if H_k < H_target else 0

    where H_k is the mean entropy per completion token of step k's batch: the weight a step
    uses is set by the steps before it (the entropy of this step's batch is known only after its
    forward), as in TRL. While the policy is
    more random than the target the bonus is off and c drifts down; once it falls below, c grows
    by ``delta`` a step until the bonus pushes entropy back up. Unlike a constant bonus it does
    not fight the early, wanted drop from the base model's entropy."""

    def __init__(self, target: float, delta: float, max_weight: float):
        self.target, self.delta, self.max_weight = target, delta, max_weight
        self.coef = 0.0
        self.entropy: float | None = None   # the last step's mean entropy (None before any)

    def weight(self) -> float:
        return self.coef if self.entropy is not None and self.entropy < self.target else 0.0

    def observe(self, entropy: float) -> None:
        if not math.isfinite(entropy):
            return
        self.entropy = entropy
        step = self.delta if entropy < self.target else -self.delta
        self.coef = min(max(self.coef + step, 0.0), self.max_weight)

    def state_dict(self) -> dict:
        return dict(coef=self.coef, entropy=self.entropy)

    def load_state_dict(self, state: dict) -> None:
        self.coef, self.entropy = state["coef"], state["entropy"]


class RewardAwareKL:
    """A KL coefficient that reacts to the batch (a course extension for the frontier-researcher
    track, not part of GRPO): beta_t = beta * clip((v_avg / v_t) * (g_{t-1} / g_avg), 1/r, r).

    v_t is this batch's reward variance and g_{t-1} the previous step's gradient norm; v_avg and
    g_avg are their running (exponential) means. A batch with less reward spread than usual
    carries less signal, and a step with a larger gradient than usual moves the policy further:
    both pull harder towards the reference. The ratio is clipped to [1/r, r]."""

    def __init__(self, beta: float, clip_range: float = 4.0, momentum: float = 0.9, eps: float = 1e-6):
        self.beta, self.clip_range, self.momentum, self.eps = beta, clip_range, momentum, eps
        self.var_avg: float | None = None
        self.grad_avg: float | None = None
        self.last_grad: float | None = None

    def coefficient(self, rewards: torch.Tensor) -> float:
        var = float(rewards.float().var(unbiased=False))
        self.var_avg = var if self.var_avg is None else self.momentum * self.var_avg + (1 - self.momentum) * var
        factor = (self.var_avg + self.eps) / (var + self.eps)
        if self.last_grad is not None and self.grad_avg:
            factor *= self.last_grad / self.grad_avg
        return self.beta * min(max(factor, 1 / self.clip_range), self.clip_range)

    def observe_gradient(self, grad_norm: float) -> None:
        if not math.isfinite(grad_norm):
            return
        self.last_grad = grad_norm
        self.grad_avg = grad_norm if self.grad_avg is None else \
            self.momentum * self.grad_avg + (1 - self.momentum) * grad_norm

    def state_dict(self) -> dict:
        return dict(var_avg=self.var_avg, grad_avg=self.grad_avg, last_grad=self.last_grad)

    def load_state_dict(self, state: dict) -> None:
        self.var_avg, self.grad_avg, self.last_grad = state["var_avg"], state["grad_avg"], state["last_grad"]


def aggregate(per_token: torch.Tensor, mask: torch.Tensor, loss_type: str,
              max_completion_length: int | None = None, total_sequences: int | None = None,
              total_tokens: int | float | None = None, micro_batches: int = 1) -> torch.Tensor:
    """Average a per-token loss into a scalar, in one of the ways the literature does it.

    "grpo":  1/N sum_i 1/|o_i| sum_t l_it   (mean per sequence, then over sequences; DeepSeekMath)
    "dapo":  sum_it l_it / sum_i |o_i|   (every token of the batch weighs the same; DAPO)
    "bnpo":  this micro-batch's own token mean, divided by ``micro_batches`` (TRL's "bnpo")
    "dr_grpo": sum_it l_it / (N * max_completion_length)   (a constant; Dr. GRPO)

    "grpo" gives each token of a short completion more weight than a token of a long one,
    which is the length bias Dr. GRPO points out. For gradient accumulation, pass the whole
    batch's ``total_sequences`` / ``total_tokens`` so that "grpo", "dapo" and "dr_grpo"
    micro-batch losses sum to the full-batch loss exactly. "bnpo" is TRL 1.16's: each
    micro-batch (on each process) is normalized by its *own* token count and the results are
    averaged, so with one micro-batch it is "dapo", and with several of unequal token counts it
    is not the full batch's token mean: a token in a micro-batch with fewer tokens weighs more.
    """
    mask = mask.to(per_token.dtype)
    n = per_token.shape[0] if total_sequences is None else total_sequences
    if loss_type == "grpo":
        per_sequence = (per_token * mask).sum(-1) / mask.sum(-1).clamp(min=1)
        return per_sequence.sum() / n
    if loss_type == "dapo":
        tokens = mask.sum() if total_tokens is None else total_tokens
        return (per_token * mask).sum() / max(float(tokens), 1.0)
    if loss_type == "bnpo":
        return (per_token * mask).sum() / mask.sum().clamp(min=1.0) / micro_batches
    if loss_type == "dr_grpo":
        length = max_completion_length if max_completion_length is not None else per_token.shape[-1]
        return (per_token * mask).sum() / (n * length)
    raise ValueError(f"unknown loss_type {loss_type!r}; choose grpo, bnpo, dapo or dr_grpo")


def masked_mean(x: torch.Tensor, mask: torch.Tensor) -> float:
    """Mean of x over real tokens, as a Python float (for logging)."""
    mask = mask.to(x.dtype)
    return float((x * mask).sum() / mask.sum().clamp(min=1))


def grpo_loss(logprobs: torch.Tensor, old_logprobs: torch.Tensor, advantages: torch.Tensor,
              mask: torch.Tensor, *, loss_type: str = "grpo", eps_low: float = 0.2,
              eps_high: float = 0.2, ref_logprobs: torch.Tensor | None = None, beta: float = 0.0,
              entropy: torch.Tensor | None = None, entropy_weight: float = 0.0,
              max_completion_length: int | None = None, total_sequences: int | None = None,
              total_tokens: int | float | None = None, micro_batches: int = 1,
              sampling_weights: torch.Tensor | None = None,
              top_entropy_quantile: float = 1.0) -> tuple[torch.Tensor, dict[str, float]]:
    """The GRPO objective, negated into a loss (DeepSeekMath eq. 3, plus the options above).

    per-token loss = -w min(rho A, clip(rho) A) + beta * KL_k3 - entropy_weight * H
    The KL term sits in the loss (not in the reward) so it regularizes every token directly.
    ``sampling_weights`` w (constants, 1 if None) correct for tokens drawn by a sampler other
    than the trainer (``mismatch.importance_weights``); as in TRL they weight the surrogate only,
    since the KL and entropy terms are computed under the trainer itself.
    ``top_entropy_quantile`` rho < 1 keeps the surrogate only at the top rho share of tokens by
    ``entropy`` (``high_entropy_mask``; TRL's option of that name): the others still count in the
    average's denominator and still get the KL term, as in TRL, and the entropy bonus too, where
    TRL 1.16 applies its bonus (and measures its adaptive target) on the kept tokens only.
    """
    # Whatever padding positions hold must not matter, not even an inf (0 * inf is NaN): replace
    # it with 0 before any exp, which also keeps the gradient at padding exactly 0.
    real = mask.bool()
    logprobs, old_logprobs = torch.where(real, logprobs, 0.0), torch.where(real, old_logprobs, 0.0)
    if ref_logprobs is not None:
        ref_logprobs = torch.where(real, ref_logprobs, 0.0)
    if entropy is not None:
        entropy = torch.where(real, entropy, 0.0)
    per_token, clipped = clipped_surrogate(logprobs, old_logprobs, advantages, eps_low, eps_high)
    stats = {"clip_fraction": masked_mean(clipped.float(), mask)}
    if sampling_weights is not None:
        weights = torch.where(real, sampling_weights.detach(), 0.0)
        per_token = per_token * weights
        stats["is_weight_mean"] = masked_mean(weights, mask)
    if top_entropy_quantile < 1:
        if entropy is None:
            raise ValueError("top_entropy_quantile < 1 needs the per-token entropy")
        forks = high_entropy_mask(entropy, mask, top_entropy_quantile)
        per_token = per_token * forks
        stats["high_entropy_frac"] = masked_mean(forks, mask)
    if beta > 0:
        if ref_logprobs is None:
            raise ValueError("beta > 0 needs ref_logprobs from the reference model")
        kl = k3_kl(logprobs, ref_logprobs)
        per_token = per_token + beta * kl
        stats["kl"] = masked_mean(kl.detach(), mask)
    if entropy is not None:
        stats["entropy"] = masked_mean(entropy.detach(), mask)
        if entropy_weight > 0:
            per_token = per_token - entropy_weight * entropy
    loss = aggregate(per_token, mask, loss_type, max_completion_length, total_sequences,
                     total_tokens, micro_batches)
    return loss, stats
