"""The checkers of the language-model exercises (issue 15) accept correct answers written in
different ways and reject each plausible wrong answer with the right diagnosis."""
import pytest
import torch

from course_utils import losses
from course_utils.exercises import ExerciseError
from course_utils.lm_exercises import _batch, _model
from course_utils.lm_exercises import (check_completion_logprobs, check_grpo_backward,
                                       check_sample_group)
from course_utils.rollout import completion_logprobs as library_logprobs
from course_utils.rollout import completion_mask, sample


# --- exercise 1: completion log-probs ------------------------------------------------------

def logprobs_sliced(model, prompt_ids, prompt_mask, completion_ids, completion_mask, temperature,
                    *, shift=0, tempered="divide", masked=True, positions=True, attention=True,
                    log=True, prompt_too=False, detach=False):
    """A correct answer, and through its options the wrong ones."""
    ids = torch.cat([prompt_ids, completion_ids], -1)
    mask = torch.cat([prompt_mask, completion_mask], -1)
    kwargs = {}
    if attention:
        kwargs["attention_mask"] = mask
    if positions:
        kwargs["position_ids"] = (mask.cumsum(-1) - 1).clamp(min=0)
    logits = model(input_ids=ids, **kwargs).logits.float()
    P, T = prompt_ids.shape[1], completion_ids.shape[1]
    if prompt_too:
        logits, targets, m = logits[:, :-1], ids[:, 1:], mask[:, 1:]
    else:
        logits, targets, m = logits[:, P - 1 + shift:P + T - 1 + shift], completion_ids, completion_mask
    logits = {"divide": logits / temperature, "none": logits, "multiply": logits * temperature}[tempered]
    values = torch.log_softmax(logits, -1) if log else torch.softmax(logits, -1)
    out = values.gather(-1, targets.unsqueeze(-1)).squeeze(-1)
    out = out * m if masked else out
    return out.detach() if detach else out


def logprobs_logsumexp(model, prompt_ids, prompt_mask, completion_ids, completion_mask, temperature):
    """Correct, written differently: only the positions needed, gather minus logsumexp."""
    T = completion_ids.shape[1]
    ids = torch.cat([prompt_ids, completion_ids], 1)
    mask = torch.cat([prompt_mask, completion_mask], 1)
    position_ids = torch.clamp(torch.cumsum(mask, 1) - 1, min=0)
    logits = model(input_ids=ids, attention_mask=mask, position_ids=position_ids,
                   logits_to_keep=T + 1).logits[:, :-1] / temperature
    picked = logits.gather(2, completion_ids[..., None])[..., 0] - logits.logsumexp(2)
    return torch.where(completion_mask.bool(), picked, torch.zeros_like(picked))


def logprobs_library(model, prompt_ids, prompt_mask, completion_ids, completion_mask, temperature):
    return library_logprobs(model, prompt_ids, prompt_mask, completion_ids, completion_mask,
                            temperature=temperature)[0] * completion_mask


@pytest.mark.parametrize("answer", [logprobs_sliced, logprobs_logsumexp, logprobs_library])
def test_completion_logprobs_accepts_correct_answers(answer):
    check_completion_logprobs(answer)


def test_position_ids_are_caught_on_the_absolute_position_model():
    """Without position ids a rotary model (Qwen2) gives the same logits, a GPT-2 does not: the
    checker's GPT-2 batch names the mistake."""
    with pytest.raises(ExerciseError, match="position ids ignore the left padding"):
        check_completion_logprobs(lambda *a: logprobs_sliced(*a, positions=False))
    qwen2 = _model(seed=0, sharpen=8.0)           # the checker's first, rotary batch
    g = torch.Generator().manual_seed(0)
    batch = _batch(g, 64, 3, 5, 4, 2)
    same = torch.allclose(logprobs_sliced(qwen2, *batch, 1.0), logprobs_sliced(qwen2, *batch, 1.0, positions=False), atol=1e-4)
    assert same   # why the GPT-2 batch is needed: on Qwen2 the mistake is invisible


def _mutating(model, prompt_ids, prompt_mask, completion_ids, completion_mask, temperature):
    prompt_ids[prompt_mask == 0] = 0   # "clean" the padding in place
    return logprobs_sliced(model, prompt_ids, prompt_mask, completion_ids, completion_mask, temperature)


