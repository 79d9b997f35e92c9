# %% [markdown]
# # Lesson 5 — Group Relative Policy Optimization (GRPO)
#
# {{COLAB_BADGE}}
#
# {{SOLUTIONS_NOTE}}
#
# GRPO (Shao et al., *DeepSeekMath*, 2024, arXiv 2402.03300) is the algorithm behind much of
# today's reinforcement learning of language models. It is PPO without the critic: for each
# prompt it samples a **group** of $G$ completions and judges each one *relative to its group*.
# Everything in it is something you built in lessons 1-4, plus a leash.
#
# **What you will learn**
# - group-relative advantages, and why groups whose rewards are all equal teach nothing (and
#   what DAPO's dynamic sampling does about it);
# - the probability ratio and its clipping, the k3 estimate of the KL to a reference model and
#   why it sits in the loss;
# - the ways of averaging the per-token loss ("grpo", "dapo", "dr_grpo") and the length bias
#   Dr. GRPO points out;
# - that with one update per batch GRPO *is* REINFORCE with a group baseline, and how it compares
#   with REINFORCE and REINFORCE + baseline on the same budget.
#
# **Exercises**: 5.1 group advantages, 5.2 the clipped surrogate, 5.3 the k3 KL, 5.4 loss
# aggregation.

# %%
{{SETUP}}

# %%
import matplotlib.pyplot as plt
import torch

from course_utils import exercises, losses, toy
from course_utils.config import smoke_mode

SMOKE = smoke_mode()
device = "cuda" if torch.cuda.is_available() else "cpu"
print(f"device: {device} (the toy policy runs on the CPU), smoke: {SMOKE}")
torch.manual_seed(0)

# %% [markdown]
# ## 1. The objective
#
# For a prompt $q$, sample $G$ completions $o_1, \dots, o_G$ from the current policy (call it
# $\pi_{\text{old}}$: the parameters that generated the samples), score them $r_1, \dots, r_G$, and
# maximize
#
# $$J(\theta) = \mathbb{E}\left[\frac{1}{G}\sum_{i=1}^{G}\frac{1}{|o_i|}\sum_{t=1}^{|o_i|}
#   \Big(\min\big(\rho_{it} A_i,\ \mathrm{clip}(\rho_{it}, 1-\varepsilon, 1+\varepsilon)\, A_i\big)
#   - \beta\, \mathbb{D}_{\text{KL}}^{(it)}\Big)\right],
#   \qquad \rho_{it} = \frac{\pi_\theta(o_{it}\mid q, o_{i,<t})}{\pi_{\text{old}}(o_{it}\mid q, o_{i,<t})},$$
#
# with, for outcome rewards, the same advantage for every token of completion $i$:
#
# $$A_i = \frac{r_i - \mathrm{mean}(r_1..r_G)}{\mathrm{std}(r_1..r_G)}.$$
#
# There is no entropy term in GRPO. (The text this course grew from adds one, scaled by the
# inverse reward variance; `course_utils` offers it as a labelled *extension*,
# `entropy_bonus="inverse_variance"`, and the learner tracks ablate it.)
#
# ## 2. Group-relative advantages
#
# The group mean is a baseline (lesson 3) computed from the group; dividing by the group's
# standard deviation puts every prompt's advantages on the same scale, whether its rewards
# differ by 0.01 or by 1. Statistics are taken **per prompt**: an easy prompt's completions are
# compared with each other, not with a hard prompt's. Centring per prompt gives each prompt its
# own baseline, which lowers the noise and, like any baseline, leaves the direction alone. The
# division by the group's std is a different matter: it is what makes a prompt's weight depend on
# how hard the prompt is, and the cell after exercise 5.1 computes that weight exactly.
#
# ### Exercise 5.1 — group advantages
#
# Rows $gG \dots gG+G-1$ belong to prompt $g$. Use the sample standard deviation (Bessel's
# correction, `torch.std`'s default) plus $\epsilon = 10^{-4}$ in the denominator, as TRL does.

# %%
def group_advantages(rewards, group_size):
    """rewards [N] -> advantages [N], standardized within each group of group_size."""
    # BEGIN SOLUTION
    r = rewards.view(-1, group_size)
    return ((r - r.mean(-1, keepdim=True)) / (r.std(-1, keepdim=True) + 1e-4)).reshape(-1)
    # END SOLUTION


