# %% [markdown]
# # Lesson 6 — GRPO for a language model, by hand
#
# {{COLAB_BADGE}}
#
# {{SOLUTIONS_NOTE}}
#
# Lesson 5 wrote GRPO's estimator for a toy policy whose tokens came from a table. Here the
# policy is a real pretrained language model, the embedded SmolLM2-135M-Instruct, and you write
# the part every GRPO trainer (TRL, verl, OpenRLHF, and `course_utils.train`) hides from you: the
# code between "a model and some prompts" and "a gradient". It is short, and almost every bug in
# it is silent: the run trains, the reward may even rise, and the gradient is still wrong.
#
# **What you will learn**
# - how to read per-token log-probabilities out of a causal LM: the one-position shift, left
#   padding (the attention mask *and* the position ids), and the sampling temperature;
# - how to sample a group of completions with a key/value cache, why the loop runs under
#   `torch.no_grad()`, and how to mask when the padding token *is* the end-of-sequence token;
# - how to backpropagate a batch in micro-batches so that the gradient equals the full batch's,
#   and the normalization mistake that breaks this;
# - that your step trains SmolLM2, that it computes the library's gradient exactly, and where the
#   library's speed comes from: sharing the prompt across its group and dropping finished rows;
# - the token entropy, the clip and a KL to the reference on a batch used for several updates,
#   each checked against the library's gradient on SmolLM2.
#
# **Exercises**: 6.1 completion log-probabilities, 6.2 sampling a group, 6.3 the micro-batched
# GRPO backward, 6.4 token entropy, 6.5 the clipped loss of a reused batch, with its clip
# fraction and KL. The checkers of 6.1 to 6.3 run your function on small random Qwen2 models
# (Qwen2.5's architecture; SmolLM2 is a Llama, the same design without biases in the attention
# projections), those of 6.4 and 6.5 on seeded tensors, against the library, and each names the
# mistake it finds.
#
# Runtime: the full run trains SmolLM2 with real weights on the CPU, in minutes (the last cell
# prints how many); a GPU is used if there is one. In smoke mode (CI) a tiny random model stands
# in and every loop is shortened.

# %%
{{SETUP}}

# %%
import time

import matplotlib.pyplot as plt
import torch
import torch.nn.functional as F
from tqdm.auto import tqdm

from course_utils import data, losses, models, rewards, rollout, stats, train
from course_utils import lm_exercises as exercises
from course_utils import loss_exercises
from course_utils.config import load_config, smoke_mode

SMOKE = smoke_mode()
DEVICE = "cuda" if torch.cuda.is_available() else "cpu"
LESSON_START = time.perf_counter()
print(f"device: {DEVICE}, smoke: {SMOKE}")

# %% [markdown]
# ## 1. The setting
#
# The task is the course's: continue a snippet in exactly a target number of characters, with
# digits that add up to a target the prompt states, judged by `course_utils.rewards` (the
# shaped reward gives partial credit for near misses). The configuration is the main job's
# (`--preset cpu`) with two changes that make a handful of steps show something: fewer prompts per
# step than the preset's {{fig:cpu.prompts_per_step}} (the cell prints how many), and a larger learning rate.

# %%
if SMOKE:   # a random-weight Qwen2 with SmolLM2's tokenizer; seconds per step
    cfg = load_config("smoke", device="cpu", prompts_per_step=1, group_size=4, grad_accum=1,
                      max_new_tokens=8, lr=1e-3)
    STEPS, HELD_OUT = 2, 4
else:
    cfg = load_config("cpu", device=DEVICE, prompts_per_step=2, lr=2e-4)
    STEPS, HELD_OUT = 8, 16
G, TEMPERATURE = cfg.group_size, cfg.temperature

tokenizer = models.load_tokenizer(cfg.model)
torch.manual_seed(cfg.seed)
model = models.load_policy(cfg.model, seed=cfg.seed).to(DEVICE)
EOS_ID = tokenizer.eos_token_id
PAD_ID = tokenizer.pad_token_id
train_prompts = data.make_prompts(cfg, tokenizer, held_out=False)
held_out_prompts = data.make_prompts(cfg, tokenizer, held_out=True)[:HELD_OUT]
print(f"model: {cfg.model}, {sum(p.numel() for p in model.parameters()) / 1e6:.0f}M parameters")
print(f"EOS id {EOS_ID} ({tokenizer.eos_token!r}), pad id {PAD_ID}: "
      f"{'the same token' if EOS_ID == PAD_ID else 'different tokens'}")
print(f"G = {G} completions per prompt, {cfg.prompts_per_step} prompts per step, up to "
      f"{cfg.max_new_tokens} new tokens, temperature {TEMPERATURE}, lr {cfg.lr}")
print("\nOne prompt, as the model sees it:\n" + train_prompts[0].text)