WRONG_LOGPROBS = [
    (dict(shift=1), "off by one"),
    (dict(tempered="none"), "temperature is missing"),
    (dict(tempered="multiply"), "multiplies"),
    (dict(masked=False), "padding positions are not zeroed"),
    (dict(log=False), "probabilities, not log-probabilities"),
    (dict(positions=False, attention=False), "attention mask is missing"),
    (dict(prompt_too=True), "covers the prompt positions"),
    (dict(detach=True), "carry no gradient"),
]


@pytest.mark.parametrize("options, diagnosis", WRONG_LOGPROBS, ids=[d for _, d in WRONG_LOGPROBS])
def test_completion_logprobs_names_each_mistake(options, diagnosis):
    with pytest.raises(ExerciseError, match=diagnosis):
        check_completion_logprobs(lambda *a: logprobs_sliced(*a, **options))


def test_completion_logprobs_refuses_an_answer_that_changes_its_inputs():
    with pytest.raises(ExerciseError, match="changed its input `prompt_ids` in place"):
        check_completion_logprobs(_mutating)


# --- exercise 2: sampling a group ------------------------------------------------------------

def sample_loop(model, prompt_ids, G, max_new_tokens, eos_id, temperature, generator, *,
                grad=False, cache=True, mask_rule="first eos", score_temperature=True,
                sample_temperature=True, detach=False, use_generator=True, pad_after_eos=True,
                early_stop=True, top_p=None):
    """A correct answer (a cache per row), and through its options the wrong ones."""
    generator = generator if use_generator else None
    with torch.set_grad_enabled(grad or detach):
        ids = prompt_ids.expand(G, -1)
        out = model(input_ids=ids, use_cache=cache)
        logits = out.logits[:, -1].float()
        done = torch.zeros(G, dtype=torch.bool)
        tokens, logps = [], []
        for t in range(max_new_tokens):
            scaled = logits / temperature
            draw = torch.softmax(scaled if sample_temperature else logits, -1)
            if top_p is not None:   # keep the smallest set of tokens holding top_p of the mass
                sorted_p, order = draw.sort(-1, descending=True)
                outside = sorted_p.cumsum(-1) - sorted_p >= top_p
                draw = draw.scatter(-1, order, sorted_p.masked_fill(outside, 0.0))
            token = torch.multinomial(draw, 1, generator=generator).squeeze(-1)
            if pad_after_eos:
                token = torch.where(done, torch.full_like(token, eos_id), token)
            logp = torch.log_softmax(scaled if score_temperature else logits, -1)
            chosen = logp.gather(-1, token[:, None]).squeeze(-1)
            logps.append(torch.where(done, torch.zeros_like(chosen), chosen))
            tokens.append(token)
            done = done | (token == eos_id)
            if done.all() and early_stop:
                break
            if cache:
                out = model(input_ids=token[:, None], past_key_values=out.past_key_values,
                            use_cache=True)
            else:   # the whole sequence again, every step
                ids = torch.cat([prompt_ids.expand(G, -1), torch.stack(tokens, 1)], 1)
                out = model(input_ids=ids)
            logits = out.logits[:, -1].float()
        ids, logps = torch.stack(tokens, 1), torch.stack(logps, 1)
        is_eos = (ids == eos_id).long()
        before = is_eos.cumsum(1) - is_eos            # EOS tokens strictly before t
        mask = {"first eos": (before == 0).long(), "not pad": 1 - is_eos,
                "exclude eos": ((before == 0) & (is_eos == 0)).long(),
                "all": torch.ones_like(ids)}[mask_rule]
        logps = logps * mask if mask_rule == "first eos" else logps
        if detach:   # built the graph of every step, then threw it away
            ids, mask, logps = ids.detach(), mask.detach(), logps.detach()
        return ids, mask, logps


def sample_with_library(model, prompt_ids, G, max_new_tokens, eos_id, temperature, generator):
    """Correct, written differently: one prefill shared by the G rows (the library's sampler)."""
    ids, logps = sample(model, prompt_ids, torch.ones_like(prompt_ids), group_size=G,
                        max_new_tokens=max_new_tokens, eos_ids=[eos_id], pad_id=eos_id,
                        temperature=temperature, generator=generator)
    mask = completion_mask(ids, [eos_id])
    return ids, mask, logps * mask


@pytest.mark.parametrize("answer", [sample_loop, sample_with_library])
def test_sample_group_accepts_correct_answers(answer):
    check_sample_group(answer)


