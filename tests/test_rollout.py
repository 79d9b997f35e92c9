"""Sampling and scoring tokens: masks, log-probabilities, padding, prefix sharing."""
import torch

from course_utils import rollout as R
from course_utils.losses import token_entropy


def test_completion_mask_keeps_the_first_eos_when_pad_equals_eos():
    eos = pad = 2
    ids = torch.tensor([[5, 6, eos, pad, pad],   # ended: EOS kept, the pads after it dropped
                        [5, eos, pad, pad, pad],
                        [eos, pad, pad, pad, pad],  # empty completion: just the EOS
                        [5, 6, 7, 8, 9]])          # truncated: no EOS, all ones
    mask = R.completion_mask(ids, [eos])
    assert mask.tolist() == [[1, 1, 1, 0, 0], [1, 1, 0, 0, 0], [1, 0, 0, 0, 0], [1, 1, 1, 1, 1]]
    naive = (ids != pad).long()  # the classic bug: the real EOS vanishes from the loss
    assert naive[0].tolist() == [1, 1, 0, 0, 0]


def test_completion_mask_with_several_stop_ids():
    ids = torch.tensor([[5, 9, 2, 9]])
    assert R.completion_mask(ids, [2, 9]).tolist() == [[1, 1, 0, 0]]


def _sampled(tiny_model, tokenizer, gen, **kw):
    prompts = ["Hello there", "A much longer prompt about the weather in the spring"]
    return R.rollout(tiny_model, tokenizer, prompts, group_size=3, max_new_tokens=8,
                     eos_ids=[tokenizer.eos_token_id], generator=gen, **kw)


def test_rollout_shapes_groups_and_trimming(tiny_model, tokenizer, gen):
    ro = _sampled(tiny_model, tokenizer, gen)
    assert ro.completion_ids.shape[0] == 6 and len(ro.texts) == 6
    assert ro.completion_ids.shape[1] == int(ro.lengths.max())  # trimmed to the longest
    assert torch.equal(ro.prompt_ids[0], ro.prompt_ids[2]) and not torch.equal(ro.prompt_ids[0], ro.prompt_ids[3])
    assert (ro.logprobs[ro.completion_mask == 0] == 0).all()
    assert (ro.logprobs[ro.completion_mask == 1] < 0).all()


def test_sampled_logprobs_equal_the_training_forward_at_any_temperature(tiny_model, tokenizer, gen):
    for temperature in (1.0, 0.7):
        ro = _sampled(tiny_model, tokenizer, gen, temperature=temperature)
        with torch.no_grad():
            lp, _ = R.completion_logprobs(tiny_model, ro.prompt_ids, ro.prompt_mask, ro.completion_ids,
                                          ro.completion_mask, temperature=temperature)
        diff = ((lp - ro.logprobs) * ro.completion_mask).abs().max()
        assert diff < 1e-4, (temperature, diff)
        # and the temperature really matters: scoring at T=1 differs when sampled at 0.7
        if temperature != 1.0:
            with torch.no_grad():
                lp1, _ = R.completion_logprobs(tiny_model, ro.prompt_ids, ro.prompt_mask,
                                               ro.completion_ids, ro.completion_mask)
            assert ((lp1 - ro.logprobs) * ro.completion_mask).abs().max() > 1e-2


def test_left_padding_does_not_change_logprobs(tiny_model, tokenizer, gen):
    ro = _sampled(tiny_model, tokenizer, gen)
    for row in (0, 3):  # the short prompt (padded) and the long one
        text = tokenizer.decode(ro.prompt_ids[row][ro.prompt_mask[row].bool()])
        ids, mask = R.tokenize_prompts(tokenizer, [text], "cpu")
        with torch.no_grad():
            alone, _ = R.completion_logprobs(tiny_model, ids, mask, ro.completion_ids[row:row + 1],
                                             ro.completion_mask[row:row + 1])
            batched, _ = R.completion_logprobs(tiny_model, ro.prompt_ids, ro.prompt_mask,
                                               ro.completion_ids, ro.completion_mask)
        m = ro.completion_mask[row]
        assert ((alone[0] - batched[row]) * m).abs().max() < 1e-4


def test_sampling_is_reproducible_and_greedy_is_deterministic(tiny_model, tokenizer):
    a = _sampled(tiny_model, tokenizer, torch.Generator().manual_seed(1))
    b = _sampled(tiny_model, tokenizer, torch.Generator().manual_seed(1))
    assert a.texts == b.texts
    g = _sampled(tiny_model, tokenizer, torch.Generator().manual_seed(2), greedy=True)
    assert g.texts[0] == g.texts[1] == g.texts[2]  # a group of greedy completions is identical


def test_entropy_returned_with_logprobs(tiny_model, tokenizer, gen):
    ro = _sampled(tiny_model, tokenizer, gen)
    _, ent = R.completion_logprobs(tiny_model, ro.prompt_ids, ro.prompt_mask, ro.completion_ids,
                                   ro.completion_mask, with_entropy=True)
    vocab = tiny_model.config.vocab_size
    assert ent.shape == ro.completion_ids.shape
    assert (ent > 0).all() and (ent <= torch.log(torch.tensor(float(vocab))) + 1e-4).all()
    assert token_entropy(torch.zeros(1, 1, 4)).item() > 1.38


def test_shared_prompt_forward_matches_the_full_forward_in_value_and_gradient(tiny_model, tokenizer):
    # prompts of different lengths (so left padding is exercised), G = 3
    ro = R.rollout(tiny_model, tokenizer, ["Hi", "A much longer prompt about the weather in the spring"],
                   group_size=3, max_new_tokens=6, eos_ids=[tokenizer.eos_token_id],
                   generator=torch.Generator().manual_seed(3))
    weights = torch.randn(ro.completion_ids.shape, generator=torch.Generator().manual_seed(4))
    results = []
    for G in (1, 3):
        tiny_model.zero_grad()
        lp, ent = R.completion_logprobs(tiny_model, ro.prompt_ids, ro.prompt_mask, ro.completion_ids,
                                        ro.completion_mask, with_entropy=True, entropy_grad=True,
                                        group_size=G)
        ((lp * weights + ent) * ro.completion_mask).sum().backward()
        grad = torch.cat([p.grad.flatten() for p in tiny_model.parameters()])
        results.append((lp.detach() * ro.completion_mask, grad))
    (lp_full, g_full), (lp_shared, g_shared) = results
    assert (lp_full - lp_shared).abs().max() < 1e-5
    rel = (g_full - g_shared).norm() / g_full.norm()
    assert rel < 1e-4, rel
    tiny_model.zero_grad()