# %% [markdown]
# ## 2. Log-probabilities of a completion
#
# A causal LM maps tokens $x_0 \dots x_{L-1}$ to logits $z_0 \dots z_{L-1}$, where $z_j$ is the
# model's prediction of token $x_{j+1}$. Put a prompt of $P$ tokens and a completion of $T$
# tokens side by side, $x = (q_0 \dots q_{P-1}, o_0 \dots o_{T-1})$. Completion token $o_t$
# sits at position $P + t$, so it is predicted by the logits at position $P + t - 1$:
#
# $$\log \pi_\theta(o_t \mid q, o_{<t}) = \log \mathrm{softmax}\big(z_{P+t-1} / \tau\big)[o_t],
# \qquad t = 0, \dots, T-1,$$
#
# that is, the logits sliced at positions $P-1$ through $P+T-2$. Three more details decide
# whether the numbers are right:
#
# - **The temperature $\tau$.** Completions are sampled from $\mathrm{softmax}(z/\tau)$, so they
#   must be scored under the same distribution. With one update per batch the ratio is
#   $\exp(\log\pi_\theta - \mathrm{sg}[\log\pi_\theta])$, exactly 1 whatever $\tau$ the scoring
#   uses, so nothing *looks* wrong; what is wrong is the gradient, which is then the gradient of
#   another policy than the one that sampled. With several updates, $\pi_{\text{old}}$ comes from
#   the sampler at $\tau$, and scoring at $\tau = 1$ also puts the ratio off 1 from the start.
# - **Left padding.** A batch of prompts of different lengths is left-padded, so that every row
#   ends where its completion starts. The attention mask keeps real tokens from attending to the
#   padding, and the **position ids** must start at 0 on each row's first real token:
#   `attention_mask.cumsum(-1) - 1`, clamped at 0. Whether omitting them does harm depends on
#   the model. transformers numbers positions `0, 1, 2, ...` from the left edge when you omit
#   them, padding included, whatever the mask says. A rotary-embedding model (Qwen2, Llama,
#   SmolLM2) only ever sees the *difference* of two positions in attention, so a row shifted by
#   its padding gets the same logits up to rounding; a model with absolute position embeddings
#   (GPT-2, the `gpt2-rtx4070` preset's model) gives the shifted row different logits. Pass them
#   always: the exercise's checker scores a GPT-2-style model too.
# - **The completion mask.** Completions are right-padded after their end-of-sequence token.
#   Those positions are not part of the completion and must get log-probability 0. A model can
#   have more than one end token: Qwen2.5-Instruct, lesson 7's model, ends a turn with
#   `<|im_end|>` and also stops at `<|endoftext|>` (its generation config lists both), so a
#   sampler that watches only one lets a completion run past its end. SmolLM2 here has one,
#   which is why this lesson's exercises take a single id; the library's sampler takes the list
#   (`models.eos_token_ids` reads it from the tokenizer and the generation config).
#
# ### Exercise 6.1 — completion log-probabilities
#
# Return an `[N, T]` tensor, differentiable with respect to the model's weights.

# %%
def completion_logprobs(model, prompt_ids, prompt_mask, completion_ids, completion_mask, temperature):
    """log pi(o_t | q, o_<t) under softmax(logits / temperature) for every completion token.

    prompt_ids, prompt_mask: [N, P], left-padded. completion_ids, completion_mask: [N, T],
    right-padded; the mask is 1 up to and including each row's first EOS. Returns [N, T], 0
    where completion_mask is 0.
    """
    # BEGIN SOLUTION
    input_ids = torch.cat([prompt_ids, completion_ids], dim=1)
    attention_mask = torch.cat([prompt_mask, completion_mask], dim=1)
    position_ids = (attention_mask.cumsum(-1) - 1).clamp(min=0)
    logits = model(input_ids=input_ids, attention_mask=attention_mask,
                   position_ids=position_ids).logits
    P, T = prompt_ids.shape[1], completion_ids.shape[1]
    logits = logits[:, P - 1:P + T - 1].float() / temperature      # position P+t-1 predicts o_t
    logprobs = torch.log_softmax(logits, dim=-1).gather(-1, completion_ids.unsqueeze(-1)).squeeze(-1)
    return logprobs * completion_mask
    # END SOLUTION


exercises.check_completion_logprobs(completion_logprobs)

# %% [markdown]
# The checker compared your function with `course_utils.rollout.completion_logprobs` on seeded
# batches with left padding at several temperatures, on Qwen2 and GPT-2 models, and checked that the gradient reaches every
# weight. The library's version computes the same numbers with two savings: it asks the model
# for the logits of the completion positions only (`logits_to_keep`), since a prompt position's
# logits, one number per vocabulary entry, are most of the memory and are never used, and it
# forwards rows in chunks sorted by length (section 5).
#
# ## 3. Sampling a group, with a key/value cache
#
# GRPO needs $G$ completions of each prompt and, for each sampled token, its log-probability
# under the distribution it was drawn from. A transformer's keys and values for the tokens
# already seen do not change when a token is appended, so a sampling loop keeps them (the
# **KV cache**, `past_key_values`) and feeds the model only the newest token: each step costs one
# position instead of the whole sequence.
#
# Three things are easy to get wrong:
#
# - **No gradient.** Sampling is not differentiated. Without `torch.no_grad()` every decoding
#   step's graph is kept until the step ends: memory grows with the completion length for nothing.
# - **EOS when pad == EOS.** SmolLM2 pads with its end-of-sequence token (the cell in section 1
#   printed the ids), and Qwen2.5-Instruct with `<|endoftext|>`, one of its two end tokens. Once a row has produced EOS, the loop keeps feeding it EOS as
#   padding. The mask must keep the *first* EOS, because that token is the model's decision to
#   stop, and a policy that is never rewarded for stopping never learns to. `ids != pad_id`
#   drops it.
# - **The temperature, twice.** Sample from $\mathrm{softmax}(z/\tau)$ and record the
#   log-probability under that same distribution.
#
# ### Exercise 6.2 — sample G completions of one prompt
#
# Give each of the $G$ rows its own copy of the prompt (`prompt_ids.expand(G, -1)`): one forward
# over the prompt fills the cache, then one forward per new token with `past_key_values`. Stop
# early once every row has produced EOS. Draw with
# `torch.multinomial(probabilities, 1, generator=generator)` so the checker can seed you.

