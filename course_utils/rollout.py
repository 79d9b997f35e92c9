"""Sampling G completions per prompt, and scoring tokens under the policy.

The sampler is a plain loop over a key/value cache rather than ``model.generate`` so that every
step is visible: the distribution sampled from (logits / temperature) is the one whose
log-probabilities are returned, and the G completions of a prompt share one prefill of that
prompt (its keys and values are computed once, then copied G times).

Layout: prompts are left-padded (every row ends where sampling starts), completions are
right-padded. Row g * G + j holds completion j of prompt g.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from .logprobs import body_and_head, output_layer_logprobs
from .losses import token_entropy


class NonFiniteLogits(FloatingPointError):
    """The sampler met NaN or inf logits (fp16 overflow, usually): ``torch.multinomial`` would
    crash on them and argmax would pick garbage, so sampling stops and says so."""


@dataclass
class Rollout:
    prompt_ids: torch.Tensor       # [N, P] left-padded prompt tokens (each prompt repeated G times)
    prompt_mask: torch.Tensor      # [N, P] 1 on real prompt tokens
    completion_ids: torch.Tensor   # [N, T] sampled tokens, padding after the first EOS
    completion_mask: torch.Tensor  # [N, T] 1 up to and including the first EOS
    logprobs: torch.Tensor         # [N, T] log pi(token) under the distribution sampled from; 0 on padding
    texts: list[str]               # decoded completions, special tokens skipped
    truncated: torch.Tensor        # [N] True where no EOS came within max_new_tokens
    group_size: int

    @property
    def lengths(self) -> torch.Tensor:
        return self.completion_mask.sum(-1)

    def select_groups(self, groups: list[int]) -> "Rollout":
        """The rows of some prompts' groups, in the order given (whole groups only)."""
        G = self.group_size
        rows = torch.tensor([g * G + j for g in groups for j in range(G)], dtype=torch.long,
                            device=self.completion_ids.device)
        pick = lambda t: t.index_select(0, rows)
        return Rollout(prompt_ids=pick(self.prompt_ids), prompt_mask=pick(self.prompt_mask),
                       completion_ids=pick(self.completion_ids),
                       completion_mask=pick(self.completion_mask), logprobs=pick(self.logprobs),
                       texts=[self.texts[int(r)] for r in rows], truncated=pick(self.truncated),
                       group_size=G)


def concat_rollouts(parts: list[Rollout], pad_id: int) -> Rollout:
    """Rollouts sampled separately, as one batch: prompts left-padded to the longest prompt,
    completions right-padded to the longest completion (padding is masked, so values and
    gradients are those of each part alone; ``tests/test_rollout.py`` checks this)."""
    if len({p.group_size for p in parts}) != 1:
        raise ValueError("rollouts with different group sizes cannot be joined")
    P = max(p.prompt_ids.shape[1] for p in parts)
    T = max(p.completion_ids.shape[1] for p in parts)

    def left(t: torch.Tensor, value) -> torch.Tensor:
        return F.pad(t, (P - t.shape[1], 0), value=value)

    def right(t: torch.Tensor, value) -> torch.Tensor:
        return F.pad(t, (0, T - t.shape[1]), value=value)

    return Rollout(prompt_ids=torch.cat([left(p.prompt_ids, pad_id) for p in parts]),
                   prompt_mask=torch.cat([left(p.prompt_mask, 0) for p in parts]),
                   completion_ids=torch.cat([right(p.completion_ids, pad_id) for p in parts]),
                   completion_mask=torch.cat([right(p.completion_mask, 0) for p in parts]),
                   logprobs=torch.cat([right(p.logprobs, 0.0) for p in parts]),
                   texts=[t for p in parts for t in p.texts],
                   truncated=torch.cat([p.truncated for p in parts]),
                   group_size=parts[0].group_size)


def completion_mask(completion_ids: torch.Tensor, eos_ids: list[int]) -> torch.Tensor:
    """1 on every token up to and including the first EOS, 0 after it.

    Built from the *position* of the first EOS, never from the pad id: for SmolLM2 and
    Qwen2.5 pad == EOS, and ``ids != pad_id`` would drop the real EOS token, so the model would
    never be trained to stop. A row with no EOS (truncated) is all ones.
    """
    is_eos = torch.isin(completion_ids, torch.tensor(eos_ids, device=completion_ids.device))
    T = completion_ids.shape[1]
    first_eos = torch.where(is_eos.any(-1), is_eos.int().argmax(-1), T)
    positions = torch.arange(T, device=completion_ids.device)
    return (positions.unsqueeze(0) <= first_eos.unsqueeze(-1)).long()


