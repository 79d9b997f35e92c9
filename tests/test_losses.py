"""Every estimator and loss checked against numbers worked out by hand or by exact enumeration."""
import math

import pytest
import torch

from course_utils import losses

# ---------------------------------------------------------------- advantages, by hand


def test_group_advantages_hand_computed_with_an_all_equal_group():
    # group 1: [1, 0, 0, 1]: mean 0.5, Bessel std sqrt(1/3); group 2: all equal -> no signal
    rewards = torch.tensor([1.0, 0.0, 0.0, 1.0, 0.7, 0.7, 0.7, 0.7])
    adv, zero_std = losses.group_advantages(rewards, group_size=4)
    expected = 0.5 / (math.sqrt(1 / 3) + 1e-4)
    assert torch.allclose(adv[:4], torch.tensor([expected, -expected, -expected, expected]), atol=1e-6)
    assert torch.equal(adv[4:], torch.zeros(4))
    assert zero_std == 1


def test_batch_normalization_differs_from_group_normalization():
    # two prompts of different difficulty: per-group stats give each group mean-zero advantages,
    # whole-batch stats (the seed text) favour every completion of the easy prompt
    rewards = torch.tensor([1.0, 0.0, 1.0, 1.0])  # easy prompt 2 (both pass)
    adv_group, z = losses.group_advantages(rewards, 2)
    adv_batch, _ = losses.group_advantages(rewards, 2, center="batch", scale="batch")
    assert z == 1 and torch.allclose(adv_group[2:], torch.zeros(2))
    mean, std = 0.75, rewards.std().item()
    assert torch.allclose(adv_batch, (rewards - mean) / (std + 1e-4), atol=1e-6)
    assert (adv_batch[2:] > 0).all()


def test_batch_centring_with_a_per_group_scale_is_refused():
    # an all-equal group's batch-centred rewards over its std of 0 (+ eps) would be ~1e4
    with pytest.raises(ValueError, match="scale='batch'"):
        losses.group_advantages(torch.tensor([1.0, 0.0, 1.0, 1.0]), 2, center="batch", scale="group")


def test_dr_grpo_scale_none_only_centres():
    rewards = torch.tensor([3.0, 1.0, 2.0, 2.0])
    adv, _ = losses.group_advantages(rewards, 2, scale="none")
    assert torch.equal(adv, torch.tensor([1.0, -1.0, 0.0, 0.0]))


def test_group_advantages_rejects_ragged_groups():
    with pytest.raises(ValueError, match="multiple of group_size"):
        losses.group_advantages(torch.ones(5), 2)


# ---------------------------------------------------------------- baselines


def test_leave_one_out_baseline_by_hand():
    rewards = torch.tensor([1.0, 2.0, 6.0, 0.0, 0.0, 3.0])
    b = losses.leave_one_out_baseline(rewards, 3)
    assert torch.allclose(b, torch.tensor([4.0, 3.5, 1.5, 1.5, 1.5, 0.0]))


def test_running_mean_baseline_uses_only_past_batches():
    base = losses.RunningMeanBaseline(momentum=0.5)
    first = base(torch.tensor([2.0, 4.0]))
    assert torch.equal(first, torch.zeros(2))  # nothing seen yet: this batch is not used
    second = base(torch.tensor([10.0, 10.0]))
    assert torch.equal(second, torch.full((2,), 1.5))  # 0.5 * 0 + 0.5 * 3
    assert base.value == pytest.approx(0.5 * 1.5 + 0.5 * 10)


def test_batch_mean_baseline():
    assert torch.equal(losses.batch_mean_baseline(torch.tensor([1.0, 3.0])), torch.tensor([2.0, 2.0]))


# ---------------------------------------------------------------- REINFORCE


def test_terminal_reward_gives_every_token_the_same_return():
    mask = torch.tensor([[1, 1, 1, 1], [1, 1, 0, 0]])
    per_token = losses.terminal_rewards(torch.tensor([2.0, -1.0]), mask)
    assert torch.equal(per_token, torch.tensor([[0.0, 0, 0, 2], [0, -1, 0, 0]]))
    g = losses.returns_to_go(per_token) * mask
    assert torch.equal(g, torch.tensor([[2.0, 2, 2, 2], [-1, -1, 0, 0]]))
    g_disc = losses.returns_to_go(per_token, gamma=0.5)
    assert torch.allclose(g_disc[0], torch.tensor([0.25, 0.5, 1.0, 2.0]))


