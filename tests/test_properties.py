"""Property-based tests (hypothesis) for the advantage and loss functions: for any finite
rewards and log-probabilities the outputs are finite, and the invariances the math promises
hold. (The rewards' own fuzzing over arbitrary Unicode is in test_rewards.py.)"""
import math

import torch
from hypothesis import given, settings, strategies as st

from course_utils import losses

finite = st.floats(min_value=-1e3, max_value=1e3, allow_nan=False, allow_infinity=False)
SCALES = [("group", "group"), ("group", "none"), ("batch", "batch"), ("group", "batch")]


@st.composite
def grouped_rewards(draw):
    G = draw(st.integers(2, 8))
    n_groups = draw(st.integers(1, 5))
    values = draw(st.lists(finite, min_size=G * n_groups, max_size=G * n_groups))
    # equal rewards inside a group are the interesting edge case: make them common
    if draw(st.booleans()):
        k = draw(st.integers(0, n_groups - 1))
        values[k * G:(k + 1) * G] = [values[k * G]] * G
    return torch.tensor(values, dtype=torch.float64), G


@settings(max_examples=200, deadline=None)
@given(grouped_rewards())
def test_advantages_are_finite_and_centred(data):
    rewards, G = data
    for center, scale in SCALES:
        adv, zero_std = losses.group_advantages(rewards, G, center, scale)
        assert torch.isfinite(adv).all()
        if center == "group":
            assert torch.allclose(adv.view(-1, G).sum(-1), torch.zeros(len(rewards) // G, dtype=adv.dtype),
                                  atol=1e-6 * (1 + float(rewards.abs().max())))
    r = rewards.view(-1, G)
    constant = (r == r[:, :1]).all(-1)
    adv, zero_std = losses.group_advantages(rewards, G)
    assert zero_std == int(constant.sum())
    assert (adv.view(-1, G)[constant] == 0).all()       # no signal from an all-equal group


@settings(max_examples=200, deadline=None)
@given(grouped_rewards(), st.lists(finite, min_size=5, max_size=5))
def test_adding_a_constant_to_a_group_changes_nothing(data, shifts):
    rewards, G = data
    n_groups = len(rewards) // G
    shift = torch.tensor(shifts[:n_groups], dtype=rewards.dtype).repeat_interleave(G)
    for scale in ("group", "none"):
        a, _ = losses.group_advantages(rewards, G, "group", scale)
        b, _ = losses.group_advantages(rewards + shift, G, "group", scale)
        assert torch.allclose(a, b, atol=1e-7 * (1 + float((rewards + shift).abs().max()))), scale


@settings(max_examples=200, deadline=None)
@given(grouped_rewards(), st.floats(min_value=1e-2, max_value=1e2))
def test_scaling_rewards_scales_dr_grpo_and_bounds_grpo(data, a):
    rewards, G = data
    dr, _ = losses.group_advantages(rewards, G, "group", "none")
    dr_scaled, _ = losses.group_advantages(a * rewards, G, "group", "none")
    assert torch.allclose(dr_scaled, a * dr, atol=1e-9 * (1 + a * float(rewards.abs().max())))
    # a standardized group member is at most (G - 1) / sqrt(G) standard deviations from the mean
    adv, _ = losses.group_advantages(rewards, G)
    assert float(adv.abs().max()) <= (G - 1) / math.sqrt(G) + 1e-9


@settings(max_examples=100, deadline=None)
@given(grouped_rewards(), st.randoms(use_true_random=False))
def test_permuting_a_group_permutes_its_advantages(data, rnd):
    rewards, G = data
    perm = torch.cat([g * G + torch.tensor(rnd.sample(range(G), G)) for g in range(len(rewards) // G)])
    a, _ = losses.group_advantages(rewards, G)
    b, _ = losses.group_advantages(rewards[perm], G)
    assert torch.allclose(a[perm], b)


@st.composite
def loss_inputs(draw):
    N, T = draw(st.integers(1, 6)), draw(st.integers(1, 8))
    lengths = draw(st.lists(st.integers(1, T), min_size=N, max_size=N))
    mask = (torch.arange(T)[None] < torch.tensor(lengths)[:, None]).float()
    logp = -torch.tensor(draw(st.lists(st.floats(0, 30), min_size=N * T, max_size=N * T))).view(N, T)
    old = logp + torch.tensor(draw(st.lists(st.floats(-3, 3), min_size=N * T, max_size=N * T))).view(N, T)
    adv = torch.tensor(draw(st.lists(st.floats(-5, 5), min_size=N, max_size=N)))
    return logp.double(), old.double(), adv.double(), mask.double()


@settings(max_examples=150, deadline=None)
@given(loss_inputs(), st.sampled_from(["grpo", "bnpo", "dapo", "dr_grpo"]))
def test_loss_is_finite_and_ignores_padding(inputs, loss_type):
    logp, old, adv, mask = inputs
    kwargs = dict(loss_type=loss_type, ref_logprobs=old - 0.5, beta=0.04,
                  entropy=torch.rand_like(logp), entropy_weight=0.01,
                  max_completion_length=logp.shape[1])
    loss, stats = losses.grpo_loss(logp, old, adv, mask, **kwargs)
    assert torch.isfinite(loss) and all(math.isfinite(v) for v in stats.values())
    junk = torch.where(mask.bool(), logp, torch.full_like(logp, -1e4))   # padding holds garbage
    loss_junk, _ = losses.grpo_loss(junk, torch.where(mask.bool(), old, 7.0), adv, mask,
                                    **{**kwargs, "ref_logprobs": torch.where(mask.bool(), old - 0.5, 3.0)})
    assert torch.allclose(loss, loss_junk)


@settings(max_examples=150, deadline=None)
@given(loss_inputs(), st.sampled_from(["grpo", "dapo"]))
def test_on_policy_gradient_is_advantage_over_the_normalizer(inputs, loss_type):
    logp, _, adv, mask = inputs
    logp = logp.clone().requires_grad_(True)
    loss, _ = losses.grpo_loss(logp, logp.detach(), adv, mask, loss_type=loss_type)
    loss.backward()
    if loss_type == "grpo":   # 1/N sum_i 1/|o_i| sum_t: each token gets -A_i / (N |o_i|)
        expected = -adv[:, None] * mask / (mask.shape[0] * mask.sum(-1, keepdim=True))
    else:                     # sum_it / sum_i |o_i|: each token gets -A_i / (total tokens)
        expected = -adv[:, None] * mask / mask.sum()
    assert torch.allclose(logp.grad, expected, atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(st.lists(finite, min_size=2, max_size=64), st.sampled_from(["none", "constant", "inverse_variance"]))
def test_entropy_weight_is_finite_and_capped(values, mode):
    w = losses.entropy_weight(torch.tensor(values), mode, 1e-3, 0.1)
    assert math.isfinite(w) and 0 <= w <= 0.1


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-50, 0), min_size=1, max_size=32), st.lists(st.floats(-50, 0), min_size=32, max_size=32))
def test_k3_is_finite_and_non_negative(logp, ref):
    a, b = torch.tensor(logp, dtype=torch.float64), torch.tensor(ref[:len(logp)], dtype=torch.float64)
    kl = losses.k3_kl(a, b)
    assert torch.isfinite(kl).all() and (kl >= 0).all()
