"""Checkers for the exercises that write GRPO's language-model side by hand (issue 15).

The learner writes three pieces that the library's ``rollout`` and ``train`` modules hide:

1. ``completion_logprobs``: the log-probability of every completion token under a causal LM,
   with the one-position shift, the temperature, left-padded prompts and the completion mask.
2. ``sample_group``: G completions of one prompt with a key/value cache, each stopped at its
   first EOS, returning the ids, the mask and the log-probabilities sampled under.
3. ``grpo_backward``: the GRPO loss on a batch, backpropagated micro-batch by micro-batch so
   that the accumulated gradient equals the full batch's.

Each checker works as those in ``exercises.py`` do: several seeded inputs of different shapes
on small random Qwen2 models (the same architecture as the lesson's real models, seconds on a
CPU), the library's implementation as the reference, the mistakes learners make recognized and
named, inputs checked for in-place changes, and gradients checked wherever the answer feeds one.
"""

from __future__ import annotations

from typing import Callable

import torch

from . import losses
from .exercises import ExerciseError, _as_tensor, _close, _run
from .models import tiny_qwen2
from .rollout import _positions, completion_logprobs as reference_logprobs
from .rollout import completion_mask as reference_mask


def _model(seed: int, vocab: int = 64, sharpen: float = 1.0):
    """A small random Qwen2 in eval mode. ``sharpen`` scales the output layer, so that its
    next-token distributions are far from uniform and a temperature visibly changes them."""
    model = tiny_qwen2(vocab, seed=seed, tie_word_embeddings=False).eval()
    with torch.no_grad():
        model.lm_head.weight.mul_(sharpen)
    return model


def _gpt2_model(seed: int, vocab: int = 64, sharpen: float = 1.0):
    """A small random GPT-2: *absolute* position embeddings, so a left-padded row scored without
    position ids gets different logits (a rotary model such as Qwen2 sees only relative
    positions and would not show the mistake)."""
    from transformers import GPT2Config, GPT2LMHeadModel

    torch.manual_seed(seed)
    config = GPT2Config(vocab_size=vocab, n_positions=64, n_embd=32, n_layer=2, n_head=4,
                        tie_word_embeddings=False)
    model = GPT2LMHeadModel(config).eval()
    with torch.no_grad():
        model.lm_head.weight.mul_(sharpen)
    return model


def _batch(g: torch.Generator, vocab: int, N: int, P: int, T: int, eos: int):
    """Left-padded prompts of different lengths and right-padded completions ending in EOS at
    different positions (one row with no EOS at all: truncated)."""
    prompt_ids = torch.randint(3, vocab, (N, P), generator=g)
    prompt_lengths = torch.randint(2, P + 1, (N,), generator=g)
    prompt_lengths[0] = P
    prompt_mask = (torch.arange(P) >= P - prompt_lengths[:, None]).long()
    prompt_ids = torch.where(prompt_mask.bool(), prompt_ids, eos)   # pad == EOS, as in SmolLM2
    completion_ids = torch.randint(3, vocab, (N, T), generator=g)
    for row in range(1, N):                    # row 0 is truncated: no EOS
        end = int(torch.randint(0, T, (1,), generator=g))
        completion_ids[row, end:] = eos
    mask = reference_mask(completion_ids, [eos])
    return prompt_ids, prompt_mask, completion_ids, mask


def _full_logits(model, prompt_ids, prompt_mask, completion_ids, completion_mask, *,
                 positions: bool = True, attention: bool = True):
    """Every position's logits over prompt + completion, for building the wrong answers."""
    ids = torch.cat([prompt_ids, completion_ids], -1)
    mask = torch.cat([prompt_mask, completion_mask], -1)
    kwargs = {}
    if attention:
        kwargs["attention_mask"] = mask
    if positions:
        kwargs["position_ids"] = _positions(mask)
    return model(input_ids=ids, **kwargs).logits.float()


def _gather(logits, ids):
    return torch.log_softmax(logits, -1).gather(-1, ids.unsqueeze(-1)).squeeze(-1)