def test_returns_to_go_with_intermediate_rewards():
    g = losses.returns_to_go(torch.tensor([[1.0, 0.0, 2.0]]), gamma=0.9)
    assert torch.allclose(g, torch.tensor([[1 + 0.9 ** 2 * 2, 0.9 * 2, 2.0]]))


def _exact_bandit_gradient(theta, reward):
    p = torch.softmax(theta, 0)
    # dJ/dtheta_k = p_k (r_k - sum_j p_j r_j), from d p_j / d theta_k = p_j (1[j=k] - p_k)
    return p * (reward - (p * reward).sum())


@pytest.mark.parametrize("baseline", [None, "leave_one_out"])
def test_reinforce_matches_the_exact_gradient_within_sampling_error(baseline):
    torch.manual_seed(0)
    theta = torch.tensor([0.3, -0.2, 0.8, 0.0], requires_grad=True)
    reward = torch.tensor([1.0, 0.0, 2.0, -1.0])
    exact = _exact_bandit_gradient(theta.detach(), reward)
    n, group = 40000, 4
    actions = torch.multinomial(torch.softmax(theta.detach(), 0), n, replacement=True)
    r = reward[actions]
    if baseline == "leave_one_out":
        r = r - losses.leave_one_out_baseline(r, group)
    logp = torch.log_softmax(theta, 0)[actions].unsqueeze(-1)
    loss = losses.reinforce_loss(logp, r, torch.ones_like(logp))
    (grad,) = torch.autograd.grad(-loss, theta)
    # per-sample score-function terms give the standard error of the mean
    per_sample = torch.stack([torch.autograd.grad(torch.log_softmax(theta, 0)[a], theta)[0] * w
                              for a, w in zip(actions[:2000], r[:2000])])
    se = per_sample.std(0) / math.sqrt(n)
    assert ((grad - exact).abs() < 4 * se + 1e-3).all(), (grad, exact, se)


# ---------------------------------------------------------------- KL, entropy, clipping


def test_k3_is_non_negative_and_unbiased_for_the_exact_kl():
    torch.manual_seed(0)
    p = torch.tensor([0.5, 0.3, 0.15, 0.05])
    q = torch.tensor([0.25, 0.25, 0.25, 0.25])
    exact = (p * (p / q).log()).sum()  # KL(p || q), p the policy, q the reference
    samples = torch.multinomial(p, 200000, replacement=True)
    k3 = losses.k3_kl(p.log()[samples], q.log()[samples])
    assert (k3 >= 0).all()
    se = k3.std() / math.sqrt(len(samples))
    assert abs(k3.mean() - exact) < 4 * se
    assert losses.k3_kl(torch.tensor([-1.0]), torch.tensor([-1.0])).item() == 0.0


def test_token_entropy_of_uniform_and_one_hot():
    logits = torch.tensor([[[0.0, 0.0, 0.0, 0.0], [100.0, 0.0, 0.0, 0.0]]])
    h = losses.token_entropy(logits)
    assert torch.allclose(h, torch.tensor([[math.log(4), 0.0]]), atol=1e-5)


def test_clipped_surrogate_by_hand_with_asymmetric_clip():
    old = torch.zeros(1, 4)
    logp = torch.log(torch.tensor([[1.0, 1.5, 0.5, 1.25]]))  # ratios 1, 1.5, 0.5, 1.25
    adv = torch.tensor([1.0])
    per_token, clipped = losses.clipped_surrogate(logp, old, adv, eps_low=0.2, eps_high=0.28)
    assert torch.allclose(per_token, -torch.tensor([[1.0, 1.28, 0.5, 1.25]]))
    assert clipped.tolist() == [[False, True, False, False]]
    # negative advantage: the low side clips
    per_token, clipped = losses.clipped_surrogate(logp, old, -adv, eps_low=0.2, eps_high=0.28)
    assert torch.allclose(per_token, torch.tensor([[1.0, 1.5, 0.8, 1.25]]))
    assert clipped.tolist() == [[False, False, True, False]]


def test_clipped_tokens_get_no_gradient():
    logp = torch.log(torch.tensor([[1.5, 1.1]])).requires_grad_()
    per_token, _ = losses.clipped_surrogate(logp, torch.zeros(1, 2), torch.tensor([1.0]))
    per_token.sum().backward()
    assert logp.grad[0, 0] == 0 and logp.grad[0, 1] != 0