exercises.check_group_advantages(group_advantages)

# %% [markdown]
# A worked example with the recipe's binary reward, $G = 4$: one group with mixed results, one
# where every completion passed, one where every completion failed.

# %%
rewards = torch.tensor([1.0, 0.0, 0.0, 1.0,   1.0, 1.0, 1.0, 1.0,   0.0, 0.0, 0.0, 0.0])
A = group_advantages(rewards, 4)
for g in range(3):
    print(f"group {g}: rewards {rewards[4 * g:4 * g + 4].tolist()} -> advantages "
          f"{[round(a, 3) for a in A[4 * g:4 * g + 4].tolist()]}")
print("zero-std groups:", losses.group_advantages(rewards, 4)[1])

# %% [markdown]
# Groups 1 and 2 have advantage 0 for every completion: **no gradient at all**. With a sparse
# binary reward this is the common case early in training. On our toy task, at initialization:

# %%
policy0 = toy.CharPolicy()
gen = torch.Generator().manual_seed(0)
prompts = toy.random_prompts(64, gen).repeat_interleave(8, 0)
tokens, mask = policy0.sample(prompts, gen)
texts = toy.decode(tokens, mask)
for kind in ("binary", "shaped"):
    r = toy.score_texts(texts, prompts, kind)
    _, zero = losses.group_advantages(r, 8)
    print(f"{kind:6s} reward: mean {r.mean():.3f}, groups with no signal: {zero}/64")

# %% [markdown]
# With the binary reward almost every group is all-fail, so almost every sample is wasted.
# Remedies: a **shaped** reward with partial credit (what the course's CPU runs use); larger
# groups; or DAPO's **dynamic sampling** (Yu et al., 2025, arXiv 2503.14476): keep sampling
# and drop the zero-std groups until the batch is full of groups that carry signal. The
# training metrics of `course_utils` log the fraction of zero-std groups at every step
# (`zero_std_frac`) for this reason.

# %% [markdown]
# **What the std division does to a prompt's weight.** Take one prompt that the policy passes
# with probability $p$, a binary reward, and a policy with one logit $z$ for passing, so the
# exact gradient of the pass rate is $\partial p / \partial z = p(1-p)$. In a group of $G$ with
# $k$ passes, a pass has advantage $(1 - k/G)/\sigma_k$ and score $\partial \log\pi/\partial z
# = 1-p$, a failure $(-k/G)/\sigma_k$ and score $-p$, where $\sigma_k$ is the group's std; the
# group's average of advantage times score simplifies to $k(G-k)/(G^2 \sigma_k)$. The cell
# averages it over the binomial distribution of $k$ (groups with $k = 0$ or $G$ give 0) and divides
# by the exact gradient: that ratio is the weight GRPO gives the prompt. Without the std
# division (Dr. GRPO, `advantage_scale="none"`) the same sum is $(G-1)/G \cdot p(1-p)$ for
# every $p$: the same weight for every prompt. A Monte Carlo run of `losses.group_advantages`
# checks the enumeration.

# %%
from math import comb


def expected_update(p, G, divide_by_std, eps=1e-4):
    """E[ (1/G) sum_i A_i * dlog pi(o_i)/dz ] for one prompt, by enumerating the passes k."""
    total = 0.0
    for k in range(1, G):                       # k = 0 or G: all equal, advantage 0
        sigma = (k * (G - k) / (G * (G - 1))) ** 0.5 + eps if divide_by_std else 1.0
        total += comb(G, k) * p**k * (1 - p) ** (G - k) * k * (G - k) / (G**2 * sigma)
    return total