def _logprob_mistakes(model, prompt_ids, prompt_mask, completion_ids, mask, temperature):
    """The wrong answers learners write, each named."""
    P, T = prompt_ids.shape[1], completion_ids.shape[1]
    with torch.no_grad():
        full = _full_logits(model, prompt_ids, prompt_mask, completion_ids, mask)
        right = full[:, P - 1:P + T - 1]
        shifted = full[:, P:P + T]
        no_positions = _full_logits(model, prompt_ids, prompt_mask, completion_ids, mask,
                                    positions=False)[:, P - 1:P + T - 1]
        no_attention = _full_logits(model, prompt_ids, prompt_mask, completion_ids, mask,
                                    attention=False, positions=False)[:, P - 1:P + T - 1]
        m = mask.float()
        return {
            "off by one: the logits at position t predict token t+1, so completion token t is "
            "scored by the logits one position *before* it (slice the logits [P-1 : P+T-1], not "
            "[P : P+T])": _gather(shifted / temperature, completion_ids) * m,
            "the temperature is missing: score under softmax(logits / temperature), the "
            "distribution the tokens were sampled from, or the ratio pi/pi_old starts away from "
            "1": _gather(right, completion_ids) * m,
            "the temperature multiplies the logits; it divides them":
                _gather(right * temperature, completion_ids) * m,
            "padding positions are not zeroed: multiply by the completion mask (tokens after the "
            "first EOS are not part of the completion)": _gather(right / temperature, completion_ids),
            "these are probabilities, not log-probabilities: use log_softmax":
                torch.softmax(right / temperature, -1).gather(-1, completion_ids.unsqueeze(-1))
                .squeeze(-1) * m,
            # (a rotary model such as Qwen2 gives the same logits without position ids, so this
            # answer is caught on the GPT-2 case only, where positions are absolute)
            "the position ids ignore the left padding: a left-padded row must start counting "
            "positions at its first real token (position_ids = attention_mask.cumsum(-1) - 1, "
            "clamped at 0)": _gather(no_positions / temperature, completion_ids) * m,
            "the attention mask is missing: real tokens attend to the padding on the left":
                _gather(no_attention / temperature, completion_ids) * m,
        }


def check_completion_logprobs(fn: Callable) -> None:
    """``fn(model, prompt_ids, prompt_mask, completion_ids, completion_mask, temperature)`` ->
    [N, T] log pi(o_t | q, o_<t) under softmax(logits / temperature), 0 on padding, with a
    gradient that reaches the model's weights."""
    name = "completion_logprobs"
    g = torch.Generator().manual_seed(0)
    cases = [(3, 5, 4, 1.0, "qwen2"), (4, 7, 6, 0.7, "qwen2"), (2, 3, 5, 1.3, "qwen2"),
             (4, 6, 5, 0.9, "gpt2")]
    for case, (N, P, T, temperature, arch) in enumerate(cases):
        model = _model(seed=case, sharpen=8.0) if arch == "qwen2" else _gpt2_model(seed=case, sharpen=8.0)
        eos = 2
        prompt_ids, prompt_mask, completion_ids, mask = _batch(g, 64, N, P, T, eos)
        args = dict(model=model, prompt_ids=prompt_ids, prompt_mask=prompt_mask,
                    completion_ids=completion_ids, completion_mask=mask, temperature=temperature)
        got = _as_tensor(name, _run(name, fn, args))
        if got.shape != (N, T):
            hint = (" It covers the prompt positions too: keep only the T positions that predict "
                    "completion tokens." if got.dim() == 2 and got.shape[1] > T else "")
            raise ExerciseError(f"{name}: wrong shape {tuple(got.shape)}, expected {(N, T)}.{hint}")
        # the library leaves values at padding inside a chunk (its loss masks them); zero them
        want = reference_logprobs(model, prompt_ids, prompt_mask, completion_ids, mask,
                                  temperature=temperature)[0] * mask
        if not _close(got.detach(), want.detach(), 2e-4):
            for message, value in _logprob_mistakes(model, prompt_ids, prompt_mask, completion_ids,
                                                    mask, temperature).items():
                if _close(got.detach(), value, 2e-4):
                    raise ExerciseError(f"{name}: {message}")
            diff = (got.detach() - want.detach()).abs().max().item()
            raise ExerciseError(f"{name}: differs from the reference by up to {diff:.3g} on a "
                                f"seeded batch ({N} rows, prompts left-padded to {P} tokens, "
                                f"completions of up to {T}). Re-read the steps above the cell.")
        _check_gradient_reaches_weights(name, model, got, want)
    print(f"✓ {name}: correct (4 batches with left padding on a rotary model, Qwen2, and one with "
          f"absolute positions, GPT-2; temperatures 1.0, 0.7, 1.3 and 0.9)")