def test_entropy_weight_inverse_variance_is_capped():
    equal = torch.ones(8)
    assert losses.entropy_weight(equal, "inverse_variance", 1e-3, 0.1) == 0.1
    r = torch.tensor([0.0, 1.0, 0.0, 1.0])  # population variance 0.25
    assert losses.entropy_weight(r, "inverse_variance", 1e-3, 0.1) == pytest.approx(4e-3)
    assert losses.entropy_weight(r, "constant", 1e-3, 0.1) == 1e-3
    assert losses.entropy_weight(r, "none", 1e-3, 0.1) == 0.0


# ---------------------------------------------------------------- aggregation


PER_TOKEN = torch.tensor([[1.0, 2.0, 3.0, 9.0], [4.0, 9.0, 9.0, 9.0]])
MASK = torch.tensor([[1, 1, 1, 0], [1, 0, 0, 0]])


@pytest.mark.parametrize("loss_type, expected", [
    ("grpo", ((1 + 2 + 3) / 3 + 4 / 1) / 2),      # mean per sequence, then over sequences
    ("bnpo", (1 + 2 + 3 + 4) / 4),                 # every real token weighs the same
    ("dapo", (1 + 2 + 3 + 4) / 4),
    ("dr_grpo", (1 + 2 + 3 + 4) / (2 * 8)),        # constant: N x max_completion_length
])
def test_aggregation_variants_by_hand(loss_type, expected):
    got = losses.aggregate(PER_TOKEN, MASK, loss_type, max_completion_length=8)
    assert got.item() == pytest.approx(expected)


def test_bnpo_is_trls_mean_of_micro_batch_token_means():
    """TRL 1.16's "bnpo": each micro-batch divided by its own token count, then by the number of
    micro-batches. With unequal token counts that is not the batch's token mean ("dapo")."""
    parts = [losses.aggregate(PER_TOKEN[i:i + 1], MASK[i:i + 1], "bnpo", 8, total_sequences=2,
                              total_tokens=int(MASK.sum()), micro_batches=2) for i in range(2)]
    assert sum(parts).item() == pytest.approx(((1 + 2 + 3) / 3 + 4 / 1) / 2)
    dapo = losses.aggregate(PER_TOKEN, MASK, "dapo", 8)
    assert dapo.item() == pytest.approx((1 + 2 + 3 + 4) / 4) != pytest.approx(sum(parts).item())
    # one micro-batch: the two are the same
    assert losses.aggregate(PER_TOKEN, MASK, "bnpo", 8).item() == pytest.approx(dapo.item())


@pytest.mark.parametrize("loss_type", ["grpo", "dapo", "dr_grpo"])
def test_micro_batches_with_global_normalizers_sum_to_the_full_batch(loss_type):
    full = losses.aggregate(PER_TOKEN, MASK, loss_type, 8)
    parts = sum(losses.aggregate(PER_TOKEN[i:i + 1], MASK[i:i + 1], loss_type, 8,
                                 total_sequences=2, total_tokens=int(MASK.sum())) for i in range(2))
    assert parts.item() == pytest.approx(full.item())


def test_unknown_loss_type_is_refused():
    with pytest.raises(ValueError, match="loss_type"):
        losses.aggregate(PER_TOKEN, MASK, "mean")


def test_grpo_loss_on_policy_equals_reinforce_with_group_baseline():
    # one update per batch: rho = 1, so the gradient is REINFORCE with advantages as weights
    torch.manual_seed(0)
    logp = torch.randn(4, 3, requires_grad=True)
    mask = torch.tensor([[1, 1, 1], [1, 1, 0], [1, 0, 0], [1, 1, 1]])
    adv = torch.tensor([1.0, -1.0, 0.5, -0.5])
    loss, stats = losses.grpo_loss(logp, logp.detach(), adv, mask, loss_type="bnpo")
    (g1,) = torch.autograd.grad(loss, logp)
    ref = -(logp * adv[:, None] * mask).sum() / mask.sum()
    (g2,) = torch.autograd.grad(ref, logp)
    assert torch.allclose(g1, g2) and stats["clip_fraction"] == 0.0


