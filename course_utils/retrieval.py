"""The policy gradient of a retrieval-augmented policy, on a problem small enough to enumerate
(lesson 8's retrieval track).

A two-stage policy: a retriever picks one of K documents, pi_phi(d) = softmax(phi)_d, then a
generator answers given it, pi_theta(y | d) = softmax(theta[d])_y. The answer earns R(y). So

    log pi(d, y) = log pi_phi(d) + log pi_theta(y | d),

and the score-function gradient of J = E[R] splits exactly: E[R grad_phi log pi_phi(d)] is
grad_phi J and E[R grad_theta log pi_theta(y | d)] is grad_theta J, one advantage for both.
What the split does *not* settle is which baseline each part may use: anything that does not
depend on the sampled d is fine for the retriever, while the generator's part may subtract a
baseline that depends on d. A baseline that depends on d, in the retriever's part, subtracts the
very signal the retriever learns from: ``estimates`` measures this.
"""

from __future__ import annotations

import torch

BASELINES = ("none", "group mean", "leave-one-out", "per-document mean")


def log_probs(phi: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """[K, Y] log pi(d, y) = log pi_phi(d) + log pi_theta(y | d)."""
    return phi.log_softmax(-1)[:, None] + theta.log_softmax(-1)


def objective(phi: torch.Tensor, theta: torch.Tensor, reward: torch.Tensor) -> torch.Tensor:
    """J = sum_{d, y} pi(d, y) R(y), exactly."""
    return (log_probs(phi, theta).exp() * reward).sum()


def exact_gradients(phi, theta, reward) -> tuple[torch.Tensor, torch.Tensor]:
    """(grad_phi J, grad_theta J) by autograd through the enumerated objective."""
    phi, theta = phi.detach().requires_grad_(True), theta.detach().requires_grad_(True)
    return torch.autograd.grad(objective(phi, theta, reward), (phi, theta))


def score_function_parts(phi, theta, reward) -> tuple[torch.Tensor, torch.Tensor]:
    """The two parts of E[R grad log pi(d, y)], each as an exact sum over (d, y): the retriever's
    E[R grad_phi log pi_phi(d)] and the generator's E[R grad_theta log pi_theta(y | d)]."""
    K, Y = theta.shape
    p = log_probs(phi, theta).exp()                                    # [K, Y]
    pi_d, pi_y = phi.softmax(-1), theta.softmax(-1)
    retriever_score = torch.eye(K, dtype=phi.dtype) - pi_d             # row d: grad_phi log pi(d)
    retriever = ((p * reward).sum(-1)[:, None] * retriever_score).sum(0)
    # grad_theta log pi(y | d) is (e_y - pi(. | d)) in row d, zero in the other rows
    generator = p[:, :, None] * reward[None, :, None] * (torch.eye(Y, dtype=theta.dtype)[None] - pi_y[:, None, :])
    return retriever, generator.sum(1)                                 # [K], [K, Y]


def sample(phi, theta, batches: int, group: int, generator: torch.Generator):
    """``batches`` groups of ``group`` rollouts: d ~ pi_phi, then y ~ pi_theta(. | d)."""
    d = torch.multinomial(phi.softmax(-1).expand(batches, -1), group, replacement=True, generator=generator)
    probs = theta.softmax(-1)[d]                                       # [B, G, Y]
    y = torch.multinomial(probs.view(-1, probs.shape[-1]), 1, generator=generator).view(d.shape)
    return d, y


def baseline_values(r: torch.Tensor, d: torch.Tensor, K: int, kind: str) -> torch.Tensor:
    """[B, G] baselines. 'per-document mean': the mean reward of the *other* rollouts of the
    group that retrieved the same document (0 when there are none)."""
    G = r.shape[-1]
    if kind == "none":
        return torch.zeros_like(r)
    if kind == "group mean":
        return r.mean(-1, keepdim=True).expand_as(r)
    if kind == "leave-one-out":
        return (r.sum(-1, keepdim=True) - r) / (G - 1)
    if kind == "per-document mean":
        one_hot = torch.nn.functional.one_hot(d, K).to(r.dtype)       # [B, G, K]
        total = (one_hot * r[..., None]).sum(1, keepdim=True)         # [B, 1, K]
        count = one_hot.sum(1, keepdim=True)
        others = ((total - one_hot * r[..., None]) * one_hot).sum(-1)
        n_others = ((count - one_hot) * one_hot).sum(-1)
        return torch.where(n_others > 0, others / n_others.clamp(min=1), torch.zeros_like(r))
    raise ValueError(f"baseline must be one of {BASELINES}, got {kind!r}")


def estimates(phi, theta, reward, d, y, kind: str) -> tuple[torch.Tensor, torch.Tensor]:
    """Per group, the score-function estimates of the two parts with baseline ``kind``:
    retriever [B, K] and generator [B, K, Y], each the mean over the group's G rollouts."""
    K, Y = theta.shape
    r = reward[y]
    advantage = r - baseline_values(r, d, K, kind)
    retriever_score = torch.nn.functional.one_hot(d, K).to(phi.dtype) - phi.softmax(-1)
    retriever = (advantage[..., None] * retriever_score).mean(1)
    pi_y = theta.softmax(-1)[d]                                        # [B, G, Y]
    generator_score = torch.nn.functional.one_hot(y, Y).to(theta.dtype) - pi_y
    per_rollout = advantage[..., None, None] * torch.nn.functional.one_hot(d, K).to(theta.dtype)[..., None] \
        * generator_score[:, :, None, :]
    return retriever, per_rollout.mean(1)


def cross_document_retriever_estimate(phi, theta, reward, d, y) -> torch.Tensor:
    """[B, K] an estimate of grad_phi J that reuses the group's answers for *every* document:
    Q(d') = E[R | d'] estimated by (1/G) sum_i pi(y_i | d') R(y_i) / m(y_i), with m the
    mixture sum_d pi_phi(d) pi(y | d) the answers were drawn from (unbiased, and the weights are
    bounded by 1 / pi_phi(d')). It needs each answer scored under every document (one forward
    pass each), but no new generation. Then grad_phi J = sum_d' pi(d') (Q(d') - J) e_d'."""
    pi_d = phi.softmax(-1)
    pi_y = theta.softmax(-1)                                           # [K, Y]
    mixture = pi_d @ pi_y                                              # [Y]
    weights = pi_y[:, y].permute(1, 2, 0) / mixture[y][..., None]      # [B, G, K]
    q = (weights * reward[y][..., None]).mean(1)                       # [B, K]
    return pi_d * (q - (pi_d * q).sum(-1, keepdim=True))


def summarize(samples: torch.Tensor, exact: torch.Tensor) -> dict:
    """Bias (with its standard error) and noise of a batch of estimates [B, ...] of ``exact``,
    both relative to |exact|; the signal-to-noise ratio of one estimate is 1 / noise."""
    flat, target = samples.flatten(1), exact.flatten()
    mean = flat.mean(0)
    scale = float(target.norm())
    noise = float(((flat - mean) ** 2).sum(-1).mean().sqrt()) / scale
    return dict(bias=float((mean - target).norm()) / scale,
                bias_se=noise / len(flat) ** 0.5, noise=noise, snr=1.0 / noise if noise > 0 else float("inf"))