def _check_gradient_reaches_weights(name, model, got, want) -> None:
    if not got.requires_grad:
        raise ExerciseError(f"{name}: the values are right but carry no gradient: the forward ran "
                            f"under torch.no_grad() or the result was detached, so the GRPO loss "
                            f"built on it could not train the model.")
    weights = torch.randn(want.shape, generator=torch.Generator().manual_seed(7))
    params = [p for p in model.parameters() if p.requires_grad]
    g_got = torch.autograd.grad((got * weights).sum(), params, retain_graph=True, allow_unused=True)
    g_want = torch.autograd.grad((want * weights).sum(), params, allow_unused=True)
    for p, a, b in zip(params, g_got, g_want):
        a = torch.zeros_like(p) if a is None else a
        b = torch.zeros_like(p) if b is None else b
        if not _close(a, b, 1e-3):
            raise ExerciseError(f"{name}: the values are right but their gradient with respect to "
                                f"the model's weights is not: part of the computation is detached.")


# ----------------------------------------------------------------------------------------------
# Exercise 2: sampling a group with a key/value cache
# ----------------------------------------------------------------------------------------------


class TokenCounter:
    """Counts the token positions the model is run on (a forward hook on the embeddings): a
    loop with a key/value cache runs each token once; one without reruns the whole sequence."""

    def __init__(self, model):
        self.tokens = 0
        self.handle = model.get_input_embeddings().register_forward_hook(self._count)

    def _count(self, module, inputs, output):
        self.tokens += inputs[0].numel()

    def close(self) -> None:
        self.handle.remove()


def _sample(name, fn, model, prompt_ids, G, max_new, eos, temperature, seed):
    args = dict(model=model, prompt_ids=prompt_ids, G=G, max_new_tokens=max_new, eos_id=eos,
                temperature=temperature, generator=torch.Generator().manual_seed(seed))
    out = _run(name, fn, args)
    if not (isinstance(out, tuple) and len(out) == 3):
        raise ExerciseError(f"{name}: return (completion_ids, completion_mask, logprobs), got "
                            f"{type(out).__name__}")
    ids, mask, logprobs = (_as_tensor(name, t) for t in out)
    if ids.dim() != 2 or ids.shape[0] != G or not 1 <= ids.shape[1] <= max_new:
        raise ExerciseError(f"{name}: completion_ids has shape {tuple(ids.shape)}; expected "
                            f"[{G}, T] with 1 <= T <= max_new_tokens = {max_new}")
    if mask.shape != ids.shape or logprobs.shape != ids.shape:
        raise ExerciseError(f"{name}: ids {tuple(ids.shape)}, mask {tuple(mask.shape)} and "
                            f"logprobs {tuple(logprobs.shape)} must have the same shape")
    return ids, mask, logprobs