def draw(probs: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
    """One token per row of ``probs`` [n, V], drawn from it by inverting the CDF: token k is
    chosen when u * total falls in [cdf[k-1], cdf[k]), which happens with probability
    probs[k] / total up to float rounding (a token of probability 0 has an empty interval and is
    never drawn: the CPU's cumulative sum adds exactly nothing for it).

    One uniform number per row instead of ``torch.multinomial``'s V exponential draws: on the
    49,152-token vocabulary that is most of a decoding step's sampling time
    (benchmarks/kernels.py, in RESULTS.md)."""
    cdf = probs.cumsum(-1)
    u = torch.rand(probs.shape[0], 1, generator=generator, device=probs.device, dtype=cdf.dtype)
    index = torch.searchsorted(cdf, u * cdf[:, -1:], right=True)
    return index.clamp_(max=probs.shape[-1] - 1).squeeze(-1)   # clamp: rounding at u * total ~ total


def _positions(mask: torch.Tensor) -> torch.Tensor:
    """Position ids that start at 0 on each row's first real token (left padding skipped)."""
    return (mask.long().cumsum(-1) - 1).clamp(min=0)


@torch.no_grad()
def sample(model, prompt_ids: torch.Tensor, prompt_mask: torch.Tensor, *, group_size: int,
           max_new_tokens: int, eos_ids: list[int], pad_id: int, temperature: float = 1.0,
           greedy: bool = False, generator: torch.Generator | None = None, fast: bool = False):
    """Sample ``group_size`` continuations of each prompt. Returns (ids, logprobs), [N, T].

    ``fast`` draws each token with ``draw`` (inverse CDF) instead of ``torch.multinomial``: the
    same distribution, a different stream of random numbers from the same generator.

    The prompt is prefilled once per *prompt* and its cache repeated G times (exact: the G
    copies see identical keys and values). Only the last prompt position's logits are
    computed. Log-probabilities are those of the tempered distribution actually sampled from;
    for ``greedy`` they are of the untempered distribution. NaN or inf logits raise
    ``NonFiniteLogits`` (the training loop skips that step and counts it).
    """
    positions = _positions(prompt_mask)
    out = model(input_ids=prompt_ids, attention_mask=prompt_mask, position_ids=positions,
                use_cache=True, logits_to_keep=1)
    cache, logits = out.past_key_values, out.logits[:, -1].float()
    if group_size > 1:
        cache.batch_repeat_interleave(group_size)
        logits = logits.repeat_interleave(group_size, 0)
        prompt_mask = prompt_mask.repeat_interleave(group_size, 0)
        positions = positions.repeat_interleave(group_size, 0)
    n = logits.shape[0]
    attention = prompt_mask
    next_position = positions[:, -1:] + 1
    eos = torch.tensor(eos_ids, device=logits.device)
    live = torch.arange(n, device=logits.device)   # rows still being decoded
    tokens, token_logprobs = [], []
    for _ in range(max_new_tokens):
        if not torch.isfinite(logits).all():
            raise NonFiniteLogits(f"non-finite logits (NaN or inf) while sampling token {len(tokens) + 1}")
        logp = F.log_softmax(logits if greedy or temperature == 1 else logits / temperature, dim=-1)
        if greedy:
            token = logp.argmax(-1)
        elif fast and logp.device.type == "cpu":   # (a GPU's float32 scan could give a
            token = draw(logp.exp(), generator)    # zero-probability token a sliver of the CDF)
        else:
            token = torch.multinomial(logp.exp(), 1, generator=generator).squeeze(-1)
        # finished rows get padding (and log-probability 0) from here on
        tokens.append(torch.full((n,), pad_id, dtype=token.dtype, device=token.device).index_copy(0, live, token))
        token_logprobs.append(logp.new_zeros(n).index_copy(0, live, logp.gather(-1, token[:, None]).squeeze(-1)))
        going = ~torch.isin(token, eos)
        if not going.any():
            break
        if not going.all():
            # Drop the rows that just stopped from the batch and the cache: a decoding step then
            # costs what the live rows need, not what the longest completion needs for all.
            keep = going.nonzero().squeeze(-1)
            cache.batch_select_indices(keep)
            live, token, attention, next_position = live[keep], token[keep], attention[keep], next_position[keep]
        attention = torch.cat([attention, attention.new_ones(len(live), 1)], dim=-1)
        out = model(input_ids=token.unsqueeze(-1), attention_mask=attention,
                    position_ids=next_position, past_key_values=cache, use_cache=True)
        logits, next_position = out.logits[:, -1].float(), next_position + 1
    return torch.stack(tokens, -1), torch.stack(token_logprobs, -1)


def tokenize_prompts(tokenizer, prompts: list[str], device) -> tuple[torch.Tensor, torch.Tensor]:
    """Left-padded prompt ids and mask. Prompts are complete strings (a chat template, if any,
    is already applied), so no special tokens are added here."""
    tokenizer.padding_side = "left"
    enc = tokenizer(prompts, return_tensors="pt", padding=True, add_special_tokens=False)
    return enc["input_ids"].to(device), enc["attention_mask"].to(device)


def rollout(model, tokenizer, prompts: list[str], *, group_size: int, max_new_tokens: int,
            eos_ids: list[int], temperature: float = 1.0, greedy: bool = False,
            generator: torch.Generator | None = None, fast: bool = False) -> Rollout:
    """Sample ``group_size`` completions for each prompt and package everything training needs
    (``fast``: see ``sample``).

    Completions are trimmed to the longest live one, so no step pays for columns of padding.
    """
    device = next(model.parameters()).device
    prompt_ids, prompt_mask = tokenize_prompts(tokenizer, prompts, device)
    ids, logprobs = sample(model, prompt_ids, prompt_mask, group_size=group_size,
                           max_new_tokens=max_new_tokens, eos_ids=eos_ids,
                           pad_id=tokenizer.pad_token_id, temperature=temperature,
                           greedy=greedy, generator=generator, fast=fast)
    mask = completion_mask(ids, eos_ids)
    longest = int(mask.sum(-1).max())
    ids, logprobs, mask = ids[:, :longest], logprobs[:, :longest], mask[:, :longest]
    is_eos = torch.isin(ids, torch.tensor(eos_ids, device=ids.device))
    truncated = ~(is_eos & mask.bool()).any(-1)
    texts = tokenizer.batch_decode([row[m.bool()] for row, m in zip(ids, mask)],
                                   skip_special_tokens=True)
    return Rollout(prompt_ids=prompt_ids.repeat_interleave(group_size, 0),
                   prompt_mask=prompt_mask.repeat_interleave(group_size, 0),
                   completion_ids=ids, completion_mask=mask, logprobs=logprobs * mask,
                   texts=texts, truncated=truncated, group_size=group_size)


# Rows per chunk of the training forward (rows sorted by completion length, each chunk cut to its
# own longest completion): small enough that little padding is computed, large enough for
# efficient matrix multiplies. Each chunk adds its share into every weight's gradient, so fewer,
# larger chunks save those additions: under bf16 autocast the fast path's 32 (a whole cpu-preset
# batch) beats 8 on SmolLM2 (benchmarks/kernels.py, in RESULTS.md; in fp32 it does not), while
# the padding it adds is a few short completions'.
ROWS_PER_CHUNK = 8
FAST_ROWS_PER_CHUNK = 32


def completion_logprobs(model, prompt_ids: torch.Tensor, prompt_mask: torch.Tensor,
                        completion_ids: torch.Tensor, completion_mask: torch.Tensor, *,
                        temperature: float = 1.0, with_entropy: bool = False,
                        entropy_grad: bool = False, group_size: int = 1,
                        rows_per_chunk: int | None = None, fast: bool = False):
    """log pi_theta(o_t | q, o_<t) for every completion token (with autograd), and optionally
    the per-token entropy (differentiable only if ``entropy_grad``). Positions past the longest
    completion of a row's chunk get 0; padding positions before that hold values that the loss's
    mask removes (with the fused output layer, 0 as well).

    The same temperature as in sampling is applied, so on-policy the ratio pi_theta / pi_old
    starts at exactly 1 (up to floating-point noise).

    Savings, all exact (the third and larger chunks only with ``fast``; without it the
    computation is the one every stored run was made with, so those reproduce bitwise):
    - With ``group_size`` G > 1 (rows g*G ... g*G+G-1 share one prompt), each prompt is
      forwarded once, with autograd, and its keys/values are copied to its G completions. The
      gradient of a copy sums over the copies, so values and gradients are those of the
      full-sequence forward, at 1/G of the prompt's cost.
    - Rows are sorted by completion length and forwarded in chunks, each cut to its own longest
      completion: one long completion no longer makes every row pay for its length.
    - On a CPU the output layer is applied only at the masked tokens, chunk by chunk, without
      keeping their [tokens, vocab] logits for the backward (``logprobs.output_layer_logprobs``).
      Models whose logits are not a plain linear map of the last hidden state get full logits.
    """
    N, T = completion_ids.shape
    lengths = completion_mask.sum(-1)
    rows_per_chunk = rows_per_chunk or (FAST_ROWS_PER_CHUNK if fast else ROWS_PER_CHUNK)
    # The fused output layer runs on a CPU only: there the course's bf16 is its own autocast
    # block around this call, while on a GPU accelerate's autocast wraps model.forward and
    # calling the body directly would step outside it.
    fused = body_and_head(model) if fast and completion_ids.device.type == "cpu" else None
    net = model if fused is None else fused[0]   # the whole model, or its body without the head
    prompt_kv = None
    if group_size > 1:
        unique_mask = prompt_mask[::group_size]
        out = net(input_ids=prompt_ids[::group_size], attention_mask=unique_mask,
                  position_ids=_positions(unique_mask), use_cache=True,
                  **({} if fused else dict(logits_to_keep=1)))
        last = out.logits[:, -1:] if fused is None else out.last_hidden_state[:, -1:]
        prompt_kv = (out.past_key_values, last)
    logprobs = torch.zeros(N, T, device=completion_ids.device)
    entropy = torch.zeros(N, T, device=completion_ids.device) if with_entropy else None
    order = torch.argsort(lengths, descending=True, stable=True)
    for rows in order.split(rows_per_chunk):
        L = max(int(lengths[rows].max()), 1)
        if prompt_kv is None:
            outputs = _full_outputs(net, prompt_ids[rows], prompt_mask[rows],
                                    completion_ids[rows, :L], completion_mask[rows, :L], fused is None)
        else:
            outputs = _shared_prompt_outputs(net, *prompt_kv, rows // group_size, prompt_mask[rows],
                                             completion_ids[rows, :L], completion_mask[rows, :L],
                                             fused is None)
        ids = completion_ids[rows, :L]
        if fused is None:   # full logits: gather minus logsumexp, without a second [n, L, V] tensor
            logits = outputs.float() if temperature == 1 else outputs.float() / temperature
            logprobs[rows, :L] = logits.gather(-1, ids.unsqueeze(-1)).squeeze(-1) - logits.logsumexp(-1)
            if with_entropy:
                with torch.set_grad_enabled(entropy_grad and torch.is_grad_enabled()):
                    entropy[rows, :L] = token_entropy(logits)
            continue
        real = completion_mask[rows, :L].bool()
        token_lp, token_entropy_ = output_layer_logprobs(outputs[real], fused[1], ids[real], temperature)
        logprobs[rows, :L] = torch.zeros_like(real, dtype=token_lp.dtype).masked_scatter(real, token_lp)
        if with_entropy:
            token_entropy_ = token_entropy_ if entropy_grad else token_entropy_.detach()
            entropy[rows, :L] = torch.zeros_like(real, dtype=token_lp.dtype).masked_scatter(real, token_entropy_)
    return logprobs, entropy


def _full_outputs(net, prompt_ids, prompt_mask, completion_ids, completion_mask, logits: bool):
    """Logits (``logits``) or last hidden states predicting each completion token, from one
    forward over prompt + completion."""
    input_ids = torch.cat([prompt_ids, completion_ids], dim=-1)
    attention = torch.cat([prompt_mask, completion_mask.to(prompt_mask.dtype)], dim=-1)
    T = completion_ids.shape[1]
    # Position P-1+t predicts completion token t, so keep the last T+1 positions and drop
    # the final one (it would predict a token after the completion).
    kwargs = dict(input_ids=input_ids, attention_mask=attention, position_ids=_positions(attention))
    if logits:
        return net(**kwargs, logits_to_keep=T + 1).logits[:, :-1]
    return net(**kwargs).last_hidden_state[:, -T - 1:-1]


def _shared_prompt_outputs(net, prompt_cache, prompt_last, groups, prompt_mask,
                           completion_ids, completion_mask, logits: bool):
    """Logits or hidden states predicting each completion token of some rows, given their
    prompts' keys/values (computed once per prompt, with autograd); ``groups`` says which prompt
    each row continues, ``prompt_last`` is the prompt's last position's output."""
    from transformers import DynamicCache

    P, T = prompt_mask.shape[1], completion_ids.shape[1]
    first = prompt_last.index_select(0, groups)              # the last prompt position predicts o_0
    if T == 1:
        return first
    cache = DynamicCache()
    for i, layer in enumerate(prompt_cache.layers):           # copies: their gradients add up
        cache.update(layer.keys.index_select(0, groups), layer.values.index_select(0, groups), i)
    attention = torch.cat([prompt_mask, completion_mask.to(prompt_mask.dtype)], dim=-1)
    positions = _positions(attention)
    out = net(input_ids=completion_ids[:, :-1], attention_mask=attention[:, :P + T - 1],
              position_ids=positions[:, P:P + T - 1], past_key_values=cache, use_cache=True)
    rest = out.logits if logits else out.last_hidden_state
    return torch.cat([first, rest], dim=1)