def test_grpo_loss_kl_and_entropy_terms_by_hand():
    logp = torch.log(torch.tensor([[0.5, 0.25]]))
    ref = torch.log(torch.tensor([[0.25, 0.25]]))
    ent = torch.tensor([[1.0, 2.0]])
    mask = torch.ones(1, 2)
    loss, stats = losses.grpo_loss(logp, logp, torch.tensor([0.0]), mask, loss_type="grpo",
                                   ref_logprobs=ref, beta=0.1, entropy=ent, entropy_weight=0.01)
    kl0 = 0.5 - math.log(0.5) - 1  # ratio ref/pi = 0.5 on token 0, 1 on token 1
    assert stats["kl"] == pytest.approx(kl0 / 2)
    assert loss.item() == pytest.approx((0.1 * kl0 - 0.01 * 1.0 - 0.01 * 2.0) / 2)
    with pytest.raises(ValueError, match="ref_logprobs"):
        losses.grpo_loss(logp, logp, torch.tensor([0.0]), mask, beta=0.1)


@pytest.mark.parametrize("seed, shape, loss_type", [(0, (4, 3), "grpo"), (1, (6, 5), "bnpo"),
                                                     (2, (3, 7), "dr_grpo")])
def test_sampling_weights_scale_each_tokens_surrogate_and_nothing_else(seed, shape, loss_type):
    # On-policy (rho = 1) the weighted loss's gradient is REINFORCE with w_t A as each token's
    # weight; the KL and entropy terms are the trainer's own and are not weighted (TRL's order).
    g = torch.Generator().manual_seed(seed)
    n, T = shape
    logp = (torch.randn(n, T, generator=g) - 1).requires_grad_(True)
    ref, ent = torch.randn(n, T, generator=g) - 1, torch.rand(n, T, generator=g)
    mask = (torch.rand(n, T, generator=g) > 0.3).float()
    mask[:, 0] = 1
    adv = torch.randn(n, generator=g)
    w = torch.rand(n, T, generator=g) * 3
    w_before = w.clone()
    w_padded = torch.where(mask.bool(), w, float("inf"))   # padding must not matter, not even inf
    kw = dict(loss_type=loss_type, ref_logprobs=ref, beta=0.05, entropy=ent, entropy_weight=0.01,
              max_completion_length=T)
    loss, stats = losses.grpo_loss(logp, logp.detach(), adv, mask, sampling_weights=w_padded, **kw)
    (grad,) = torch.autograd.grad(loss, logp)
    by_hand = -w * adv[:, None] * torch.exp(logp - logp.detach()) + 0.05 * losses.k3_kl(logp, ref) - 0.01 * ent
    expected = losses.aggregate(by_hand, mask, loss_type, T)
    (grad_by_hand,) = torch.autograd.grad(expected, logp)
    assert torch.isfinite(loss) and loss.item() == pytest.approx(expected.item(), rel=1e-5, abs=1e-7)
    assert torch.allclose(grad, grad_by_hand, atol=1e-6)
    assert stats["is_weight_mean"] == pytest.approx(float((w * mask).sum() / mask.sum()), rel=1e-6)
    assert torch.equal(w, w_before)
    # weights of 1 are no correction: the same loss, bitwise
    plain, _ = losses.grpo_loss(logp, logp.detach(), adv, mask, **kw)
    ones, _ = losses.grpo_loss(logp, logp.detach(), adv, mask, sampling_weights=torch.ones(n, T), **kw)
    assert torch.equal(plain, ones)


def test_sampling_weights_off_policy_weight_the_clipped_surrogate_and_get_no_gradient():
    g = torch.Generator().manual_seed(3)
    logp = (torch.randn(5, 4, generator=g) - 1).requires_grad_(True)
    old = logp.detach() + 0.5 * torch.randn(5, 4, generator=g)   # ratios well away from 1: clipping acts
    mask, adv = torch.ones(5, 4), torch.randn(5, generator=g)
    w = (torch.rand(5, 4, generator=g) * 2).requires_grad_(True)
    loss, stats = losses.grpo_loss(logp, old, adv, mask, loss_type="bnpo", eps_low=0.1, eps_high=0.2,
                                   sampling_weights=w)
    loss.backward()
    surrogate, clipped = losses.clipped_surrogate(logp, old, adv, 0.1, 0.2)
    assert clipped.any() and stats["clip_fraction"] > 0
    by_hand = losses.aggregate(surrogate * w.detach(), mask, "bnpo")
    assert loss.item() == pytest.approx(by_hand.item(), rel=1e-6)
    assert w.grad is None   # the weights are constants of the step