# %%
@torch.no_grad()
def sample_group(model, prompt_ids, G, max_new_tokens, eos_id, temperature, generator):
    """G completions of one prompt (prompt_ids: [1, P]). Returns (completion_ids,
    completion_mask, logprobs), each [G, T] with T <= max_new_tokens: padding (= eos_id) after
    each row's first EOS, the mask 1 up to and including that EOS, and the log-probability of
    each sampled token under softmax(logits / temperature), 0 on padding."""
    # BEGIN SOLUTION
    out = model(input_ids=prompt_ids.expand(G, -1), use_cache=True)
    finished = torch.zeros(G, dtype=torch.bool, device=prompt_ids.device)
    tokens, logprobs = [], []
    for _ in range(max_new_tokens):
        logp = torch.log_softmax(out.logits[:, -1].float() / temperature, dim=-1)
        token = torch.multinomial(logp.exp(), 1, generator=generator).squeeze(-1)
        token = torch.where(finished, eos_id, token)            # finished rows: padding
        tokens.append(token)
        logprobs.append(torch.where(finished, 0.0, logp.gather(-1, token[:, None]).squeeze(-1)))
        finished = finished | (token == eos_id)
        if finished.all():
            break
        out = model(input_ids=token[:, None], past_key_values=out.past_key_values, use_cache=True)
    completion_ids = torch.stack(tokens, dim=1)
    is_eos = (completion_ids == eos_id).long()
    completion_mask = (is_eos.cumsum(1) - is_eos == 0).long()   # no EOS strictly before t
    return completion_ids, completion_mask, torch.stack(logprobs, dim=1)
    # END SOLUTION


exercises.check_sample_group(sample_group)

# %% [markdown]
# Now on the real model: one group for the first prompt, decoded and scored. The last column
# re-scores the same tokens with your exercise 6.1; on-policy, the two log-probabilities of a
# completion must agree, which is the ratio $\pi_\theta/\pi_{\text{old}} = 1$ that GRPO's first
# update starts from.

# %%
generator = torch.Generator(device=DEVICE).manual_seed(cfg.seed)


def prompt_tensor(prompt):
    return tokenizer(prompt.text, return_tensors="pt", add_special_tokens=False).input_ids.to(DEVICE)


def decode(completion_ids, completion_mask):
    return tokenizer.batch_decode([row[m.bool()] for row, m in zip(completion_ids, completion_mask)],
                                  skip_special_tokens=True)


def score(prompts, texts):
    """The shaped reward of each completion (prompts repeated once per completion)."""
    return torch.tensor(rewards.shaped_reward(None, texts,
                                              target_chars=[p.target_chars for p in prompts],
                                              target_digit_sum=[p.target_digit_sum for p in prompts]))


prompt = train_prompts[0]
prompt_ids = prompt_tensor(prompt)
ids, mask, sampled_logprobs = sample_group(model, prompt_ids, G, cfg.max_new_tokens, EOS_ID,
                                           TEMPERATURE, generator)
with torch.no_grad():
    rescored = completion_logprobs(model, prompt_ids.expand(G, -1), torch.ones_like(prompt_ids).expand(G, -1),
                                   ids, mask, TEMPERATURE)
texts = decode(ids, mask)
group_rewards = score([prompt] * G, texts)
print(f"targets: {prompt.target_chars} characters, digit sum {prompt.target_digit_sum}")
print(f"{'reward':>6}  {'chars':>5}  {'tokens':>6}  {'log p sampled':>13}  {'log p rescored':>14}  completion")
for text, r, m, a, b in zip(texts, group_rewards, mask, sampled_logprobs, rescored):
    print(f"{r:6.3f}  {len(text.strip()):5d}  {int(m.sum()):6d}  {float(a.sum()):13.4f}  "
          f"{float(b.sum()):14.4f}  {text.strip()!r:.60}")
print(f"largest |sampled - rescored| over all tokens: {(sampled_logprobs - rescored).abs().max():.2e}")