G = 8
prompt_weight = {}
print("pass probability p | GRPO weight | Dr. GRPO weight (no std) | GRPO, Monte Carlo")
for p_pass in (0.05, 0.2, 0.5, 0.8, 0.95):
    exact = p_pass * (1 - p_pass)
    passes = (torch.rand(20_000 if SMOKE else 200_000, G, generator=torch.Generator().manual_seed(0))
              < p_pass).double()
    A_mc, _ = losses.group_advantages(passes.reshape(-1), G)
    score = torch.where(passes.reshape(-1) == 1, 1 - p_pass, -p_pass)
    mc = float((A_mc * score).view(-1, G).mean(-1).mean())
    w_grpo, w_dr = (expected_update(p_pass, G, d) / exact for d in (True, False))
    print(f"{p_pass:18.2f} | {w_grpo:11.3f} | {w_dr:24.3f} | {mc / exact:.3f}")
    assert abs(w_dr - (G - 1) / G) < 1e-12
    assert abs(mc / exact - w_grpo) < 0.05 * w_grpo
    prompt_weight[p_pass] = w_grpo
w = prompt_weight  # larger towards both ends, smallest at p = 0.5
assert w[0.05] > w[0.2] > w[0.5] < w[0.8] < w[0.95]

# %% [markdown]
# The weights grow towards both ends: a prompt the policy almost always fails, or almost always
# passes, has a small group std, and dividing by it scales its rare differences up. Dr. GRPO
# (arXiv 2503.20783) calls this a question-level difficulty bias. Standardizing over the whole
# batch instead divides every prompt by the *same* number, so it changes the size of the update,
# not the balance between prompts; lesson 8 measures all four choices against the exact
# gradient of a small multi-prompt problem, and finds the same thing there.

# %% [markdown]
# ## 3. The ratio and its clip
#
# After the first gradient step on a batch, $\pi_\theta$ is no longer the policy that sampled it.
# Lesson 4 took this apart: the per-token ratio $\rho$ is importance sampling's first-order
# stand-in for the weight of the whole sequence, trustworthy only near $\pi_{\text{old}}$, and
# the clip is the trust region that keeps a single batch from moving the policy far: once $\rho A$ has gained more than $\varepsilon |A|$, the gradient
# of that token is zero. Taking the min of the clipped and unclipped objectives makes the bound
# pessimistic: the clip can only *remove* improvement, never add it. DAPO uses a larger upper
# bound ("clip-higher": $\varepsilon_{\text{low}} = 0.2$, $\varepsilon_{\text{high}} = 0.28$) so that
# unlikely tokens with positive advantage can grow faster.
#
# ### Exercise 5.2 — the clipped surrogate (as a per-token loss)
#
# Return the per-token **loss** $-\min(\rho A,\ \mathrm{clip}(\rho, 1-\varepsilon_{\text{low}}, 1+\varepsilon_{\text{high}})A)$,
# shape `[N, T]`, from log-probabilities under the current and the old policy and per-sequence
# advantages `[N]`.

# %%
def clipped_surrogate(logprobs, old_logprobs, advantages, eps_low, eps_high):
    """logprobs, old_logprobs [N, T]; advantages [N] -> per-token loss [N, T]."""
    # BEGIN SOLUTION
    ratio = torch.exp(logprobs - old_logprobs)
    A = advantages[:, None]
    return torch.maximum(-ratio * A, -torch.clamp(ratio, 1 - eps_low, 1 + eps_high) * A)
    # END SOLUTION


exercises.check_clipped_surrogate(clipped_surrogate)

# %%
ratios = torch.linspace(0.5, 1.6, 200)
fig, axes = plt.subplots(1, 2, figsize=(10, 3.3))
for ax, adv in zip(axes, (1.0, -1.0)):
    objective = -clipped_surrogate(ratios.log()[:, None], torch.zeros(200, 1), torch.tensor([adv] * 200),
                                   0.2, 0.28)[:, 0]
    ax.plot(ratios, ratios * adv, "--", color="gray", label=r"unclipped $\rho A$")
    ax.plot(ratios, objective, label="clipped objective")
    ax.axvline(0.8, color="k", lw=0.5); ax.axvline(1.28, color="k", lw=0.5)
    ax.set_title(f"A = {adv:+.0f}"); ax.set_xlabel(r"ratio $\rho$"); ax.legend()
plt.tight_layout(); plt.show()