def check_sample_group(fn: Callable) -> None:
    """``fn(model, prompt_ids, G, max_new_tokens, eos_id, temperature, generator)`` with one
    prompt ``prompt_ids`` [1, P] -> (completion_ids [G, T], completion_mask [G, T], logprobs
    [G, T]): G continuations sampled from softmax(logits / temperature) with a key/value cache,
    the mask 1 up to and including each row's first EOS, and the log-probability of each sampled
    token under the distribution it was sampled from (0 on padding)."""
    name = "sample_group"
    g = torch.Generator().manual_seed(1)
    # EOS made likely enough that some rows stop early and others run to max_new_tokens, and in
    # the last case so likely that every row stops well before it (the loop must stop then)
    for case, (P, G, max_new, temperature, eos_boost) in enumerate(
            [(4, 6, 8, 1.0, 0.15), (7, 4, 12, 0.7, 0.15), (5, 5, 24, 1.0, 10.0)]):
        model = _model(seed=10 + case, vocab=32, sharpen=6.0)
        eos = 2
        with torch.no_grad():
            model.lm_head.weight[eos] = model.lm_head.weight.mean(0) + eos_boost * model.lm_head.weight.std()
        prompt_ids = torch.randint(3, 32, (1, P), generator=g)
        counter = TokenCounter(model)
        grad_modes: list[bool] = []
        watch = model.register_forward_pre_hook(lambda *_: grad_modes.append(torch.is_grad_enabled()))
        try:
            ids, mask, logprobs = _sample(name, fn, model, prompt_ids, G, max_new, eos,
                                          temperature, seed=case)
        finally:
            counter.close()
            watch.remove()
        if logprobs.requires_grad or ids.requires_grad or any(grad_modes):
            raise ExerciseError(f"{name}: sampling built an autograd graph (the log-probs require "
                                f"grad): run the loop under torch.no_grad(). Sampling is not "
                                f"differentiated, and the graph of every decoding step would be "
                                f"kept in memory until the step ends.")
        T = ids.shape[1]
        again, _, _ = _sample(name, fn, model, prompt_ids, G, max_new, eos, temperature, seed=case)
        if not torch.equal(again, ids):
            raise ExerciseError(f"{name}: two calls with generators seeded alike sampled different "
                                f"tokens: draw every token with the generator passed in "
                                f"(torch.multinomial(..., generator=generator)), so a run can be "
                                f"reproduced and resumed.")
        _check_sample_mask(name, ids, mask, eos)
        is_eos = ids == eos
        after = (is_eos.long().cumsum(1) - is_eos.long()) > 0      # strictly after the first EOS
        if (ids[after] != eos).any():
            raise ExerciseError(f"{name}: a row has tokens other than EOS after its first EOS: once "
                                f"a row has ended, feed and record EOS (the padding) for it.")
        ends = torch.where(is_eos.any(1), is_eos.float().argmax(1) + 1, torch.full((G,), max_new))
        if T != int(ends.max()):
            raise ExerciseError(f"{name}: the completions are {T} tokens wide, but the longest row "
                                f"ends after {int(ends.max())}: stop the loop once every row has "
                                f"produced EOS (and not before).")
        _check_sample_logprobs(name, model, prompt_ids, ids, mask, logprobs, temperature)
        # with a cache: the prompt once (or once per row) and each new token once
        budget = G * P + G * T
        if counter.tokens > budget:
            raise ExerciseError(f"{name}: the model ran on {counter.tokens} token positions to "
                                f"sample {G} x {T} tokens after a {P}-token prompt; a loop with a "
                                f"key/value cache needs at most {budget}. Pass past_key_values "
                                f"(and use_cache=True) and feed only the newest token each step.")
    _check_sampling_distribution(name, fn)
    print(f"✓ {name}: correct (EOS handling, log-probs under the sampled temperature, a key/value "
          f"cache, samples that follow the tempered distribution)")


def _check_sample_mask(name, ids, mask, eos) -> None:
    want = reference_mask(ids, [eos])
    if torch.equal(mask.long(), want):
        return
    if torch.equal(mask.long(), (ids != eos).long()):
        # with pad == EOS this is also the mask that stops just before the first EOS
        raise ExerciseError(f"{name}: the mask is `ids != pad_id`, which drops the real EOS token "
                            f"(pad == EOS here, as for SmolLM2; Qwen2.5 pads with <|endoftext|>, one of "
                            f"its end tokens), so the model would "
                            f"never be trained to stop. Mask up to and including the first EOS.")
    if bool(mask.all()):
        raise ExerciseError(f"{name}: the mask is 1 everywhere, padding after the first EOS "
                            f"included; it must be 0 after each row's first EOS.")
    raise ExerciseError(f"{name}: the mask is not 1 up to and including each row's first EOS "
                        f"and 0 after it.")