# %% [markdown]
# ## 4. The GRPO step, micro-batch by micro-batch
#
# With one update per batch, $\pi_{\text{old}}$ is the current policy, the ratio is exactly 1,
# the clip never binds, and (without a KL term) GRPO's loss is
#
# $$\mathcal{L}(\theta) = -\frac{1}{N}\sum_{i=1}^{N} \frac{1}{|o_i|}\sum_{t} \rho_{it} A_i
# \quad\text{('grpo')}, \qquad
# \mathcal{L}(\theta) = -\frac{1}{\sum_i |o_i|}\sum_{i=1}^{N}\sum_{t} \rho_{it} A_i
# \quad\text{('dapo')},$$
#
# with $\rho_{it} = \exp(\log\pi_\theta - \mathrm{sg}[\log\pi_\theta])$: equal to 1, with gradient
# $\nabla\log\pi_\theta$ ("sg" is stop-gradient, `.detach()`). Lesson 5 wrote the advantages and
# these aggregations for a toy; here the batch may not fit through the model at once (it does
# not on lesson 7's T4), so the backward runs over
# micro-batches of whole groups, and the gradients accumulate in `.grad`.
#
# Accumulation gives the full batch's gradient when the micro-batch losses add up to the full
# batch's loss. Dividing each micro-batch's sum by the whole batch's counts ($N$ sequences, or
# all its completion tokens) and adding is exact for every aggregation. Averaging micro-batch
# *means* is exact only where each micro-batch's mean has the same denominator: for 'grpo' with
# micro-batches of equal numbers of sequences (the per-sequence means are averaged either way;
# TRL and CS336 accumulate like this), but not for 'dapo', where a micro-batch's own token
# count varies with its completions' lengths. Normalizing each micro-batch by its own token
# count and averaging (TRL's 'bnpo') weights a token by how few tokens its micro-batch holds.
#
# ### Exercise 6.3 — the micro-batched backward
#
# Backpropagate the loss in micro-batches of `micro_rows` rows, using your exercise 6.1. Do not
# zero the gradients (the caller does, once per step), and return the full batch's loss as a
# float. `advantages` has shape `[N, 1]`.

# %%
def grpo_backward(model, prompt_ids, prompt_mask, completion_ids, completion_mask, advantages,
                  temperature, micro_rows, loss_type):
    """Accumulate the gradient of the GRPO loss (loss_type 'grpo' or 'dapo') in the model's
    .grad, micro_rows rows at a time, equal to the full batch's. Returns the loss (a float)."""
    # BEGIN SOLUTION
    N = completion_ids.shape[0]
    total_tokens = completion_mask.sum()                 # the whole batch's counts, not a micro-batch's
    loss_sum = 0.0
    for start in range(0, N, micro_rows):
        rows = slice(start, start + micro_rows)
        logprobs = completion_logprobs(model, prompt_ids[rows], prompt_mask[rows],
                                       completion_ids[rows], completion_mask[rows], temperature)
        ratio = torch.exp(logprobs - logprobs.detach())  # 1, with gradient d log pi
        per_token = -ratio * advantages[rows]
        m = completion_mask[rows].float()
        if loss_type == "dapo":
            loss = (per_token * m).sum() / total_tokens
        else:
            loss = ((per_token * m).sum(-1) / m.sum(-1).clamp(min=1)).sum() / N
        loss.backward()
        loss_sum += loss.item()
    return loss_sum
    # END SOLUTION


exercises.check_grpo_backward(grpo_backward)

# %% [markdown]
# ### The rest of the step: entropy, the clip, a KL to the reference
#
# Exercise 6.3 is the whole step when each batch is used once and there is no KL term. Two more
# things complete what a GRPO trainer computes each step: the token entropy it logs, and, for a
# batch used more than once, the clip and a KL to the reference. Section 6 runs them on SmolLM2.
#
# **The entropy of each token's distribution**, $H_t = -\sum_a \pi(a\mid s_t)\log\pi(a\mid s_t)$,
# is the number to watch for collapse (lesson 7 diagnoses a run by it), and the one an entropy
# bonus pushes up (GRPO itself has none). TRL logs it every step, and its
# `top_entropy_quantile` $= \rho$ keeps only the top-$\rho$ share of tokens by entropy in the
# policy term (the KL term still covers every token). The course's trainer has the same option
# (`--top_entropy_quantile`, `losses.high_entropy_mask`), and lesson 7, section 6.9 tries it.
#
# ### Exercise 6.4 — token entropy
#
# From logits `[N, T, V]` (already divided by the temperature), return `[N, T]`: the entropy at
# each position in nats, 0 where `mask` is 0, with a gradient. A policy near collapse has one
# logit far above the rest; the checker includes logits of size $10^4$, so make the computation
# survive them.

# %%
def token_entropy(logits, mask):
    """-sum_a pi(a) log pi(a) per position for pi = softmax(logits); 0 where mask is 0."""
    # BEGIN SOLUTION
    logp = torch.log_softmax(logits, dim=-1)        # subtracts the largest logit: no underflow to log 0
    entropy = -(logp.exp() * logp).sum(-1)
    return torch.where(mask.bool(), entropy, 0.0)   # where, not *: padding logits may hold anything
    # END SOLUTION


loss_exercises.check_token_entropy(token_entropy)

