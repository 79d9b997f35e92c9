"""The chunked output layer (logprobs.py) against the plain computation: values, gradients of
the hidden states and of the output weight, with temperature, entropy gradients and bf16."""

import pytest
import torch

from course_utils import models
from course_utils.logprobs import body_and_head, output_layer_logprobs
from course_utils.rollout import completion_logprobs


def plain(hidden, weight, ids, temperature):
    z = (hidden @ weight.T).to(torch.promote_types(hidden.dtype, torch.float32)) / temperature
    logp = torch.log_softmax(z, -1)
    return logp.gather(-1, ids[:, None]).squeeze(-1), -(logp.exp() * logp).sum(-1)


@pytest.mark.parametrize("n, vocab, chunk, temperature", [(7, 11, 3, 1.0), (5, 13, 8, 0.7),
                                                           (12, 9, 1, 1.6)])
def test_gradcheck_against_autograd(n, vocab, chunk, temperature):
    g = torch.Generator().manual_seed(n)
    hidden = torch.randn(n, 4, dtype=torch.float64, generator=g, requires_grad=True)
    weight = torch.randn(vocab, 4, dtype=torch.float64, generator=g, requires_grad=True)
    ids = torch.randint(vocab, (n,), generator=g)
    torch.autograd.gradcheck(
        lambda h, w: output_layer_logprobs(h, w, ids, temperature, chunk), (hidden, weight))
    # and the same values and gradients as the plain computation, for a loss on both outputs
    a, b = torch.randn(n, dtype=torch.float64, generator=g), torch.randn(n, dtype=torch.float64, generator=g)
    lp, ent = output_layer_logprobs(hidden, weight, ids, temperature, chunk)
    lp_ref, ent_ref = plain(hidden.double(), weight.double(), ids, temperature)
    torch.testing.assert_close(lp.double(), lp_ref, rtol=0, atol=1e-6)
    torch.testing.assert_close(ent.double(), ent_ref, rtol=0, atol=1e-6)
    mine = torch.autograd.grad((a * lp).sum() + (b * ent).sum(), (hidden, weight))
    ref = torch.autograd.grad((a * lp_ref).sum() + (b * ent_ref).sum(), (hidden, weight))
    for x, y in zip(mine, ref):
        torch.testing.assert_close(x, y, rtol=1e-5, atol=1e-6)


def _batch(tokenizer, model, seed):
    g = torch.Generator().manual_seed(seed)
    P, T, G = 6, 5, 2
    prompt_ids = torch.randint(3, model.config.vocab_size, (2, P), generator=g).repeat_interleave(G, 0)
    prompt_mask = torch.ones_like(prompt_ids)
    prompt_mask[2:, :2] = 0                                      # left padding on the second prompt
    completion_ids = torch.randint(3, model.config.vocab_size, (2 * G, T), generator=g)
    completion_mask = torch.ones_like(completion_ids)
    completion_mask[1, 3:] = 0
    completion_mask[3, 1:] = 0
    return prompt_ids, prompt_mask, completion_ids, completion_mask


@pytest.mark.parametrize("group_size", [1, 2])
def test_completion_logprobs_match_full_logits(group_size):
    """The model's own logits (``model(...).logits``) give the same log-probs, entropies and
    parameter gradients as the chunked output layer, with and without prompt sharing."""
    model = models.tiny_qwen2(vocab_size=97, seed=3)
    assert body_and_head(model) is not None
    batch = _batch(None, model, 0)
    prompt_ids, prompt_mask, completion_ids, completion_mask = batch

    def reference():
        ids = torch.cat([prompt_ids, completion_ids], -1)
        mask = torch.cat([prompt_mask, completion_mask], -1)
        pos = (mask.cumsum(-1) - 1).clamp(min=0)
        logits = model(input_ids=ids, attention_mask=mask, position_ids=pos).logits.float()
        logits = logits[:, prompt_ids.shape[1] - 1:-1] / 0.8
        logp = torch.log_softmax(logits, -1)
        lp = logp.gather(-1, completion_ids[..., None]).squeeze(-1) * completion_mask
        ent = -(logp.exp() * logp).sum(-1) * completion_mask
        return lp, ent

    lp_ref, ent_ref = reference()
    ((lp_ref * 1.3).sum() - ent_ref.sum()).backward()
    grads_ref = [p.grad.clone() for p in model.parameters()]
    model.zero_grad()
    lp, ent = completion_logprobs(model, *batch, temperature=0.8, with_entropy=True,
                                  entropy_grad=True, group_size=group_size, rows_per_chunk=3,
                                  fast=True)
    torch.testing.assert_close(lp * completion_mask, lp_ref, rtol=0, atol=2e-5)
    torch.testing.assert_close(ent * completion_mask, ent_ref, rtol=0, atol=2e-5)
    ((lp * completion_mask * 1.3).sum() - (ent * completion_mask).sum()).backward()
    for p, ref in zip(model.parameters(), grads_ref):
        torch.testing.assert_close(p.grad, ref, rtol=1e-4, atol=1e-6)


def test_bf16_autocast_stays_close_to_fp32():
    """Under CPU bf16 autocast the products run in bf16 and the rest in float32: log-probs move
    by bf16 rounding only (a loose bound; benchmarks/RESULTS.md reports the real model's gap)."""
    g = torch.Generator().manual_seed(0)
    hidden, weight = torch.randn(40, 16, generator=g), torch.randn(50, 16, generator=g) * 0.3
    ids = torch.randint(50, (40,), generator=g)
    lp32, _ = output_layer_logprobs(hidden, weight, ids)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        lp16, _ = output_layer_logprobs(hidden, weight, ids)
    assert lp16.dtype == torch.float32
    assert 0 < float((lp16 - lp32).abs().max()) < 0.1


def test_plain_heads_only():
    """GPT-2 style tied heads are plain linear maps; a head with a bias is not, and falls back."""
    model = models.tiny_qwen2(vocab_size=31, seed=0)
    body, weight = body_and_head(model)
    assert weight is model.get_output_embeddings().weight
    head = model.get_output_embeddings()
    model.set_output_embeddings(torch.nn.Linear(head.in_features, head.out_features, bias=True))
    assert body_and_head(model) is None