def _check_sample_logprobs(name, model, prompt_ids, ids, mask, logprobs, temperature) -> None:
    G = ids.shape[0]
    prompts = prompt_ids.expand(G, -1)
    prompt_mask = torch.ones_like(prompts)
    with torch.no_grad():
        want = reference_logprobs(model, prompts, prompt_mask, ids, mask, temperature=temperature)[0]
        untempered = reference_logprobs(model, prompts, prompt_mask, ids, mask)[0]
    real = mask.bool()
    if (logprobs[~real] != 0).any():
        raise ExerciseError(f"{name}: log-probs after a row's first EOS must be 0 (those positions "
                            f"are padding, not sampled tokens).")
    if _close(logprobs[real], want[real], 2e-4):
        return
    if temperature != 1.0 and _close(logprobs[real], untempered[real], 2e-4):
        raise ExerciseError(f"{name}: the tokens are sampled at the temperature but their "
                            f"log-probs are of the untempered distribution: record "
                            f"log_softmax(logits / temperature) at the sampled token, or the "
                            f"ratio pi/pi_old will not start at 1.")
    if _close(logprobs[real], want[real].exp(), 2e-4):
        raise ExerciseError(f"{name}: these are probabilities, not log-probabilities.")
    diff = (logprobs[real] - want[real]).abs().max().item()
    raise ExerciseError(f"{name}: the sampled log-probs differ by up to {diff:.3g} from scoring the "
                        f"same tokens afterwards (exercise 1's computation): each must be "
                        f"log_softmax(logits / temperature) of the step that sampled it.")


def _check_sampling_distribution(name, fn) -> None:
    """The sampled tokens follow softmax(logits / temperature), at the first step and at the
    second (rows whose first token was the likeliest one, so that they share a context): each
    closer to it in total variation than to the untempered distribution, and within sampling
    noise of it. With 4,000 rows the noise is about 0.008 (99% of draws below 0.019); top-p 0.95
    sampling, which drops the tail, is 0.049 away, so the threshold 0.035 tells them apart."""
    # a model whose next-token distribution after this prompt is neither flat nor one-hot: at
    # temperature 0.5 it moves about 0.3 in total variation
    model = _model(seed=20, vocab=8, sharpen=7.0)
    prompt_ids = torch.tensor([[5, 3, 7, 4]])
    G, temperature, threshold = 4000, 0.5, 0.035
    ids, _, _ = _sample(name, fn, model, prompt_ids, G, 2, 2, temperature, seed=3)
    tv = lambda p, q: 0.5 * float((p - q).abs().sum())  # noqa: E731
    with torch.no_grad():
        first = model(input_ids=prompt_ids).logits[0, -1].float()
        top = int(first.argmax())
        second = model(input_ids=torch.cat([prompt_ids, torch.tensor([[top]])], -1)).logits[0, -1].float()
    rows = ids[:, 0] == top
    for step, logits, drawn in (("first", first, ids[:, 0]),
                                ("second", second, ids[rows, 1] if ids.shape[1] > 1 else None)):
        if drawn is None or len(drawn) < 1000:   # every row stopped at the first token
            continue
        counts = torch.bincount(drawn.long(), minlength=8).double() / len(drawn)
        tempered = torch.softmax(logits / temperature, -1).double()
        plain = torch.softmax(logits, -1).double()
        if tv(tempered, plain) < 0.15:  # pragma: no cover - guards the check itself
            raise RuntimeError("the distribution check's model is too flat to tell temperatures apart")
        if tv(counts, tempered) > threshold or tv(counts, tempered) >= tv(counts, plain):
            raise ExerciseError(f"{name}: over {len(drawn)} samples of the {step} token, the "
                                f"frequencies are {tv(counts, tempered):.3f} (total variation) from "
                                f"softmax(logits / temperature) and {tv(counts, plain):.3f} from "
                                f"softmax(logits), against sampling noise below {threshold}: "
                                f"sample from the tempered distribution at every step, all of it, "
                                f"torch.multinomial(softmax(logits / temperature), 1), with no "
                                f"top-k or top-p cut.")


# ----------------------------------------------------------------------------------------------
# Exercise 3: the micro-batched GRPO backward
# ----------------------------------------------------------------------------------------------


def _grads(model) -> list[torch.Tensor]:
    return [torch.zeros_like(p) if p.grad is None else p.grad.detach().clone()
            for p in model.parameters()]