# %% [markdown]
# **A batch used more than once.** With one update per batch the ratio is exactly 1 and the clip
# never acts (section 4). Reuse the batch for another update and the policy that sampled it is
# no longer the current one: the ratio is $\rho_t = \pi_\theta / \pi_{\text{old}}$ with
# $\pi_{\text{old}}$'s log-probabilities *fixed before the first update* (exercise 6.2 returns the
# sampler's; recomputing them after an update would make the ratio 1 again), and the clip starts
# to remove the incentive of tokens that moved too far. Recomputing them *once*, with the
# training model before the first update, is also right, and is what TRL and `train.grpo_step`
# with a bf16 sampler do: it keeps the sampler–trainer rounding gap out of the ratio (lesson 4,
# section 6, measures that gap's effect). A KL penalty toward a reference model (here the
# pretrained weights) uses lesson 5's k3 estimate on the same tokens. Once the batch is reused
# the tokens come from $\pi_{\text{old}}$, not $\pi_\theta$, so its mean is no longer an unbiased
# estimate of $\mathrm{KL}(\pi_\theta \,\|\, \pi_{\text{ref}})$; weighting each token's k3 by $\rho$
# restores that (TRL's `use_bias_correction_kl`). The exercise keeps the plain k3, as the
# library does.
#
# ### Exercise 6.5 — the clipped loss, with its clip fraction and KL
#
# Assemble lesson 5's pieces (exercises 5.2, 5.3 and 5.4) for this setting. Return
# `(loss, clip_fraction, kl)`: the loss is a differentiable scalar, the per-token clipped
# surrogate plus `beta` times the k3 KL to the reference, averaged over each completion's real
# tokens and then over completions ('grpo'); `clip_fraction` is the share of real tokens whose
# *surrogate* gradient the clip removes (lesson 4, exercise 4.4; the KL term's gradient still
# flows there); `kl` is the mean k3 KL over real tokens, whatever `beta` is (with `beta = 0` the
# penalty is off but the distance can still be measured; TRL and `train.grpo_step` log it only
# when `beta > 0`, since otherwise they load no reference model). Both as floats; `advantages`
# is `[N, 1]`.

# %%
def clipped_loss(logprobs, old_logprobs, ref_logprobs, advantages, mask, eps_low, eps_high, beta):
    """GRPO's loss for a batch sampled by old_logprobs' policy, and what a run logs about it."""
    # BEGIN SOLUTION
    real = mask.bool()
    ratio = torch.exp(logprobs - old_logprobs)
    unclipped, clipped = ratio * advantages, ratio.clamp(1 - eps_low, 1 + eps_high) * advantages
    log_r = ref_logprobs - logprobs
    kl = torch.expm1(log_r) - log_r                          # k3: r - log r - 1, r = pi_ref / pi
    per_token = -torch.minimum(unclipped, clipped) + beta * kl
    per_token = torch.where(real, per_token, 0.0)
    m = mask.to(per_token.dtype)
    loss = (per_token.sum(-1) / m.sum(-1).clamp(min=1)).mean()
    removed = (clipped < unclipped) & real                   # the clipped branch is the active one
    clip_fraction = float(removed.sum() / m.sum())
    mean_kl = float((torch.where(real, kl, 0.0).sum() / m.sum()).detach())
    return loss, clip_fraction, mean_kl
    # END SOLUTION


loss_exercises.check_clipped_loss(clipped_loss)

# %% [markdown]
# ## 5. Your GRPO step on SmolLM2
#
# Everything is in place. One step: sample a group for each prompt with your sampler, put the
# groups in one batch (prompts left-padded, completions right-padded), score them, compute the
# group advantages (lesson 5's exercise 5.1, which the library has as `losses.group_advantages`),
# backpropagate with your exercise 6.3 one group per micro-batch, clip the gradient norm and take
# an AdamW step: the main job's optimizer settings.

# %%
def stack_groups(groups):
    """[(prompt_ids [1, P_g], completion_ids [G, T_g], completion_mask [G, T_g]), ...] -> one
    batch: prompts left-padded to the longest, completions right-padded to the longest."""
    P = max(p.shape[1] for p, _, _ in groups)
    T = max(c.shape[1] for _, c, _ in groups)
    rows = [(F.pad(p.expand(len(c), -1), (P - p.shape[1], 0), value=PAD_ID),
             F.pad(torch.ones_like(p).expand(len(c), -1), (P - p.shape[1], 0), value=0),
             F.pad(c, (0, T - c.shape[1]), value=PAD_ID),
             F.pad(m, (0, T - m.shape[1]), value=0)) for p, c, m in groups]
    return [torch.cat(parts) for parts in zip(*rows)]