WRONG_SAMPLERS = [
    (dict(grad=True), "run the loop under torch.no_grad"),
    (dict(mask_rule="not pad"), "drops the real EOS"),
    (dict(mask_rule="exclude eos"), "drops the real EOS"),   # the same mask when pad == EOS
    (dict(mask_rule="all"), "1 everywhere"),
    (dict(score_temperature=False), "log-probs are of the untempered distribution"),
    (dict(sample_temperature=False), "sample from the tempered distribution"),
    (dict(cache=False), "key/value cache"),
    (dict(detach=True), "run the loop under torch.no_grad"),          # grad on, outputs detached
    (dict(use_generator=False), "generators seeded alike"),
    (dict(pad_after_eos=False), "other than EOS after its first EOS"),
    (dict(early_stop=False), "stop the loop once every row"),
    (dict(top_p=0.95), "no top-k or top-p cut"),
]


@pytest.mark.parametrize("options, diagnosis", WRONG_SAMPLERS, ids=[d for _, d in WRONG_SAMPLERS])
def test_sample_group_names_each_mistake(options, diagnosis):
    with pytest.raises(ExerciseError, match=diagnosis):
        check_sample_group(lambda *a: sample_loop(*a, **options))


# --- exercise 3: the micro-batched backward --------------------------------------------------

def backward_by_hand(model, prompt_ids, prompt_mask, completion_ids, completion_mask, advantages,
                     temperature, micro_rows, loss_type, *, normalize="global", zero_each=False,
                     count_prompt=False):
    """A correct answer, and through its options the wrong ones."""
    N = completion_ids.shape[0]
    total_tokens = completion_mask.sum() + (prompt_mask.sum() if count_prompt else 0)
    n_micro, total = N // micro_rows, 0.0
    for start in range(0, N, micro_rows):
        rows = slice(start, start + micro_rows)
        if zero_each:
            model.zero_grad()
        lp = logprobs_sliced(model, prompt_ids[rows], prompt_mask[rows], completion_ids[rows],
                             completion_mask[rows], temperature)
        per_token = -torch.exp(lp - lp.detach()) * advantages[rows]
        m = completion_mask[rows].float()
        if loss_type == "dapo":
            tokens = total_tokens if normalize == "global" else m.sum()
            loss = (per_token * m).sum() / tokens
        else:
            per_sequence = (per_token * m).sum(-1) / m.sum(-1).clamp(min=1)
            loss = per_sequence.sum() / (N if normalize == "global" else micro_rows)
        if normalize == "averaged":
            loss = loss / n_micro
        loss.backward()
        total += loss.item()
    return total


def backward_with_library(model, prompt_ids, prompt_mask, completion_ids, completion_mask,
                          advantages, temperature, micro_rows, loss_type):
    """Correct, written differently: the library's loss with the whole batch's counts."""
    N, T = completion_ids.shape
    loss_sum = torch.zeros(())
    for start in range(0, N, micro_rows):
        rows = slice(start, start + micro_rows)
        lp = logprobs_logsumexp(model, prompt_ids[rows], prompt_mask[rows], completion_ids[rows],
                                completion_mask[rows], temperature)
        loss, _ = losses.grpo_loss(lp, lp.detach(), advantages[rows], completion_mask[rows],
                                   loss_type=loss_type, total_sequences=N,
                                   total_tokens=completion_mask.sum(), max_completion_length=T)
        loss.backward()
        loss_sum = loss_sum + loss.detach()
    return loss_sum


@pytest.mark.parametrize("answer", [backward_by_hand, backward_with_library])
def test_grpo_backward_accepts_correct_answers(answer):
    check_grpo_backward(answer)


WRONG_BACKWARDS = [
    (dict(normalize="averaged"), "losses averaged"),
    (dict(normalize="summed"), "losses summed"),
    (dict(zero_each=True), "zeroed between micro-batches"),
    (dict(count_prompt=True), "includes the prompt tokens"),
]


@pytest.mark.parametrize("options, diagnosis", WRONG_BACKWARDS, ids=[d for _, d in WRONG_BACKWARDS])
def test_grpo_backward_names_each_mistake(options, diagnosis):
    with pytest.raises(ExerciseError, match=diagnosis):
        check_grpo_backward(lambda *a: backward_by_hand(*a, **options))


