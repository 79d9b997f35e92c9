"""The geometry of a policy, on problems small enough to enumerate (the trust-region lesson).

* Two policies with every outcome listed, so that expectations are exact sums:
  a softmax bandit with K arms and K-1 free logits (the last is fixed at 0, so no direction of
  the parameters leaves the policy unchanged and the Fisher matrix is invertible), and a
  tabular sequence policy that writes T tokens from a vocabulary of V, each token's logits
  looked up by (position, previous token).
* The Fisher information matrix F(theta) = E[grad log pi grad log pi^T], the natural gradient
  F^-1 grad J, and the step that maximizes the linearized objective under a KL budget (TRPO's),
  formed explicitly and, as TRPO does at scale, matrix-free: Fisher-vector products by double
  backward, conjugate gradients and a backtracking line search.
* Importance weights of whole sequences, against per-token ratios.

Everything here is a reference for the lesson's checkers and cells; each formula is checked
against an independent computation in ``tests/test_trust.py`` (autograd's Hessian of the KL,
finite differences, closed forms).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Callable

import torch

# ----------------------------------------------------------------------------------------------
# Policies with enumerable outcomes
# ----------------------------------------------------------------------------------------------


def bandit_log_probs(theta: torch.Tensor) -> torch.Tensor:
    """log pi(a) for a = 0..K-1, with logits (theta_1, ..., theta_{K-1}, 0)."""
    return torch.log_softmax(torch.cat([theta, theta.new_zeros(1)]), -1)


@dataclass
class SequencePolicy:
    """pi(x_1..x_T) = prod_t softmax(theta[t, x_{t-1}])[x_t], x_0 = a start symbol (index V).

    ``theta`` is flat ([T * (V + 1) * V]) so that Jacobians and Fisher matrices are plain
    matrices. ``sequences`` lists all V**T outcomes."""
    T: int
    V: int

    @property
    def n_params(self) -> int:
        return self.T * (self.V + 1) * self.V

    @property
    def sequences(self) -> torch.Tensor:
        return torch.tensor(list(itertools.product(range(self.V), repeat=self.T)))

    def token_log_probs(self, theta: torch.Tensor, sequences: torch.Tensor | None = None) -> torch.Tensor:
        """[M, T] log pi(x_t | x_{t-1}) of each listed (or given) sequence."""
        x = self.sequences if sequences is None else sequences
        table = theta.view(self.T, self.V + 1, self.V).log_softmax(-1)
        previous = torch.cat([torch.full((x.shape[0], 1), self.V), x[:, :-1]], 1)
        return table[torch.arange(self.T), previous, x]

    def log_probs(self, theta: torch.Tensor) -> torch.Tensor:
        """[V**T] log pi of every sequence."""
        return self.token_log_probs(theta).sum(-1)

    def sample(self, theta: torch.Tensor, n: int, generator: torch.Generator) -> torch.Tensor:
        """[n, T] sequences drawn from pi_theta."""
        table = theta.view(self.T, self.V + 1, self.V).softmax(-1)
        x = torch.full((n,), self.V)
        out = []
        for t in range(self.T):
            x = torch.multinomial(table[t, x], 1, generator=generator).squeeze(-1)
            out.append(x)
        return torch.stack(out, 1)


# ----------------------------------------------------------------------------------------------
# Exact objective, Fisher matrix, natural gradient
# ----------------------------------------------------------------------------------------------


def objective(log_prob_fn: Callable, theta: torch.Tensor, reward: torch.Tensor) -> torch.Tensor:
    """J(theta) = sum_x pi_theta(x) R(x), exactly."""
    return (log_prob_fn(theta).exp() * reward).sum()


def exact_gradient(log_prob_fn: Callable, theta: torch.Tensor, reward: torch.Tensor) -> torch.Tensor:
    theta = theta.detach().requires_grad_(True)
    (grad,) = torch.autograd.grad(objective(log_prob_fn, theta, reward), theta)
    return grad


def fisher_matrix(log_prob_fn: Callable, theta: torch.Tensor) -> torch.Tensor:
    """F = sum_x pi(x) s(x) s(x)^T with s(x) = grad_theta log pi(x): the Jacobian of the log-probs
    of all outcomes, weighted by their probabilities."""
    scores = torch.autograd.functional.jacobian(log_prob_fn, theta.detach())   # [M, d]
    probs = log_prob_fn(theta.detach()).exp()
    return scores.T @ (probs[:, None] * scores)


def kl(log_p: torch.Tensor, log_q: torch.Tensor) -> torch.Tensor:
    """KL(p || q) between two distributions given by the log-probabilities of every outcome."""
    return (log_p.exp() * (log_p - log_q)).sum()


def natural_gradient(F: torch.Tensor, g: torch.Tensor, damping: float) -> torch.Tensor:
    """(F + damping I)^-1 g, by a linear solve (never an explicit inverse)."""
    return torch.linalg.solve(F + damping * torch.eye(len(g), dtype=F.dtype), g)


def kl_step(F: torch.Tensor, g: torch.Tensor, max_kl: float, damping: float = 0.0) -> torch.Tensor:
    """The step delta maximizing g . delta subject to 1/2 delta^T F delta <= max_kl: the natural
    gradient, scaled to the edge of the KL ball (TRPO's step, without its line search)."""
    direction = natural_gradient(F, g, damping)
    return direction * torch.sqrt(2 * max_kl / (g @ direction))


# ----------------------------------------------------------------------------------------------
# TRPO's step without forming F: Fisher-vector products, conjugate gradients, a line search
# ----------------------------------------------------------------------------------------------


def fisher_vector_product(log_prob_fn: Callable, theta: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """F v without forming F. F is the Hessian of theta' -> KL(pi_theta || pi_theta') at
    theta' = theta (section 1), so F v is the derivative along v of that KL's gradient: two
    backward passes, the first kept differentiable (create_graph). The fixed distribution pi_theta
    is detached; otherwise the KL is KL(pi || pi) = 0 for every theta'."""
    log_p = log_prob_fn(theta.detach()).detach()
    theta_new = theta.detach().clone().requires_grad_(True)
    (kl_grad,) = torch.autograd.grad(kl(log_p, log_prob_fn(theta_new)), theta_new, create_graph=True)
    (Fv,) = torch.autograd.grad(kl_grad @ v, theta_new)
    return Fv


def conjugate_gradient(matrix_vector_product: Callable, b: torch.Tensor, iters: int) -> torch.Tensor:
    """x with A x = b for a symmetric positive-definite A given only as x -> A x: ``iters``
    conjugate-gradient iterations from x = 0, one product each, stopping early when the residual
    vanishes. Exact after d iterations in exact arithmetic; far fewer suffice when A's
    eigenvalues cluster, as a damped Fisher matrix's do (it has rank at most the number of
    outcomes minus one)."""
    x = torch.zeros_like(b)
    r = b.clone()          # the residual b - A x
    p = r.clone()          # the search direction, conjugate (A-orthogonal) to the earlier ones
    rr = r @ r
    for _ in range(iters):
        if rr <= 1e-30 * (b @ b):
            break
        Ap = matrix_vector_product(p)
        alpha = rr / (p @ Ap)
        x = x + alpha * p
        r = r - alpha * Ap
        rr_new = r @ r
        p = r + (rr_new / rr) * p
        rr = rr_new
    return x


def trpo_step(log_prob_fn: Callable, theta: torch.Tensor, surrogate: Callable, max_kl: float,
              cg_iters: int = 10, damping: float = 1e-3, backtrack: float = 0.5,
              max_backtracks: int = 10) -> torch.Tensor:
    """One TRPO update of theta: the new parameters.

    g is the gradient of ``surrogate`` (a differentiable estimate of the objective) at theta;
    conjugate gradients solve (F + damping I) x = g with Fisher-vector products; the step
    delta = sqrt(2 max_kl / g.x) x sits on the edge of the quadratic KL ball; the line search
    tries theta + backtrack**k delta for k = 0, 1, ..., max_backtracks - 1 and keeps the first whose
    true KL(pi_theta || pi_new) is at most max_kl *and* whose surrogate improved. If none passes,
    theta is returned unchanged."""
    theta = theta.detach()
    start = theta.clone().requires_grad_(True)
    value = surrogate(start)
    (g,) = torch.autograd.grad(value, start)
    x = conjugate_gradient(lambda v: fisher_vector_product(log_prob_fn, theta, v) + damping * v, g, cg_iters)
    delta = torch.sqrt(2 * max_kl / (g @ x)) * x
    log_p = log_prob_fn(theta)
    with torch.no_grad():
        for k in range(max_backtracks):
            candidate = theta + backtrack ** k * delta
            if kl(log_p, log_prob_fn(candidate)) <= max_kl and surrogate(candidate) > value:
                return candidate
    return theta.clone()


# ----------------------------------------------------------------------------------------------
# Importance sampling
# ----------------------------------------------------------------------------------------------


def sequence_weights(logp_new: torch.Tensor, logp_old: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """w_i = pi_new(tau_i) / pi_old(tau_i) = prod_t rho_it over the real tokens: [n]."""
    return torch.exp(((logp_new - logp_old) * mask).sum(-1))


def importance_weighted_surrogate(logp_new: torch.Tensor, logp_old: torch.Tensor,
                                  rewards: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """[n] per-sequence surrogate w_i R_i, whose gradient is w_i R_i grad log pi_new(tau_i): averaged
    over sequences drawn from pi_old, an unbiased estimate of grad J at pi_new."""
    return sequence_weights(logp_new, logp_old.detach(), mask) * rewards


def clip_fraction(logp_new: torch.Tensor, logp_old: torch.Tensor, advantages: torch.Tensor,
                  mask: torch.Tensor, eps_low: float, eps_high: float) -> float:
    """The fraction of real tokens whose gradient the clip removes: rho > 1 + eps_high where
    A > 0, rho < 1 - eps_low where A < 0."""
    ratio = torch.exp(logp_new - logp_old)
    A = advantages if advantages.dim() == ratio.dim() else advantages.unsqueeze(-1)
    clipped = ((A > 0) & (ratio > 1 + eps_high)) | ((A < 0) & (ratio < 1 - eps_low))
    m = mask.to(ratio.dtype)
    return float((clipped.to(ratio.dtype) * m).sum() / m.sum().clamp(min=1))