def my_grpo_step(model, optimizer, prompts, generator):
    """Sample, score, and update once. Returns the batch's rewards and the step's seconds."""
    start = time.perf_counter()
    groups = []
    for prompt in prompts:
        prompt_ids = prompt_tensor(prompt)
        ids, mask, _ = sample_group(model, prompt_ids, G, cfg.max_new_tokens, EOS_ID,
                                    TEMPERATURE, generator)
        groups.append((prompt_ids, ids, mask))
    prompt_ids, prompt_mask, completion_ids, completion_mask = stack_groups(groups)
    batch_rewards = score([p for p in prompts for _ in range(G)], decode(completion_ids, completion_mask))
    advantages, _ = losses.group_advantages(batch_rewards, G)
    optimizer.zero_grad(set_to_none=True)
    grpo_backward(model, prompt_ids, prompt_mask, completion_ids, completion_mask,
                  advantages.to(DEVICE)[:, None], TEMPERATURE, micro_rows=G, loss_type=cfg.loss_type)
    torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.max_grad_norm)
    optimizer.step()
    return batch_rewards, time.perf_counter() - start


@torch.no_grad()
def held_out_reward(model, seed=1234):
    """Mean shaped reward per held-out prompt: 4 sampled completions each (the library's sampler,
    a fixed seed), so two policies can be compared prompt by prompt."""
    g = torch.Generator(device=DEVICE).manual_seed(seed)
    ro = rollout.rollout(model, tokenizer, [p.text for p in held_out_prompts], group_size=4,
                         max_new_tokens=cfg.max_new_tokens, eos_ids=[EOS_ID],
                         temperature=TEMPERATURE, generator=g)
    return score([p for p in held_out_prompts for _ in range(4)], ro.texts).view(-1, 4).mean(-1)


def compare(after, before):
    """after minus before, paired by held-out prompt (course_utils.stats: a t-interval on n - 1
    degrees of freedom and a sign-flip test)."""
    return stats.paired(after.tolist(), before.tolist(), unit="prompt")

# %% [markdown]
# The run: your step for a handful of steps from the pretrained weights, on the main job's
# prompt order. The reward is noisy step to step (a few prompts, {{fig:cpu.group_size}} completions each), so the
# cell also compares the policy before and after on held-out prompts it never trained on, prompt
# by prompt.

# %%
initial_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
reward_before = held_out_reward(model)
optimizer = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
generator = torch.Generator(device=DEVICE).manual_seed(cfg.seed)
mine = {"reward": [], "seconds": []}
for step in tqdm(range(STEPS), desc="your GRPO step"):
    batch_rewards, seconds = my_grpo_step(model, optimizer, train.batch_for_step(step, train_prompts, cfg),
                                          generator)
    mine["reward"].append(float(batch_rewards.mean()))
    mine["seconds"].append(seconds)
reward_after_mine = held_out_reward(model)
gain = compare(reward_after_mine, reward_before)
print(f"training reward, step 1 -> step {STEPS}: {mine['reward'][0]:.3f} -> {mine['reward'][-1]:.3f}")
print(f"held-out reward ({HELD_OUT} prompts x 4 samples): {float(reward_before.mean()):.3f} -> "
      f"{float(reward_after_mine.mean()):.3f}; after minus before, {gain.verdict()}")
if not SMOKE:   # the lesson's promise: your step improves the policy beyond noise
    assert gain.significant and gain.p_value <= 0.05 and gain.mean > 0, "the held-out reward did not rise beyond noise"

# %% [markdown]
# ## 6. The same algorithm as the library
#
# `course_utils.train.grpo_step` is the library's version of `my_grpo_step` (with the options
# lesson 5 and lesson 7 use: the clip, a KL term, dynamic sampling, several processes). First the
# exact check: one batch sampled from the pretrained model, and the gradient of your exercise 6.3
# against the library's loss on the same tokens, computed its own way (the prompt shared across
# its group, chunks sorted by length).

# %%
model.load_state_dict(initial_state)
check_prompts = train.batch_for_step(0, train_prompts, cfg)
ro = rollout.rollout(model, tokenizer, [p.text for p in check_prompts], group_size=G,
                     max_new_tokens=cfg.max_new_tokens, eos_ids=[EOS_ID], temperature=TEMPERATURE,
                     generator=torch.Generator(device=DEVICE).manual_seed(7))
advantages, _ = losses.group_advantages(score([p for p in check_prompts for _ in range(G)], ro.texts), G)
advantages = advantages.to(DEVICE)[:, None]
batch = (ro.prompt_ids, ro.prompt_mask, ro.completion_ids, ro.completion_mask)

model.zero_grad(set_to_none=True)
grpo_backward(model, *batch, advantages, TEMPERATURE, micro_rows=G, loss_type=cfg.loss_type)
yours = torch.cat([p.grad.flatten() for p in model.parameters()])
model.zero_grad(set_to_none=True)
logprobs, _ = rollout.completion_logprobs(model, *batch, temperature=TEMPERATURE, group_size=G)
loss, _ = losses.grpo_loss(logprobs, logprobs.detach(), advantages, ro.completion_mask,
                           loss_type=cfg.loss_type)
loss.backward()
library = torch.cat([p.grad.flatten() for p in model.parameters()])
model.zero_grad(set_to_none=True)
relative = float((yours - library).norm() / library.norm())
print(f"gradient norm {float(library.norm()):.4f}; |yours - library| / |library| = {relative:.1e}")
# float32 sums in another order differ by about 1e-5 relative; the mistakes exercise 6.3's
# checker names are off by tens of percent or more
assert relative < 1e-3, "your step's gradient differs from the library's on the real model"

