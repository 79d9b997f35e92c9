"""The training-inference mismatch, exactly (lesson 4, section 6).

A fast sampler (vLLM, a lower precision, top-k or top-p) draws completions from a distribution q
that is not the trainer's pi_theta, and the trainer then scores them under pi_theta. The policy
gradient estimated on those samples is biased. On a sequence policy small enough to enumerate
(``trust.SequencePolicy``) every expectation is an exact sum, so the bias of each estimator, and
the variance of one sample's gradient, are numbers rather than estimates.

* ``truncated_table``: the sampler's per-token log-probabilities under top-k (the k largest
  logits of each row, renormalized), as vLLM reports them.
* ``rounded_table``: a sampler that rounds the logits to a lower precision (bf16) first.
* ``importance_weights``: TRL 1.16's correction (``vllm_importance_sampling_mode``): the ratio
  pi_train / pi_sampler per token or per sequence, truncated (clipped at C_max) or masked (set
  to 0 above C_max).
* ``gradient_moments``: the exact mean and total variance of a one-sample gradient estimate.
"""

from __future__ import annotations

import torch

from .trust import SequencePolicy

MODES = ("token_truncate", "token_mask", "sequence_truncate", "sequence_mask")


def truncated_table(theta: torch.Tensor, policy: SequencePolicy, k: int) -> torch.Tensor:
    """[T, V+1, V] log-probabilities of top-k sampling: each row's k largest logits renormalized,
    -inf elsewhere. Differentiable in theta (the renormalization is)."""
    logits = theta.view(policy.T, policy.V + 1, policy.V)
    keep = logits >= logits.topk(k, dim=-1).values[..., -1:]
    return torch.where(keep, logits, float("-inf")).log_softmax(-1)


def rounded_table(theta: torch.Tensor, policy: SequencePolicy, dtype=torch.bfloat16) -> torch.Tensor:
    """[T, V+1, V] log-probabilities of a sampler that rounds the logits to ``dtype`` first (the
    softmax then in full precision): close to pi_theta, not equal. Not differentiable."""
    logits = theta.detach().view(policy.T, policy.V + 1, policy.V)
    return logits.to(dtype).to(theta.dtype).log_softmax(-1)


def token_log_probs(table: torch.Tensor, policy: SequencePolicy, sequences: torch.Tensor | None = None) -> torch.Tensor:
    """[M, T] log q(x_t | x_{t-1}) of every listed (or given) sequence, for a [T, V+1, V] table."""
    x = policy.sequences if sequences is None else sequences
    previous = torch.cat([torch.full((x.shape[0], 1), policy.V), x[:, :-1]], 1)
    return table[torch.arange(policy.T), previous, x]


def importance_weights(logp_train: torch.Tensor, logp_sampler: torch.Tensor, mask: torch.Tensor,
                       mode: str, clip_max: float = 3.0) -> torch.Tensor:
    """[n, T] weights correcting samples from the sampler towards the trainer, TRL's way: the
    ratio pi_train / pi_sampler per token (``token_*``) or of the whole sequence, the product
    over its real tokens, broadcast to them (``sequence_*``); ``*_truncate`` clips it at
    ``clip_max``, ``*_mask`` sets it to 0 above. Constants (no gradient); 0 on padding."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    log_ratio = ((logp_train - logp_sampler) * mask).detach()
    if mode.startswith("sequence"):
        log_ratio = log_ratio.sum(-1, keepdim=True).expand_as(mask)
    ratio = torch.exp(log_ratio)
    if mode.endswith("truncate"):
        ratio = ratio.clamp(max=clip_max)
    else:
        ratio = torch.where(ratio > clip_max, 0.0, ratio)
    return ratio * mask


def gradient_moments(policy: SequencePolicy, theta: torch.Tensor, sampler_log_probs: torch.Tensor,
                     reward: torch.Tensor, weights: torch.Tensor | None = None,
                     score_table: torch.Tensor | None = None) -> tuple[torch.Tensor, float]:
    """The exact mean and total variance (trace of the covariance) of the one-sample estimate
    R(x) sum_t w_t(x) grad log p(x_t | x_<t), x drawn from the sampler.

    ``sampler_log_probs`` [M, T]: the sampler's per-token log-probs of every sequence (-inf
    where a token is outside its support); ``weights`` [M, T]: per-token weights (1 if None);
    ``score_table``: score under these log-probs instead of pi_theta's (a function of theta)."""
    q = sampler_log_probs.sum(-1).exp()
    support = q > 0
    theta = theta.detach().requires_grad_(True)

    def score_log_probs(th):
        lp = policy.token_log_probs(th) if score_table is None else token_log_probs(score_table(th), policy)
        return lp[support]

    scores = torch.autograd.functional.jacobian(score_log_probs, theta)          # [M', T, d]
    w = torch.ones_like(sampler_log_probs) if weights is None else weights
    per_sample = reward[support, None] * (w[support, :, None] * scores).sum(1)   # [M', d]
    q = q[support]
    mean = (q[:, None] * per_sample).sum(0)
    variance = float((q * ((per_sample - mean) ** 2).sum(-1)).sum())
    return mean, variance
