"""Sampling and scoring tokens: masks, log-probabilities, padding, prefix sharing. The tests
that sample or score run both kernels (``fast``: inverse-CDF sampling, the fused output layer)."""
import pytest
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


@pytest.mark.parametrize("fast", [False, True])
def test_sampled_logprobs_equal_the_training_forward_at_any_temperature(tiny_model, tokenizer, gen, fast):
    for temperature in (1.0, 0.7):
        ro = _sampled(tiny_model, tokenizer, gen, temperature=temperature, fast=fast)
        with torch.no_grad():
            lp, _ = R.completion_logprobs(tiny_model, ro.prompt_ids, ro.prompt_mask, ro.completion_ids,
                                          ro.completion_mask, temperature=temperature, fast=fast)
        diff = ((lp - ro.logprobs) * ro.completion_mask).abs().max()
        assert diff < 1e-4, (temperature, diff)
        # and the temperature really matters: scoring at T=1 differs when sampled at 0.7
        if temperature != 1.0:
            with torch.no_grad():
                lp1, _ = R.completion_logprobs(tiny_model, ro.prompt_ids, ro.prompt_mask,
                                               ro.completion_ids, ro.completion_mask, fast=fast)
            assert ((lp1 - ro.logprobs) * ro.completion_mask).abs().max() > 1e-2


@pytest.mark.parametrize("fast", [False, True])
def test_left_padding_does_not_change_logprobs(tiny_model, tokenizer, gen, fast):
    ro = _sampled(tiny_model, tokenizer, gen)
    for row in (0, 3):  # the short prompt (padded) and the long one
        text = tokenizer.decode(ro.prompt_ids[row][ro.prompt_mask[row].bool()])
        ids, mask = R.tokenize_prompts(tokenizer, [text], "cpu")
        with torch.no_grad():
            alone, _ = R.completion_logprobs(tiny_model, ids, mask, ro.completion_ids[row:row + 1],
                                             ro.completion_mask[row:row + 1], fast=fast)
            batched, _ = R.completion_logprobs(tiny_model, ro.prompt_ids, ro.prompt_mask,
                                               ro.completion_ids, ro.completion_mask, fast=fast)
        m = ro.completion_mask[row]
        assert ((alone[0] - batched[row]) * m).abs().max() < 1e-4


@pytest.mark.parametrize("fast", [False, True])
def test_sampling_is_reproducible_and_greedy_is_deterministic(tiny_model, tokenizer, fast):
    a = _sampled(tiny_model, tokenizer, torch.Generator().manual_seed(1), fast=fast)
    b = _sampled(tiny_model, tokenizer, torch.Generator().manual_seed(1), fast=fast)
    assert a.texts == b.texts
    g = _sampled(tiny_model, tokenizer, torch.Generator().manual_seed(2), greedy=True, fast=fast)
    assert g.texts[0] == g.texts[1] == g.texts[2]  # a group of greedy completions is identical


@pytest.mark.parametrize("fast", [False, True])
def test_entropy_returned_with_logprobs(tiny_model, tokenizer, gen, fast):
    ro = _sampled(tiny_model, tokenizer, gen)
    _, ent = R.completion_logprobs(tiny_model, ro.prompt_ids, ro.prompt_mask, ro.completion_ids,
                                   ro.completion_mask, with_entropy=True, fast=fast)
    vocab = tiny_model.config.vocab_size
    assert ent.shape == ro.completion_ids.shape
    assert (ent > 0).all() and (ent <= torch.log(torch.tensor(float(vocab))) + 1e-4).all()
    assert token_entropy(torch.zeros(1, 1, 4)).item() > 1.38


def _plain_logprobs(model, prompt_ids, prompt_mask, completion_ids, completion_mask):
    """The textbook computation, independent of the library's: one forward over every full
    sequence, logits at every position, log-softmax, pick the completion tokens."""
    ids = torch.cat([prompt_ids, completion_ids], -1)
    att = torch.cat([prompt_mask, completion_mask], -1)
    pos = (att.cumsum(-1) - 1).clamp(min=0)
    logits = model(input_ids=ids, attention_mask=att, position_ids=pos).logits
    P, T = prompt_ids.shape[1], completion_ids.shape[1]
    logp = torch.log_softmax(logits[:, P - 1:P + T - 1].float(), -1)
    return logp.gather(-1, completion_ids[..., None]).squeeze(-1) * completion_mask