# %% [markdown]
# ### Several updates per batch, with the clip and the KL
#
# Now the same batch for several updates, with your exercises 6.1, 6.4 and 6.5: the ratio
# against the log-probabilities the sampler saved, a KL penalty toward the pretrained model
# (which sampled this batch, so its log-probabilities are the reference's too), and at every
# update your gradient against the library's `losses.grpo_loss` on the same weights. The step is
# then taken with your gradient; each row is measured before its update's step. Watch the clip
# fraction: 0 at the first update (the sampler's and the trainer's log-probabilities differ by
# far less than the clip range here, section 3; a bf16 or vLLM sampler can differ by more), then
# rising once the first update has moved the policy. Because the reference *is* the sampler
# here, this cell cannot tell `old_logprobs` from `ref_logprobs`; exercise 6.5's checker can.

# %%
UPDATES, BETA = 3, 0.04
params = [p for p in model.parameters()]
model.load_state_dict(initial_state)
optimizer = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay)
old_logprobs = ref_logprobs = ro.logprobs      # saved when the batch was sampled


def completion_logits(model, prompt_ids, prompt_mask, completion_ids, completion_mask, temperature):
    """The logits that predict each completion token, as in your exercise 6.1, [N, T, V]."""
    attention_mask = torch.cat([prompt_mask, completion_mask], 1)
    logits = model(input_ids=torch.cat([prompt_ids, completion_ids], 1), attention_mask=attention_mask,
                   position_ids=(attention_mask.cumsum(-1) - 1).clamp(min=0)).logits
    return logits[:, prompt_ids.shape[1] - 1:-1].float() / temperature


print(f"{'update':>6} {'loss':>9} {'clip fraction':>14} {'KL to ref':>10} {'entropy':>8} "
      f"{'|yours - library| / |library|':>30}")
clip_fractions = []
for update in range(1, UPDATES + 1):
    model.zero_grad(set_to_none=True)
    logprobs = completion_logprobs(model, *batch, TEMPERATURE)
    loss, clip_fraction, kl = clipped_loss(logprobs, old_logprobs, ref_logprobs, advantages,
                                           ro.completion_mask, cfg.clip_eps_low, cfg.clip_eps_high, BETA)
    loss.backward()
    your_grads = [p.grad.clone() for p in params]
    model.zero_grad(set_to_none=True)
    library_logprobs, library_entropy = rollout.completion_logprobs(
        model, *batch, temperature=TEMPERATURE, group_size=G, with_entropy=True)
    library_loss, library_stats = losses.grpo_loss(
        library_logprobs, old_logprobs, advantages, ro.completion_mask, loss_type="grpo",
        eps_low=cfg.clip_eps_low, eps_high=cfg.clip_eps_high, ref_logprobs=ref_logprobs, beta=BETA)
    library_loss.backward()
    relative = float(torch.cat([(a - p.grad).flatten() for a, p in zip(your_grads, params)]).norm()
                     / torch.cat([p.grad.flatten() for p in params]).norm())
    with torch.no_grad():
        entropy = token_entropy(completion_logits(model, *batch, TEMPERATURE), ro.completion_mask)
        mean_entropy = float(entropy.sum() / ro.completion_mask.sum())
        assert torch.allclose(entropy, library_entropy * ro.completion_mask, atol=1e-3)
    print(f"{update:6d} {loss.item():9.4f} {clip_fraction:14.3f} {kl:10.2e} {mean_entropy:8.3f} "
          f"{relative:30.1e}")
    assert relative < 1e-3, "your clipped loss's gradient differs from the library's"
    clip_fractions.append(clip_fraction)
    for p, grad in zip(params, your_grads):            # the step, with your gradient
        p.grad = grad
    torch.nn.utils.clip_grad_norm_(params, cfg.max_grad_norm)
    optimizer.step()
assert clip_fractions[-1] > 0, "the clip never acted: the batch was not reused"

# %% [markdown]
# Then the library's step for the same number of steps, from the same pretrained weights, on the
# same prompts, with the same settings. The sampled completions differ (the library's sampler
# draws the random numbers in another order), so the two curves are two draws of one process:
# expect them to wander apart step to step and to end up at similar rewards. The cell also times
# both steps, side by side in one run.

# %%
policy = train.setup(cfg)   # the pretrained weights again, and the same AdamW settings
theirs = {"reward": [], "seconds": []}
for step in tqdm(range(STEPS), desc="train.grpo_step"):
    metrics = train.grpo_step(policy, train.batch_for_step(step, train_prompts, cfg))
    theirs["reward"].append(metrics["reward_mean"])
    theirs["seconds"].append(metrics["step_time"])
reward_after_library = held_out_reward(policy.model)
gain_lib = compare(reward_after_library, reward_before)
between = compare(reward_after_mine, reward_after_library)

fig, ax = plt.subplots(figsize=(6.5, 3.4))
steps = range(1, STEPS + 1)
ax.plot(steps, mine["reward"], "o-", label="your step")
ax.plot(steps, theirs["reward"], "s--", label="train.grpo_step")
ax.set_xlabel("step"); ax.set_ylabel("mean shaped reward of the batch"); ax.legend()
ax.set_title("GRPO on " + cfg.model); plt.tight_layout(); plt.show()