def test_grpo_backward_refuses_no_backward_and_a_wrong_returned_loss():
    def no_backward(*args):
        return 0.0

    with pytest.raises(ExerciseError, match="no gradient reached the model"):
        check_grpo_backward(no_backward)
    with pytest.raises(ExerciseError, match="return the full-batch loss"):
        check_grpo_backward(lambda *a: backward_by_hand(*a) * 2)


def test_sample_group_and_grpo_backward_refuse_answers_that_change_their_inputs():
    def centring_in_place(model, prompt_ids, prompt_mask, completion_ids, completion_mask,
                          advantages, *rest):
        advantages -= advantages.mean()
        return backward_by_hand(model, prompt_ids, prompt_mask, completion_ids, completion_mask,
                                advantages, *rest)

    def padding_in_place(model, prompt_ids, *rest):
        prompt_ids[:, 0] = 0
        return sample_loop(model, prompt_ids, *rest)

    with pytest.raises(ExerciseError, match="changed its input `advantages` in place"):
        check_grpo_backward(centring_in_place)
    with pytest.raises(ExerciseError, match="changed its input `prompt_ids` in place"):
        check_sample_group(padding_in_place)


# --- exercise 3: answers that get the gradient right the wrong way (issue 25) ------------------

def _full_batch_loss(model, prompt_ids, prompt_mask, completion_ids, completion_mask, advantages,
                     temperature, loss_type, rows=slice(None)):
    lp = logprobs_sliced(model, prompt_ids[rows], prompt_mask[rows], completion_ids[rows],
                         completion_mask[rows], temperature)
    loss, _ = losses.grpo_loss(lp, lp.detach(), advantages[rows], completion_mask[rows],
                               loss_type=loss_type, total_sequences=completion_ids.shape[0],
                               total_tokens=completion_mask.sum(),
                               max_completion_length=completion_ids.shape[1])
    return loss


def one_full_batch_backward(model, prompt_ids, prompt_mask, completion_ids, completion_mask,
                            advantages, temperature, micro_rows, loss_type):
    """Right gradient, no micro-batching at all: micro_rows is ignored."""
    loss = _full_batch_loss(model, prompt_ids, prompt_mask, completion_ids, completion_mask,
                            advantages, temperature, loss_type)
    loss.backward()
    return loss.item()


def one_forward_then_sliced_backwards(model, prompt_ids, prompt_mask, completion_ids,
                                      completion_mask, advantages, temperature, micro_rows, loss_type):
    """One forward over every row, then a backward per slice of its loss (retain_graph)."""
    N = completion_ids.shape[0]
    lp = logprobs_sliced(model, prompt_ids, prompt_mask, completion_ids, completion_mask, temperature)
    total = 0.0
    for start in range(0, N, micro_rows):
        rows = slice(start, start + micro_rows)
        loss, _ = losses.grpo_loss(lp[rows], lp[rows].detach(), advantages[rows], completion_mask[rows],
                                   loss_type=loss_type, total_sequences=N,
                                   total_tokens=completion_mask.sum(),
                                   max_completion_length=completion_ids.shape[1])
        loss.backward(retain_graph=True)
        total += loss.item()
    return total


def summed_then_one_backward(model, prompt_ids, prompt_mask, completion_ids, completion_mask,
                             advantages, temperature, micro_rows, loss_type):
    """Micro-batched forwards, but the losses added up and backpropagated once."""
    total = 0
    for start in range(0, completion_ids.shape[0], micro_rows):
        total = total + _full_batch_loss(model, prompt_ids, prompt_mask, completion_ids,
                                         completion_mask, advantages, temperature, loss_type,
                                         slice(start, start + micro_rows))
    total.backward()
    return total.item()


def zeroed_first(model, *args):
    """Correct, except that it clears .grad before starting."""
    model.zero_grad()
    return backward_by_hand(model, *args)


HIDDEN_BACKWARDS = [
    (one_full_batch_backward, "rows in one forward"),
    (one_forward_then_sliced_backwards, "rows in one forward"),
    (summed_then_one_backward, "backward pass\\(es\\) for"),
    (zeroed_first, "zeroed before the first micro-batch"),
]


@pytest.mark.parametrize("answer, diagnosis", HIDDEN_BACKWARDS, ids=[d for _, d in HIDDEN_BACKWARDS])
def test_grpo_backward_refuses_a_right_gradient_computed_without_micro_batches(answer, diagnosis):
    with pytest.raises(ExerciseError, match=diagnosis):
        check_grpo_backward(answer)