# %% [markdown]
# Flat means zero gradient: for $A > 0$ the token stops being pushed up once $\rho > 1.28$; for
# $A < 0$ it stops being pushed down once $\rho < 0.8$.
#
# ## 4. The KL to a reference policy
#
# A reward checker can be gamed, and a policy that wanders far from its pretrained self loses
# what it knew. GRPO adds $\beta\,\mathbb{D}_{\text{KL}}(\pi_\theta \| \pi_{\text{ref}})$ to the
# **loss**, per token, with the reference $\pi_{\text{ref}}$ the frozen starting model. (PPO for
# RLHF usually folds the KL into the reward instead; putting it in the loss regularizes every
# token directly and keeps the advantage a pure function of the reward.) The exact KL needs a
# sum over the whole vocabulary at every position; GRPO uses a one-sample estimate at the
# sampled token, the "k3" estimator (Schulman, 2020):
#
# $$\mathbb{D}^{(t)}_{\text{KL}} = \frac{\pi_{\text{ref}}(o_t)}{\pi_\theta(o_t)} - \log\frac{\pi_{\text{ref}}(o_t)}{\pi_\theta(o_t)} - 1 .$$
#
# It is never negative ($x - \log x - 1 \ge 0$) and, for tokens sampled from $\pi_\theta$, its mean
# is the exact KL. That is a statement about its *value*. In the loss, what acts on the policy
# is its *gradient*, and section 4's last cell shows that the two are different questions.
#
# ### Exercise 5.3 — the k3 estimate

# %%
def k3_kl(logprobs, ref_logprobs):
    """Per-token k3 estimate of KL(pi_theta || pi_ref) from log-probabilities [N, T]."""
    # BEGIN SOLUTION
    log_ratio = ref_logprobs - logprobs
    return torch.exp(log_ratio) - log_ratio - 1
    # END SOLUTION


exercises.check_k3_kl(k3_kl)

# %%
p = torch.tensor([0.5, 0.3, 0.15, 0.05])   # the policy
q = torch.tensor([0.3, 0.3, 0.2, 0.2])     # the reference
exact_kl = float((p * (p / q).log()).sum())
samples = torch.multinomial(p, 20_000 if SMOKE else 200_000, replacement=True,
                            generator=torch.Generator().manual_seed(1))
k1 = (p.log() - q.log())[samples]
k3 = k3_kl(p.log()[samples], q.log()[samples])
print(f"exact KL {exact_kl:.4f} | k1 mean {k1.mean():.4f} (negative on {float((k1 < 0).float().mean()):.0%} of tokens) "
      f"| k3 mean {k3.mean():.4f} (min {k3.min():.4f})")
assert abs(k3.mean() - exact_kl) < 4 * k3.std() / len(samples) ** 0.5 and k3.min() >= 0

# %% [markdown]
# **Value versus gradient.** In a loss, the sampled token is data: autograd differentiates the
# log-probabilities at that token and nothing else. So what a penalty term does on average is
# $\mathbb{E}_{o \sim \pi_\theta}[\nabla_\theta k(o)]$ with $o$ held fixed. On the same $p$
# and $q$, with $p = \mathrm{softmax}(\theta)$, the cell enumerates the four tokens and compares
# that expectation with the gradients of both KL directions (autograd on the exact sums), for k1,
# for k3, and for k2 $= \tfrac12 (\log \pi_\theta - \log \pi_{\text{ref}})^2$:
#
# - $\nabla k1 = \nabla \log \pi_\theta(o)$, whose mean under $\pi_\theta$ is exactly 0: as a loss
#   term k1 does nothing on average, whatever the KL is.
# - $\nabla k3 = (1 - \pi_{\text{ref}}(o)/\pi_\theta(o))\,\nabla \log \pi_\theta(o)$, whose mean is
#   $-\sum_o \pi_{\text{ref}}(o) \nabla \log \pi_\theta(o) = \nabla \mathrm{KL}(\pi_{\text{ref}} \| \pi_\theta)$:
#   the gradient of the *other* direction of the KL.
# - $\nabla k2 = \log(\pi_\theta/\pi_{\text{ref}})\,\nabla \log \pi_\theta(o)$, whose mean is
#   $\nabla \mathrm{KL}(\pi_\theta \| \pi_{\text{ref}})$.
#
# Both KL directions are zero at $\pi_\theta = \pi_{\text{ref}}$ and grow away from it, so k3 in
# the loss still pulls the policy towards the reference; it just follows the gradient of
# $\mathrm{KL}(\pi_{\text{ref}} \| \pi_\theta)$, which punishes dropping tokens the reference
# likes more than adding tokens it does not. Schulman's note on KL approximators is about values;
# analyses of KL estimators in GRPO (2025) make this point about gradients.