print(f"held-out reward after {STEPS} steps: yours {float(reward_after_mine.mean()):.3f}, "
      f"library {float(reward_after_library.mean()):.3f} (before: {float(reward_before.mean()):.3f})")
print(f"library minus before: {gain_lib.verdict()}")
print(f"yours minus library: {between.verdict()}")
mean_mine, mean_theirs = sum(mine["seconds"]) / STEPS, sum(theirs["seconds"]) / STEPS
print(f"seconds per step: yours {mean_mine:.1f}, library {mean_theirs:.1f} "
      f"({mean_mine / mean_theirs:.1f}x)")

# %% [markdown]
# One algorithm predicts no difference between the two runs. Read the last comparison with
# care: it is paired by held-out prompt, so it measures how these particular runs differ on
# these prompts, not how the two implementations differ over seeds; one seed and a few steps
# bound that only loosely. The exact gradient check above is the real evidence that the steps
# agree. The time per step is the other story: same numbers,
# different cost.
#
# ## 7. Where the library's speed comes from
#
# Every completion of a group starts with the same prompt, and here the prompt is most of each
# row's tokens (the chat template, the instruction and the snippet, against a completion of a
# few tokens). Your two loops pay for it $G$ times:
#
# - **Sampling.** Your sampler prefills $G$ copies of the prompt. The library's
#   (`rollout.sample`) prefills it once and copies its keys and values $G$ times, which is
#   exact: the copies are identical. It also drops a row from the batch and the cache as soon as
#   the row produces EOS, so one rambling completion no longer keeps $G$ rows decoding.
# - **Training.** Your exercise 6.1 runs the prompt through the model once per row. The
#   library's forward (`rollout.completion_logprobs(..., group_size=G)`) runs it once per group,
#   with autograd, and repeats its keys and values for the group's completions. The gradient of a
#   repeated tensor is the sum over its copies, so values and gradients are exactly those of the
#   full computation. It also sorts rows by completion length and cuts each chunk to its own
#   longest completion.
#
# The cell counts the token positions each version runs the model on (a hook on the embedding
# layer) and checks that the shared-prompt forward gives the same log-probabilities.

# %%
counter = exercises.TokenCounter(model)
sample_group(model, prompt_tensor(check_prompts[0]), G, cfg.max_new_tokens, EOS_ID, TEMPERATURE,
             torch.Generator(device=DEVICE).manual_seed(0))
yours_sampling, counter.tokens = counter.tokens, 0
rollout.rollout(model, tokenizer, [check_prompts[0].text], group_size=G, max_new_tokens=cfg.max_new_tokens,
                eos_ids=[EOS_ID], temperature=TEMPERATURE, generator=torch.Generator(device=DEVICE).manual_seed(0))
library_sampling, counter.tokens = counter.tokens, 0
with torch.no_grad():
    full = completion_logprobs(model, *batch, TEMPERATURE)
    yours_training, counter.tokens = counter.tokens, 0
    shared, _ = rollout.completion_logprobs(model, *batch, temperature=TEMPERATURE, group_size=G)
    library_training = counter.tokens
counter.close()
difference = float(((full - shared) * ro.completion_mask).abs().max())
print(f"sampling one group:          yours {yours_sampling:6d} token positions, library {library_sampling:6d}")
print(f"training forward, one batch: yours {yours_training:6d} token positions, library {library_training:6d} "
      f"({yours_training / library_training:.1f}x fewer)")
print(f"largest |log-prob difference|, shared prompt vs full forward: {difference:.1e}")
assert difference < 1e-3   # float32 rounding: the two compute the same sums in another order

# %% [markdown]
# The same idea is in production trainers under other names (prefix caching in vLLM's sampler,
# shared-prefix attention in training). When you read one, the questions to ask are the ones
# this lesson's checkers ask: which positions are scored, under which temperature, with which
# mask, normalized by which counts.
#
# ## Check yourself
#
# 1. The logits at position $j$ predict which token? Write the slice that scores a completion of
#    $T$ tokens after a prompt of $P$, and say what goes wrong with the slice one position later.
# 2. A run samples at temperature 0.7 and scores at 1.0. What is the ratio
#    $\pi_\theta / \pi_{\text{old}}$ of a token at the first update, and what does the clip do
#    with it?
# 3. SmolLM2 pads with its EOS token. What does the mask `ids != pad_id` remove, and what does
#    the policy then never learn?
# 4. Why does the sampling loop run under `torch.no_grad()`, and what would the training forward
#    lose if it did too?
# 5. A batch of 32 completions is backpropagated in 4 micro-batches under the 'dapo'
#    aggregation. Each micro-batch's loss is divided by its own token count and the four losses
#    are averaged. Which tokens weigh more than they should?
# 6. Why is copying a prompt's keys and values $G$ times exact for both the values and the
#    gradients? What would break if the copies were detached?

# %%
print(f"this lesson ran in {time.perf_counter() - LESSON_START:.0f} s")