def _reference_backward(model, batch, advantages, temperature, loss_type, micro_rows, mode):
    """The gradient of the full-batch loss (``mode='global'``) or of two wrong accumulations."""
    prompt_ids, prompt_mask, completion_ids, mask = batch
    N, T = completion_ids.shape
    model.zero_grad(set_to_none=True)
    n_micro = N // micro_rows
    for start in range(0, N, micro_rows):
        rows = slice(start, start + micro_rows)
        logprobs = reference_logprobs(model, prompt_ids[rows], prompt_mask[rows],
                                      completion_ids[rows], mask[rows], temperature=temperature)[0]
        tokens = int(mask.sum()) + (int(prompt_mask.sum()) if mode == "prompt tokens" else 0)
        totals = dict(max_completion_length=T, total_sequences=N, total_tokens=tokens)
        if mode in ("averaged", "summed"):   # each micro-batch normalized by its own counts
            totals = dict(max_completion_length=T)
        loss, _ = losses.grpo_loss(logprobs, logprobs.detach(), advantages[rows], mask[rows],
                                   loss_type=loss_type, **totals)
        if mode == "averaged":
            loss = loss / n_micro
        if mode == "zeroed":                 # .grad cleared before each micro-batch's backward
            model.zero_grad(set_to_none=True)
        loss.backward()
    grads = _grads(model)
    model.zero_grad(set_to_none=True)
    return grads