def test_reward_aware_kl_by_hand():
    kl = losses.RewardAwareKL(beta=0.1, clip_range=4.0, momentum=0.9, eps=1e-12)
    wide = torch.tensor([0.0, 1.0, 0.0, 1.0])            # variance 0.25
    assert kl.coefficient(wide) == pytest.approx(0.1)     # first batch: its own average
    narrow = torch.tensor([0.0, 0.5, 0.0, 0.5])          # variance 0.0625
    avg = 0.9 * 0.25 + 0.1 * 0.0625
    assert kl.coefficient(narrow) == pytest.approx(0.1 * avg / 0.0625)   # less signal: pull harder
    kl.observe_gradient(1.0)
    kl.observe_gradient(2.0)                              # grad average 1.1, last 2.0
    avg = 0.9 * avg + 0.1 * 0.25
    assert kl.coefficient(wide) == pytest.approx(0.1 * (avg / 0.25) * (2.0 / 1.1))
    flat = torch.zeros(4)                                 # no spread at all: the clip, not inf
    assert kl.coefficient(flat) == pytest.approx(0.4)
    kl.observe_gradient(float("nan"))                     # a skipped step does not poison it
    assert kl.last_grad == 2.0


# ---------------------------------------------------------------- the top-entropy mask (80/20)


def test_high_entropy_mask_by_hand_ties_and_padding():
    # real entropies 0.1 0.2 0.3 0.4 0.5 (padding 9.0 must not count, nor be kept): the 0.6
    # quantile (rho = 0.4) interpolates to 0.34, so 0.4 and 0.5 are kept
    ent = torch.tensor([[0.1, 0.5, 9.0], [0.3, 0.2, 0.4]])
    mask = torch.tensor([[1.0, 1.0, 0.0], [1.0, 1.0, 1.0]])
    kept = losses.high_entropy_mask(ent, mask, 0.4)
    assert kept.tolist() == [[0, 1, 0], [0, 0, 1]]
    assert losses.high_entropy_mask(ent, mask, 1.0).tolist() == mask.tolist()   # rho = 1: every real token
    tied = losses.high_entropy_mask(torch.full((2, 3), 0.7), torch.ones(2, 3), 0.2)
    assert tied.sum() == 6                                 # >= at a tie keeps them all, as TRL does
    assert losses.high_entropy_mask(ent, torch.zeros(2, 3), 0.2).sum() == 0
    for bad in (0.0, -0.1, 1.5):
        with pytest.raises(ValueError, match="top_quantile"):
            losses.high_entropy_mask(ent, mask, bad)


@pytest.mark.parametrize("seed, shape, rho, loss_type", [(0, (4, 6), 0.2, "grpo"), (1, (8, 3), 0.5, "dapo"),
                                                          (2, (5, 9), 0.8, "dr_grpo")])
def test_top_entropy_quantile_trains_the_policy_term_at_the_forks_only(seed, shape, rho, loss_type):
    # against a second implementation: sort the real tokens' entropies and keep those at or above
    # the (1 - rho) quantile read off by hand; the KL term and the denominator keep every token
    g = torch.Generator().manual_seed(seed)
    n, T = shape
    logp = (torch.randn(n, T, generator=g) - 1).requires_grad_(True)
    ref = torch.randn(n, T, generator=g) - 1
    ent = torch.rand(n, T, generator=g) * 2
    mask = (torch.rand(n, T, generator=g) > 0.25).float()
    mask[:, 0] = 1
    adv = torch.randn(n, generator=g)
    ent_before, mask_before = ent.clone(), mask.clone()
    values = sorted(ent[mask.bool()].tolist())
    pos = (1 - rho) * (len(values) - 1)
    lo, frac = int(pos), pos - int(pos)
    threshold = values[lo] + frac * (values[min(lo + 1, len(values) - 1)] - values[lo])
    forks = ((ent >= threshold - 1e-7) & mask.bool()).float()
    assert 0 < forks.sum() < mask.sum()
    kw = dict(loss_type=loss_type, ref_logprobs=ref, beta=0.05, entropy=ent, max_completion_length=T)
    loss, stats = losses.grpo_loss(logp, logp.detach(), adv, mask, top_entropy_quantile=rho, **kw)
    (grad,) = torch.autograd.grad(loss, logp)
    by_hand = -forks * adv[:, None] * torch.exp(logp - logp.detach()) + 0.05 * losses.k3_kl(logp, ref)
    expected = losses.aggregate(by_hand, mask, loss_type, T)
    (grad_by_hand,) = torch.autograd.grad(expected, logp)
    assert loss.item() == pytest.approx(expected.item(), rel=1e-5, abs=1e-7)
    assert torch.allclose(grad, grad_by_hand, atol=1e-6)
    assert stats["high_entropy_frac"] == pytest.approx(float(forks.sum() / mask.sum()))
    assert torch.equal(ent, ent_before) and torch.equal(mask, mask_before)
    # a policy term at the low-entropy tokens is gone: with beta = 0 their gradient is exactly 0
    loss0, _ = losses.grpo_loss(logp, logp.detach(), adv, mask, top_entropy_quantile=rho,
                                loss_type=loss_type, entropy=ent, max_completion_length=T)
    (grad0,) = torch.autograd.grad(loss0, logp)
    assert torch.all(grad0[forks == 0] == 0) and torch.any(grad0[forks == 1] != 0)
    # rho = 1 is the plain loss, bitwise
    full, _ = losses.grpo_loss(logp, logp.detach(), adv, mask, top_entropy_quantile=1.0, **kw)
    plain, _ = losses.grpo_loss(logp, logp.detach(), adv, mask, **kw)
    assert torch.equal(full, plain)