# %%
theta = p.log().clone().requires_grad_(True)      # logits whose softmax is p
log_pi, log_ref = torch.log_softmax(theta, -1), q.log()


def expected_grad(k_of_token):
    """sum_o pi(o) * d k(o) / d theta, the token o held fixed (what a loss term does on average)."""
    pi = log_pi.exp().detach()
    return sum(pi[o] * torch.autograd.grad(k_of_token(o), theta, retain_graph=True)[0]
               for o in range(len(q)))


estimators = {
    "k1": lambda o: log_pi[o] - log_ref[o],
    "k2": lambda o: 0.5 * (log_pi[o] - log_ref[o]) ** 2,
    "k3": lambda o: k3_kl(log_pi[o], log_ref[o]),
}
kl_forward = (log_pi.exp() * (log_pi - log_ref)).sum()       # KL(pi_theta || pi_ref)
kl_reverse = (log_ref.exp() * (log_ref - log_pi)).sum()      # KL(pi_ref || pi_theta)
grad_forward = torch.autograd.grad(kl_forward, theta, retain_graph=True)[0]
grad_reverse = torch.autograd.grad(kl_reverse, theta, retain_graph=True)[0]
print("grad KL(pi_theta || pi_ref):", [round(v, 4) for v in grad_forward.tolist()])
print("grad KL(pi_ref || pi_theta):", [round(v, 4) for v in grad_reverse.tolist()])
mean_grads = {name: expected_grad(k) for name, k in estimators.items()}
for name, g in mean_grads.items():
    print(f"E[grad {name}]:                ", [round(v, 4) for v in g.tolist()])
assert torch.allclose(mean_grads["k1"], torch.zeros(4), atol=1e-7)
assert torch.allclose(mean_grads["k3"], grad_reverse, atol=1e-6)
assert torch.allclose(mean_grads["k2"], grad_forward, atol=1e-6)
assert not torch.allclose(grad_forward, grad_reverse, atol=1e-3)

# %% [markdown]
# ## 5. Averaging the per-token loss, and the length bias
#
# The objective above averages over each completion's tokens ($1/|o_i|$) and then over the
# group. That is one of several choices in use:
#
# | `loss_type` | normalizer | used by |
# |---|---|---|
# | `grpo` | mean over a completion's tokens, then over completions | DeepSeekMath |
# | `dapo` | sum over all tokens / number of real tokens in the batch | DAPO, TRL's default |
# | `bnpo` | each micro-batch's token mean, averaged over micro-batches (equal to `dapo` with one micro-batch on one process) | TRL's `bnpo` |
# | `dr_grpo` | sum over all tokens / (completions x max length): a constant | Dr. GRPO |
#
# ### Exercise 5.4 — aggregation
#
# Implement `"grpo"` and `"dapo"` for a per-token loss `[N, T]` and a mask `[N, T]`.

# %%
def aggregate(per_token, mask, loss_type):
    """per_token [N, T], mask [N, T] -> scalar: 'grpo' or 'dapo' averaging over real tokens."""
    # BEGIN SOLUTION
    mask = mask.to(per_token.dtype)
    if loss_type == "grpo":
        return ((per_token * mask).sum(-1) / mask.sum(-1)).mean()
    return (per_token * mask).sum() / mask.sum()
    # END SOLUTION


exercises.check_aggregate(aggregate)

# %% [markdown]
# **The length bias** (Liu et al., *Dr. GRPO*, 2025, arXiv 2503.20783). Under `grpo`, each token
# of completion $i$ carries weight $A_i / |o_i|$. Two wrong answers with the same negative
# advantage: the short one's tokens are pushed down hard, the long one's barely. So the policy
# learns that being wrong at length is cheap, and wrong answers grow longer. Under `dapo` and
# `dr_grpo` every token weighs the same. Measured on two completions:

# %%
logp = torch.zeros(2, 8, requires_grad=True)
mask = torch.tensor([[1, 1, 0, 0, 0, 0, 0, 0], [1, 1, 1, 1, 1, 1, 1, 1]])   # 2 tokens vs 8 tokens
advantages = torch.tensor([-1.0, -1.0])
for loss_type in ("grpo", "dapo", "dr_grpo"):
    loss = losses.aggregate(-logp * advantages[:, None], mask, loss_type, max_completion_length=8)
    (grad,) = torch.autograd.grad(loss, logp)
    print(f"{loss_type:8s} push on each token: short completion {-grad[0, 0].item():+.4f}, "
          f"long completion {-grad[1, 0].item():+.4f}")

# %% [markdown]
# ## 6. One update per batch: GRPO is REINFORCE with a group baseline
#
# With a single gradient step per batch, $\pi_{\text{old}} = \pi_\theta$ at the moment the gradient
# is taken, so $\rho = 1$, nothing is clipped, and $\nabla \rho = \nabla \log \pi_\theta$. The
# gradient is then exactly lesson 3's estimator with the group-normalized advantage as the
# weight. Checked on the toy policy:

# %%
policy = toy.CharPolicy()
gen = torch.Generator().manual_seed(3)
prompts = toy.random_prompts(8, gen).repeat_interleave(4, 0)
tokens, mask = policy.sample(prompts, gen)
A = group_advantages(toy.score_texts(toy.decode(tokens, mask), prompts), 4)
logp, _ = policy.log_probs(prompts, tokens)
grpo = aggregate(clipped_surrogate(logp, logp.detach(), A, 0.2, 0.2), mask, "dapo")
reinforce = -(logp * A[:, None] * mask).sum() / mask.sum()
g1 = torch.autograd.grad(grpo, list(policy.parameters()), retain_graph=True)
g2 = torch.autograd.grad(reinforce, list(policy.parameters()))
difference = max(float((a - b).abs().max()) for a, b in zip(g1, g2))
print(f"largest difference between the two gradients: {difference:.2e}")
assert difference < 1e-6

# %% [markdown]
# The ratio and clip matter only when a batch is reused for several steps
# (`updates_per_batch > 1` in `course_utils`), which is how PPO and GRPO save sampling cost.
#
# ## 7. REINFORCE vs REINFORCE + baseline vs GRPO, same task and budget
#
# Each method trains a fresh toy policy with the same number of samples per step (16 prompts x 8
# completions), the same optimizer and learning rate, over several seeds. "REINFORCE" uses the
# raw reward, "batch mean" subtracts the batch's mean reward, "RLOO" the leave-one-out mean of
# the prompt's group: these three use lesson 2's REINFORCE loss, summed over a completion's
# tokens. "GRPO" is section 1's objective, `losses.grpo_loss`: group-standardized advantages,
# the clipped ratio (exactly 1 here: one update per batch) and the mean over each completion's
# tokens. So the GRPO arm differs from RLOO in two ways at once, the std division and the
# per-completion average, and the comparison measures the package, not either part alone.

# %%
method_names = {"reinforce": "REINFORCE", "batch_mean": "REINFORCE + batch mean",
                "rloo": "RLOO (leave-one-out)", "grpo": "GRPO"}
seeds = [0] if SMOKE else list(range(20))   # a run takes seconds: enough seeds to see small differences
steps = 10 if SMOKE else 300
runs = {m: [toy.train_toy(m, steps=steps, seed=s, eval_every=20) for s in seeds] for m in method_names}

fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 3.8))
final = {}
for m, label in method_names.items():
    reward = torch.tensor([r["reward"] for r in runs[m]])
    passes = torch.tensor([r["eval_pass"] for r in runs[m]])
    x, xe = runs[m][0]["step"], runs[m][0]["eval_step"]
    ax1.plot(x, reward.mean(0), label=label)
    ax1.fill_between(x, reward.min(0).values, reward.max(0).values, alpha=0.15)
    ax2.plot(xe, passes.mean(0), "o-", ms=3, label=label)
    ax2.fill_between(xe, passes.min(0).values, passes.max(0).values, alpha=0.15)
    final[m] = (reward[:, -20:].mean(-1), passes[:, -1])   # per seed
