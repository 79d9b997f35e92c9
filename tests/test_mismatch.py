"""The training-inference mismatch (lesson 4, section 6): the library's exact measurements against
hand computations, and exercise 4.5's checker (TRL's importance weights): correct variants
accepted, each plausible mistake named."""
import math

import pytest
import torch

from course_utils import mismatch, trust
from course_utils.exercises import ExerciseError
from course_utils.trust_exercises import check_importance_weights

D = torch.float64
POLICY = trust.SequencePolicy(T=3, V=4)


def _theta(seed, scale=1.5):
    return scale * torch.randn(POLICY.n_params, generator=torch.Generator().manual_seed(seed), dtype=D)


def test_on_policy_the_one_sample_gradient_is_unbiased():
    theta, reward = _theta(0), torch.rand(64, generator=torch.Generator().manual_seed(1), dtype=D)
    mean, variance = mismatch.gradient_moments(POLICY, theta, POLICY.token_log_probs(theta), reward)
    assert torch.allclose(mean, trust.exact_gradient(POLICY.log_probs, theta, reward), atol=1e-12)
    assert variance > 0


def test_the_full_sequence_weight_removes_a_stale_samplers_bias_exactly():
    theta, reward = _theta(0), torch.rand(64, generator=torch.Generator().manual_seed(1), dtype=D)
    stale = theta + 0.5 * torch.randn(POLICY.n_params, generator=torch.Generator().manual_seed(2), dtype=D)
    lp, lq = POLICY.token_log_probs(theta), POLICY.token_log_probs(stale)
    w = mismatch.importance_weights(lp, lq, torch.ones_like(lp), "sequence_truncate", math.inf)
    exact = trust.exact_gradient(POLICY.log_probs, theta, reward)
    assert torch.allclose(mismatch.gradient_moments(POLICY, theta, lq, reward, w)[0], exact, atol=1e-12)
    assert not torch.allclose(mismatch.gradient_moments(POLICY, theta, lq, reward)[0], exact, atol=1e-3)


def test_top_k_keeps_k_tokens_per_row_renormalized_and_scoring_under_it_gives_its_own_gradient():
    theta, reward = _theta(3), torch.rand(64, generator=torch.Generator().manual_seed(4), dtype=D)
    table = mismatch.truncated_table(theta, POLICY, 2)
    assert (torch.isfinite(table).sum(-1) == 2).all()
    assert torch.allclose(table.exp().sum(-1), torch.ones(3, 5, dtype=D))
    lq = mismatch.token_log_probs(table, POLICY)
    assert int((lq.sum(-1).exp() > 0).sum()) == 2 ** 3      # every token from its row's two
    J_q = lambda th: (mismatch.token_log_probs(mismatch.truncated_table(th, POLICY, 2), POLICY).sum(-1).exp() * reward).sum()  # noqa: E731
    t = theta.clone().requires_grad_(True)
    (grad_J_q,) = torch.autograd.grad(J_q(t), t)
    mean, _ = mismatch.gradient_moments(POLICY, theta, lq, reward,
                                        score_table=lambda th: mismatch.truncated_table(th, POLICY, 2))
    assert torch.allclose(mean, grad_J_q, atol=1e-12)


def test_importance_weights_by_hand():
    lp = torch.tensor([[-1.0, -2.0, -0.5]], dtype=D)
    lq = torch.tensor([[-1.5, -1.0, -9.0]], dtype=D)
    mask = torch.tensor([[1.0, 1.0, 0.0]], dtype=D)
    # token ratios e^0.5 = 1.65 and e^-1 = 0.37; the sequence ratio e^-0.5 = 0.61; padding 0
    token = mismatch.importance_weights(lp, lq, mask, "token_truncate", 1.5)
    assert torch.allclose(token, torch.tensor([[1.5, math.exp(-1), 0.0]], dtype=D))
    assert torch.allclose(mismatch.importance_weights(lp, lq, mask, "token_mask", 1.5),
                          torch.tensor([[0.0, math.exp(-1), 0.0]], dtype=D))
    sequence = mismatch.importance_weights(lp, lq, mask, "sequence_mask", 1.5)
    assert torch.allclose(sequence, torch.tensor([[math.exp(-0.5)] * 2 + [0.0]], dtype=D))
    with pytest.raises(ValueError, match="mode must be one of"):
        mismatch.importance_weights(lp, lq, mask, "sequence", 1.5)