class _CallLog:
    """Records, while active, how many rows each forward of ``model`` runs on and when a
    backward pass reaches its weights (a hook on the input embedding, which every forward uses),
    so a checker can tell a micro-batched backward from one that only looks like it."""

    def __init__(self, model):
        self.events: list[tuple[str, int]] = []
        self._handles = [
            model.register_forward_pre_hook(self._forward, with_kwargs=True),
            model.get_input_embeddings().weight.register_hook(self._backward),
        ]

    def _forward(self, module, args, kwargs):
        ids = kwargs.get("input_ids", args[0] if args else None)
        if ids is None:
            ids = kwargs.get("inputs_embeds")
        self.events.append(("forward", int(ids.shape[0])))

    def _backward(self, grad):
        self.events.append(("backward", 0))
        return grad

    def close(self):
        for handle in self._handles:
            handle.remove()

    def problem(self, N: int, micro_rows: int) -> str | None:
        """What is wrong with the call pattern, or None: every forward on at most micro_rows
        rows, and one backward per micro-batch, each after that micro-batch's forwards."""
        rows = [n for kind, n in self.events if kind == "forward"]
        backwards = sum(kind == "backward" for kind, _ in self.events)
        if rows and max(rows) > micro_rows:
            return (f"the model ran on {max(rows)} rows in one forward; micro-batching means at "
                    f"most micro_rows = {micro_rows} rows per forward, so that only one "
                    f"micro-batch's activations are in memory at a time")
        micro_batches = -(-N // micro_rows)
        if backwards < micro_batches:
            return (f"{backwards} backward pass(es) for {micro_batches} micro-batches: the "
                    f"micro-batch losses were added up and backpropagated together, which keeps "
                    f"every micro-batch's graph in memory at once; call .backward() on each "
                    f"micro-batch's loss before the next forward")
        kinds = [kind for kind, _ in self.events]
        for a, b in zip(kinds, kinds[1:]):
            if a == b == "backward":
                return ("two backward passes without a forward between them: backpropagate each "
                        "micro-batch's loss once, right after its forward")
        return None


def check_grpo_backward(fn: Callable) -> None:
    """``fn(model, prompt_ids, prompt_mask, completion_ids, completion_mask, advantages,
    temperature, micro_rows, loss_type)``: backpropagate the GRPO loss (one update per batch, so
    pi_old = the current policy, detached) micro-batch by micro-batch of ``micro_rows`` rows, so
    that the gradients accumulated in the model's ``.grad`` equal the full batch's for
    ``loss_type`` 'grpo' (mean per sequence, then over sequences) or 'dapo' (mean over all
    tokens). Returns the full-batch loss as a float."""
    name = "grpo_backward"
    g = torch.Generator().manual_seed(2)
    for case, (N, micro, P, T, loss_type, temperature) in enumerate(
            [(8, 4, 5, 6, "dapo", 1.0), (6, 2, 4, 5, "grpo", 0.7), (8, 2, 6, 7, "dapo", 0.8)]):
        model = _model(seed=30 + case, sharpen=4.0)
        batch = _batch(g, 64, N, P, T, eos=2)
        advantages = torch.randn(N, 1, generator=g)
        want = _reference_backward(model, batch, advantages, temperature, loss_type, N, "global")
        # .grad holds something already, as it would after another loss's backward: the answer
        # must add to it, not clear it (the caller zeroes once per step)
        with torch.no_grad():
            for k, param in enumerate(model.parameters()):
                param.grad = 0.01 * torch.randn(param.shape, generator=torch.Generator().manual_seed(k))
        before = _grads(model)
        args = dict(model=model, prompt_ids=batch[0], prompt_mask=batch[1],
                    completion_ids=batch[2], completion_mask=batch[3], advantages=advantages,
                    temperature=temperature, micro_rows=micro, loss_type=loss_type)
        log = _CallLog(model)
        try:
            loss = _run(name, fn, args)
        finally:
            log.close()
        raw = _grads(model)
        got = [r - b for r, b in zip(raw, before)]
        model.zero_grad(set_to_none=True)
        if all(_close(r, w, 1e-4) for r, w in zip(raw, want)):
            raise ExerciseError(f"{name}: the gradients were zeroed before the first micro-batch: "
                                f"leave .grad as you find it and add to it (the caller zeroes it "
                                f"once per step, before your function; a test here fills it first)")
        if all(float(t.abs().max()) == 0 for t in got):
            raise ExerciseError(f"{name}: no gradient reached the model: call loss.backward() on "
                                f"each micro-batch's loss (and do not zero the gradients between "
                                f"micro-batches).")
        pattern = log.problem(N, micro)
        if pattern:
            raise ExerciseError(f"{name}: {pattern}.")
        if not all(_close(a, b, 1e-4) for a, b in zip(got, want)):
            wrong = {
                "averaged": f"each micro-batch's loss is normalized by its own counts and the "
                            f"{N // micro} losses averaged: with '{loss_type}' that weighs a "
                            f"token by the size of its micro-batch. Normalize every micro-batch by "
                            f"the whole batch's counts (total sequences, total tokens) and sum.",
                "summed": f"each micro-batch's loss is normalized by its own counts and the "
                          f"losses summed: the gradient is about {N // micro}x the full batch's. "
                          f"Normalize by the whole batch's counts.",
                "zeroed": "only the last micro-batch's gradient is left: the gradients were "
                          "zeroed between micro-batches. Zero them once, before the first.",
                "prompt tokens": "the token count includes the prompt tokens: only completion "
                                 "tokens (completion_mask) are in the loss, so only they count.",
            }
            for mode, message in wrong.items():
                other = _reference_backward(model, batch, advantages, temperature, loss_type,
                                            micro, mode)
                # zeroing between micro-batches also wiped what .grad held before the call
                seen = raw if mode == "zeroed" else got
                if all(_close(a, b, 1e-4) for a, b in zip(seen, other)):
                    raise ExerciseError(f"{name}: {message}")
            raise ExerciseError(f"{name}: the accumulated gradient differs from the full batch's "
                                f"({N} rows in micro-batches of {micro}, loss_type {loss_type!r}).")
        with torch.no_grad():
            logprobs = reference_logprobs(model, *batch, temperature=temperature)[0]
            full, _ = losses.grpo_loss(logprobs, logprobs, advantages, batch[3],
                                       loss_type=loss_type)
        try:
            loss = float(loss)
        except (TypeError, ValueError, RuntimeError):
            loss = float("nan")
        if abs(loss - float(full)) > 1e-4:
            raise ExerciseError(f"{name}: the gradients are right; return the full-batch loss as a "
                                f"float (the sum of the micro-batch losses, {float(full):.4f} here)")
    print(f"✓ {name}: correct (micro-batched gradients equal the full batch's for 'grpo' and "
          f"'dapo')")