@pytest.mark.parametrize("fast", [False, True])
def test_shared_prompt_and_chunked_forward_match_the_plain_forward_in_value_and_gradient(tiny_model, tokenizer, fast):
    # prompts of different lengths (so left padding is exercised), G = 3, and completions of
    # different lengths (so chunks are cut to different lengths)
    ro = R.rollout(tiny_model, tokenizer, ["Hi", "A much longer prompt about the weather in the spring"],
                   group_size=3, max_new_tokens=6, eos_ids=[tokenizer.eos_token_id],
                   generator=torch.Generator().manual_seed(3))
    lengths = torch.tensor([6, 1, 3, 6, 2, 4])[:, None]
    mask = (torch.arange(ro.completion_ids.shape[1])[None] < lengths).long() * ro.completion_mask
    assert len(set(mask.sum(-1).tolist())) > 3
    weights = torch.randn(ro.completion_ids.shape, generator=torch.Generator().manual_seed(4))

    def value_and_grad(fn):
        tiny_model.zero_grad()
        lp = fn()
        (lp * weights * mask).sum().backward()
        return lp.detach() * mask, torch.cat([p.grad.flatten() for p in tiny_model.parameters()])

    plain = value_and_grad(lambda: _plain_logprobs(tiny_model, ro.prompt_ids, ro.prompt_mask,
                                                   ro.completion_ids, mask))
    for G, chunk in [(1, 8), (1, 2), (3, 8), (3, 2), (3, 1)]:
        got = value_and_grad(lambda: R.completion_logprobs(
            tiny_model, ro.prompt_ids, ro.prompt_mask, ro.completion_ids, mask, group_size=G,
            rows_per_chunk=chunk, fast=fast)[0])
        assert (got[0] - plain[0]).abs().max() < 1e-5, (G, chunk)
        rel = (got[1] - plain[1]).norm() / plain[1].norm()
        assert rel < 1e-4, (G, chunk, rel)
    # and the entropy's gradient through the shared prompt
    ents = []
    for G in (1, 3):
        tiny_model.zero_grad()
        _, ent = R.completion_logprobs(tiny_model, ro.prompt_ids, ro.prompt_mask, ro.completion_ids,
                                       mask, with_entropy=True, entropy_grad=True, group_size=G,
                                       rows_per_chunk=2, fast=fast)
        (ent * mask).sum().backward()
        ents.append(torch.cat([p.grad.flatten() for p in tiny_model.parameters()]))
    assert (ents[0] - ents[1]).norm() / ents[0].norm() < 1e-4
    tiny_model.zero_grad()


@pytest.mark.parametrize("fast", [False, True])
def test_rows_that_stop_leave_the_decoding_batch_without_changing_the_others(tiny_model, tokenizer, fast):
    """Rows stop at different steps and are dropped from the batch and the cache. Greedy
    decoding must then give, row by row, what each prompt gives alone; sampled
    log-probabilities must still be the training forward's."""
    prompts = ["Hello there", "A much longer prompt about the weather in the spring", "Why"]
    free = R.rollout(tiny_model, tokenizer, prompts, group_size=1, max_new_tokens=10,
                     eos_ids=[tokenizer.eos_token_id], greedy=True).completion_ids
    # stop ids taken from the free-running greedy output, so the rows end early and at different
    # steps; plus a third of the vocabulary, so sampled rows stop at different steps too
    stop = sorted({int(free[0, 1]), int(free[2, 4])} | set(range(0, len(tokenizer), 3)))
    together = R.rollout(tiny_model, tokenizer, prompts, group_size=1, max_new_tokens=10,
                         eos_ids=stop, greedy=True)
    lengths = together.lengths.tolist()
    assert len(set(lengths)) > 1, lengths     # rows did stop at different steps
    for i, prompt in enumerate(prompts):
        alone = R.rollout(tiny_model, tokenizer, [prompt], group_size=1, max_new_tokens=10,
                          eos_ids=stop, greedy=True)
        n = int(alone.lengths[0])
        assert n == lengths[i] and torch.equal(alone.completion_ids[0, :n], together.completion_ids[i, :n])
    ro = R.rollout(tiny_model, tokenizer, prompts, group_size=4, max_new_tokens=10, eos_ids=stop,
                   generator=torch.Generator().manual_seed(5), fast=fast)
    assert len(set(ro.lengths.tolist())) > 2
    with torch.no_grad():
        lp, _ = R.completion_logprobs(tiny_model, ro.prompt_ids, ro.prompt_mask, ro.completion_ids,
                                      ro.completion_mask, group_size=4, fast=fast)
    assert ((lp - ro.logprobs) * ro.completion_mask).abs().max() < 1e-4
    assert (ro.logprobs[ro.completion_mask == 0] == 0).all()


def test_draw_samples_the_given_distribution_and_never_a_zero_probability_token():
    # unnormalised weights with zeros at both ends and in the middle, rows of different shapes
    g = torch.Generator().manual_seed(0)
    for weights in (torch.tensor([0.0, 1.0, 0.0, 3.0, 6.0, 0.0]), torch.tensor([0.0, 0.0, 2.0, 2.0])):
        n = 40_000
        tokens = R.draw(weights.expand(n, -1).contiguous(), g)
        counts = torch.bincount(tokens, minlength=len(weights)).double()
        assert (counts[weights == 0] == 0).all()
        p = weights.double() / weights.sum()
        # each frequency within 4.5 standard errors of its probability (a fail has odds ~1e-5)
        se = (p * (1 - p) / n).sqrt()
        assert ((counts / n - p).abs() <= 4.5 * se + 1e-12).all(), (counts / n, p)
    one_hot = torch.zeros(3, 7)
    one_hot[torch.arange(3), torch.tensor([0, 6, 3])] = 0.5   # a single possible token per row
    assert R.draw(one_hot, g).tolist() == [0, 6, 3]
    w = torch.rand(5, 9, generator=g)
    draws = [R.draw(w, torch.Generator().manual_seed(1)) for _ in range(2)]
    assert torch.equal(*draws)                                # the generator alone decides