def weights_by_hand(logp_train, logp_sampler, mask, mode, clip_max):
    """Correct, written differently: per-row loops, torch.minimum, a multiplied mask."""
    out = torch.zeros_like(mask)
    for i in range(mask.shape[0]):
        real = mask[i].bool()
        log_ratio = (logp_train[i] - logp_sampler[i]).detach()[real]
        ratio = log_ratio.sum().exp().expand(int(real.sum())) if mode.startswith("sequence") else log_ratio.exp()
        if mode.endswith("truncate"):
            ratio = torch.minimum(ratio, torch.tensor(clip_max, dtype=ratio.dtype))
        else:
            ratio = ratio * (ratio <= clip_max)
        out[i, real] = ratio
    return out


@pytest.mark.parametrize("answer", [mismatch.importance_weights, weights_by_hand])
def test_importance_weights_checker_accepts_correct_answers(answer):
    check_importance_weights(answer)


def _wrong(kind):
    def answer(lp, lq, mask, mode, clip_max):
        if kind == "in place":
            mask.mul_(1.0)
            lq.add_(0.0)
            lq[0, 0] = lq[0, 0] + 1.0
        a, b = (lq, lp) if kind == "inverted" else (lp, lq)
        log_ratio = (a - b) * (1.0 if kind == "padding in sum" else mask)
        if kind != "grad":
            log_ratio = log_ratio.detach()
        sequence = mode.startswith("sequence") != (kind == "level")
        if sequence:
            log_ratio = log_ratio.sum(-1, keepdim=True).expand_as(mask)
        ratio = torch.exp(log_ratio)
        cap = 3.0 if kind == "typed cap" else clip_max
        truncate = mode.endswith("truncate") != (kind == "truncate vs mask")
        if truncate:
            ratio = ratio.clamp(max=cap)
        else:
            # setting a masked ratio to the cap instead of 0 is truncation: named as such
            ratio = torch.where(ratio > cap, cap if kind == "mask to cap" else 0.0, ratio)
        return ratio if kind == "padding kept" else ratio * mask
    return answer


WRONG = [("inverted", "ratio is inverted"), ("truncate vs mask", "this is '"), ("level", "-level weight"),
         ("padding in sum", "padding is counted"), ("padding kept", "padding positions are not 0"),
         ("typed cap", "cap is typed in"), ("mask to cap", "this is '"), ("grad", "carry a gradient"),
         ("in place", "changed its input")]


@pytest.mark.parametrize("kind, diagnosis", WRONG, ids=[k for k, _ in WRONG])
def test_importance_weights_checker_names_each_mistake(kind, diagnosis):
    with pytest.raises(ExerciseError, match=diagnosis):
        check_importance_weights(_wrong(kind))


def test_the_fixture_with_no_mistake_is_accepted():
    check_importance_weights(_wrong("none"))


def weights_with_a_float32_cap(logp_train, logp_sampler, mask, mode, clip_max):
    """Correct: the cap as a float32 tensor (1.7 is 1.70000005 there), in log space for masks."""
    log_ratio = ((logp_train - logp_sampler) * mask).detach()
    if mode.startswith("sequence"):
        log_ratio = log_ratio.sum(-1, keepdim=True).expand_as(mask)
    ratio = log_ratio.exp()
    cap = torch.tensor(clip_max, dtype=torch.float32)
    if mode.endswith("truncate"):
        return torch.minimum(ratio, cap) * mask
    return torch.where(log_ratio > torch.log(cap.double()), 0.0, ratio) * mask


def weights_by_arithmetic(logp_train, logp_sampler, mask, mode, clip_max):
    """Wrong only without a cap: cap * (ratio > cap) is inf * 0 = NaN when clip_max is inf."""
    log_ratio = ((logp_train - logp_sampler) * mask).detach()
    if mode.startswith("sequence"):
        log_ratio = log_ratio.sum(-1, keepdim=True).expand_as(mask)
    ratio = log_ratio.exp()
    over = (ratio > clip_max).to(ratio.dtype)
    ratio = ratio * (1 - over) + clip_max * over if mode.endswith("truncate") else ratio * (1 - over)
    return ratio * mask


def test_a_float32_cap_is_accepted_and_nan_arithmetic_without_a_cap_is_named():
    torch.set_default_dtype(torch.float32)     # as in the lesson when the checker runs
    check_importance_weights(weights_with_a_float32_cap)
    with pytest.raises(ExerciseError, match=r"NaN or inf weights on .*clip_max inf"):
        check_importance_weights(weights_by_arithmetic)