ax1.set_title(f"mean shaped reward ({len(seeds)} seeds, band = min..max)"); ax1.set_xlabel("step")
ax2.set_title("held-out greedy pass rate (both constraints)"); ax2.set_xlabel("step")
ax1.legend(); plt.tight_layout(); plt.show()
for m, (r, p) in final.items():
    print(f"{method_names[m]:25s} reward over the last 20 steps {r.mean():.3f} +- {r.std() if len(r) > 1 else 0:.3f}   "
          f"final pass rate {p.mean():.1%} +- {p.std() if len(p) > 1 else 0:.1%}   (mean +- std over seeds)")
if not SMOKE:  # every baselined method beats plain REINFORCE on every seed
    for m in ("batch_mean", "rloo", "grpo"):
        assert final[m][0].min() > final["reinforce"][0].max(), m
# Between the baselined methods: paired by seed (course_utils.stats), a t-interval on n-1 df
from course_utils import stats  # noqa: E402
from course_utils.tracks import differs  # noqa: E402

for m in ("batch_mean", "rloo"):
    for i, what in enumerate(("reward", "pass rate")):
        print(f"GRPO vs {method_names[m]}, {what}: {differs(final['grpo'][i].tolist(), final[m][i].tolist())}")
    if not SMOKE:  # the text below: pass-rate differences spread wider across seeds than reward ones
        reward_sd, pass_sd = (stats.paired(final["grpo"][i].tolist(), final[m][i].tolist()).sd for i in (0, 1))
        assert pass_sd > reward_sd, (m, pass_sd, reward_sd)

# %% [markdown]
# What the runs show: every baselined method beats plain REINFORCE on every seed, by a wide
# margin, as lesson 3's variance measurements predicted (the cell asserts it). Between the
# baselined methods, read the lines the cell prints: each compares GRPO with one of the others
# seed by seed (the runs share seeds, so the comparison is paired: `course_utils.stats`), with
# a t-interval and a sign-flip test. A toy run takes seconds, so the cell affords many seeds
# (the plot's title says how many), and each "no difference detected" comes with the size of
# difference these seeds could have seen: it bounds the effect, it does not show the methods
# equal. The pass rate is one greedy, pass-or-fail evaluation on the held-out prompts at the
# last step, while the reward averages many sampled completions over the last steps; per seed
# the pass-rate differences spread more widely (the cell asserts it), so its intervals are wider. Where GRPO's extra step, the division by the group's std, can matter: it
# rescales every prompt's advantages to size about 1, so a prompt whose completions differ only
# slightly is pushed as hard as one with large differences. That is also the rescaling Dr. GRPO
# argues biases the objective (`advantage_scale="none"` in `course_utils` turns it off); lesson
# 8's grouping track measures that bias exactly, and on real runs.
#
# ## 8. From the toy to a language model
#
# `course_utils.train.grpo_step` is this lesson's loop for a real model: sample $G$ completions
# per prompt, score them with the rule checker, `group_advantages`, the clipped surrogate with
# optional k3 KL, aggregation, AdamW with gradient clipping. Lesson 6 has you write its
# language-model side yourself, on the pretrained SmolLM2: the log-probabilities of a completion,
# a sampling loop with a key/value cache, and the micro-batched backward. It then checks your
# step against this one and shows where the library's speed comes from. Lesson 7 runs the whole
# recipe on a Colab T4 and shows why a run can reach a high reward and still fail the rule; the
# main job, `python -m course_utils.train --preset cpu`, runs it on two CPU cores.
#
# ## Check yourself
#
# 1. What does centring on each prompt's own group mean buy over centring on the whole batch's
#    mean? Which part of GRPO's normalization makes a prompt's weight depend on its difficulty,
#    and which prompts does it favour (section 2's table)?
# 2. A group of 8 completions all fail. What is its contribution to the gradient, and what are
#    three ways to get signal from such prompts?
# 3. For $A < 0$, which ratios get zero gradient? Why is the min pessimistic?
# 4. k1 and k3 both estimate KL(π_θ‖π_ref) without bias. Put into the loss, what does each
#    one's gradient equal on average (section 4's enumeration)? Which estimator's gradient is
#    that of KL(π_θ‖π_ref), and why does GRPO's k3 still pull the policy towards the reference?
# 5. Under the `grpo` aggregation, why do wrong answers tend to get longer?
# 6. When is GRPO's gradient exactly REINFORCE with a group baseline, and what changes when a
#    batch is reused?