def test_top_entropy_quantile_needs_the_entropy():
    with pytest.raises(ValueError, match="entropy"):
        losses.grpo_loss(torch.zeros(2, 3), torch.zeros(2, 3), torch.zeros(2), torch.ones(2, 3),
                         top_entropy_quantile=0.2)


def test_high_entropy_mask_leaves_its_inputs_alone():
    ent = torch.tensor([[0.1, 0.5, 9.0], [0.3, 0.2, 0.4]], requires_grad=True)   # as from the model
    mask = torch.tensor([[1.0, 1.0, 0.0], [1.0, 1.0, 1.0]])
    ent_before, mask_before = ent.detach().clone(), mask.clone()
    kept = losses.high_entropy_mask(ent, mask, 0.4)
    assert kept.tolist() == [[0, 1, 0], [0, 0, 1]]
    assert torch.equal(ent, ent_before) and torch.equal(mask, mask_before)   # padding's 9.0 still there
    assert not kept.requires_grad


@pytest.mark.parametrize("seed, rho", [(0, 0.2), (1, 0.5)])
def test_top_entropy_quantile_keeps_the_entropy_bonus_and_the_sampling_weights(seed, rho):
    # the mask acts on the clipped surrogate alone: the off-policy weights still weight it, and
    # the entropy bonus still reaches every real token, kept or not
    g = torch.Generator().manual_seed(seed)
    n, T = 6, 5
    logp = (torch.randn(n, T, generator=g) - 1).requires_grad_(True)
    old = logp.detach() + 0.05 * torch.randn(n, T, generator=g)
    ent = (torch.rand(n, T, generator=g) * 2).requires_grad_(True)
    mask = (torch.rand(n, T, generator=g) > 0.25).float()
    mask[:, 0] = 1
    adv = torch.randn(n, generator=g)
    w = torch.rand(n, T, generator=g) + 0.5
    forks = losses.high_entropy_mask(ent, mask, rho)
    assert 0 < forks.sum() < mask.sum()
    loss, _ = losses.grpo_loss(logp, old, adv, mask, entropy=ent, entropy_weight=0.01,
                               sampling_weights=w, top_entropy_quantile=rho, loss_type="dapo")
    surrogate, _ = losses.clipped_surrogate(logp, old, adv)
    by_hand = losses.aggregate(forks * w * surrogate - 0.01 * ent, mask, "dapo")
    assert loss.item() == pytest.approx(by_hand.item(), rel=1e-6)
    g_loss = torch.autograd.grad(loss, (logp, ent))
    g_hand = torch.autograd.grad(by_hand, (logp, ent))
    assert all(torch.allclose(a, b, atol=1e-7) for a, b in zip(g_loss, g_hand))
    assert torch.allclose(g_loss[1], -0.01 * mask / mask.sum())
    _, plain = losses.grpo_loss(logp, old, adv, mask, entropy=ent, top_entropy_quantile=1.0)
    assert "high_entropy_frac" not in plain
