"""Prioritized target sampling and the adaptive entropy weight: their rules on hand examples."""
import pytest
import torch

from course_utils import curriculum, losses
from course_utils.data import Prompt


def pool(targets=(3, 5, 10, 12), per_target=4):
    return [Prompt(text=f"p{t}-{i}", snippet=f"s{i}", target_chars=32, target_digit_sum=t)
            for t in targets for i in range(per_target)]


def test_unseen_targets_are_drawn_uniformly_and_draws_are_seeded():
    prio = curriculum.TargetPriority(pool())
    assert torch.equal(prio.weights(), torch.full((4,), 1.1, dtype=torch.float64))
    a, b = prio.batch(seed=0, step=3, size=16), prio.batch(seed=0, step=3, size=16)
    assert a == b and a != prio.batch(seed=0, step=4, size=16)
    assert all(p.target_digit_sum in (3, 5, 10, 12) for p in a)


def test_solved_targets_lose_weight_and_unsolved_ones_are_drawn_more():
    prompts = pool()
    prio = curriculum.TargetPriority(prompts, floor=0.1)
    batch = [p for p in prompts if p.target_digit_sum in (3, 10)][::4]   # one prompt of 3, one of 10
    assert [p.target_digit_sum for p in batch] == [3, 10]
    passed = torch.tensor([1.0] * 4 + [0.0] * 4)                          # G = 4: all pass / none
    prio.observe(batch, passed, group_size=4)
    assert prio.pass_rate[3] == 1.0 and prio.pass_rate[10] == 0.0         # first sight replaces the prior
    assert prio.weights().tolist() == pytest.approx([0.1, 1.1, 1.1, 1.1])
    prio.observe(batch[:1], torch.zeros(4), group_size=4)                 # later sights average
    assert prio.pass_rate[3] == pytest.approx(0.8)
    drawn = [p.target_digit_sum for step in range(200) for p in prio.batch(0, step, 4)]
    share_3 = drawn.count(3) / len(drawn)
    expected = (0.1 + 0.2) / (0.3 + 3 * 1.1)
    assert abs(share_3 - expected) < 0.03


def test_priority_state_round_trips_through_a_checkpoint():
    prompts = pool()
    prio = curriculum.TargetPriority(prompts)
    prio.observe(prompts[:1], torch.tensor([1.0, 0.0]), group_size=2)
    other = curriculum.TargetPriority(prompts)
    other.load_state_dict({k: {str(t): v for t, v in d.items()} for k, d in prio.state_dict().items()})
    assert other.pass_rate == prio.pass_rate and other.seen == prio.seen
    assert other.batch(1, 7, 8) == prio.batch(1, 7, 8)
    with pytest.raises(ValueError, match="floor"):
        curriculum.TargetPriority(prompts, floor=0.0)


def test_adaptive_entropy_turns_on_below_the_target_and_off_above():
    ctl = losses.AdaptiveEntropy(target=1.0, delta=0.01, max_weight=0.025)
    assert ctl.weight() == 0.0                          # nothing observed yet
    ctl.observe(3.0)                                    # above the target: off, coefficient stays at 0
    assert ctl.weight() == 0.0 and ctl.coef == 0.0
    for expected in (0.01, 0.02, 0.025, 0.025):         # below: grows by delta, capped
        ctl.observe(0.5)
        assert ctl.weight() == pytest.approx(expected)
    ctl.observe(1.5)                                    # back above: off at once, coefficient decays
    assert ctl.weight() == 0.0 and ctl.coef == pytest.approx(0.015)
    ctl.observe(float("nan"))                           # a non-finite reading changes nothing
    assert ctl.coef == pytest.approx(0.015) and ctl.entropy == 1.5
    restored = losses.AdaptiveEntropy(1.0, 0.01, 0.025)
    restored.load_state_dict(ctl.state_dict())
    assert (restored.coef, restored.entropy) == (ctl.coef, ctl.entropy)


def test_one_update_per_target_and_step_whatever_the_order_of_the_groups():
    prompts = pool()
    threes = [p for p in prompts if p.target_digit_sum == 3][:2]
    a, b = curriculum.TargetPriority(prompts), curriculum.TargetPriority(prompts)
    flags = torch.tensor([1.0, 1.0, 0.0, 0.0])       # G = 2: the first group passes, the second fails
    a.observe(threes, flags, group_size=2)
    b.observe(threes[::-1], torch.tensor([0.0, 0.0, 1.0, 1.0]), group_size=2)
    assert a.pass_rate[3] == b.pass_rate[3] == 0.5   # both groups' samples, averaged at once


def test_bad_settings_and_a_changed_pool_are_handled():
    with pytest.raises(ValueError, match="momentum"):
        curriculum.TargetPriority(pool(), momentum=1.0)
    with pytest.raises(ValueError, match="at least one training prompt"):
        curriculum.TargetPriority([])
    old = curriculum.TargetPriority(pool(targets=(3, 5)))
    old.observe(pool(targets=(3,))[:1], torch.ones(2), group_size=2)
    new = curriculum.TargetPriority(pool(targets=(3, 7)))   # 5 gone, 7 new
    new.load_state_dict(old.state_dict())
    assert new.pass_rate == {3: 1.0, 7: 0.0} and new.seen == {3: True, 7: False}
    assert len(new.weights()) == 2


@pytest.mark.parametrize("targets, hardest", [((3, 5, 10, 12), [10, 12]), ((3, 5, 9), [3, 5, 9]),
                                              ((3, 18, 19), [19]), ((12,), [12])])
def test_hardest_targets_are_those_needing_the_most_digits(targets, hardest):
    assert curriculum.TargetPriority(pool(targets=targets)).hardest() == hardest


def test_a_restricted_draw_keeps_to_its_targets_and_their_weights():
    prompts = pool()
    prio = curriculum.TargetPriority(prompts, floor=0.1)
    prio.observe([p for p in prompts if p.target_digit_sum == 10][:1], torch.ones(4), group_size=4)
    only = prio.hardest()
    a = prio.batch(seed=1, step=7, size=16, only=only)
    assert a == prio.batch(seed=1, step=7, size=16, only=only)          # seeded by (seed, step)
    drawn = [p.target_digit_sum for step in range(300) for p in prio.batch(1, step, 4, only=only)]
    assert set(drawn) == {10, 12}                                        # no one-digit target
    # 10 is solved (weight 0.1), 12 is not (1.1): 10 gets 0.1 / 1.2 of the draws, not half
    assert abs(drawn.count(10) / len(drawn) - 0.1 / 1.2) < 0.03
    assert prio.batch(1, 7, 16, only=prio.targets) == prio.batch(1, 7, 16)   # no restriction
    assert {p.target_digit_sum for p in prio.batch(0, 0, 32, only=[7, 12])} == {12}
    with pytest.raises(ValueError, match=r"only=\[7\]: none of these targets"):
        prio.batch(0, 0, 4, only=[7])
    assert prio.batch(1, 7, 16, only=only, others_scale=0.0) == a       # 0: the hardest alone
    assert prio.batch(1, 7, 16, only=only, others_scale=1.0) == prio.batch(1, 7, 16)
    with pytest.raises(ValueError, match="others_scale must be in"):
        prio.batch(0, 0, 4, only=only, others_scale=1.5)


@pytest.mark.parametrize("scale", [0.25, 0.6])
def test_a_ramped_draw_scales_the_other_targets_weights(scale):
    prompts = pool(targets=range(3, 13))
    prio = curriculum.TargetPriority(prompts)
    prio.observe([p for p in prompts if p.target_digit_sum == 4][:1], torch.ones(4), group_size=4)
    weights = {t: w for t, w in zip(prio.targets, prio.weights().tolist())}
    expected = {t: w * (1.0 if t >= 10 else scale) for t, w in weights.items()}
    drawn = [p.target_digit_sum for step in range(1500)
             for p in prio.batch(2, step, 4, only=prio.hardest(), others_scale=scale)]
    total = sum(expected.values())
    for t in (4, 5, 11):   # a solved easy target, an unsolved easy one, a hard one
        assert abs(drawn.count(t) / len(drawn) - expected[t] / total) < 0.02, t


def test_training_draws_only_the_hardest_targets_for_the_curriculums_steps(tmp_path, monkeypatch):
    from course_utils import checkpoint, train
    from course_utils.config import load_config

    restricted = []
    batch = train.curriculum.TargetPriority.batch
    monkeypatch.setattr(train.curriculum.TargetPriority, "batch", lambda self, *a, only=None, **k:
                        (restricted.append(only), batch(self, *a, only=only, **k))[1])
    cfg = load_config("smoke", out_dir=str(tmp_path), digit_sum_min=3, digit_sum_max=12,
                      target_sampling="prioritized", hard_first_steps=3, max_steps=6, train_prompts=32)
    train.train(cfg, progress=False)
    assert restricted == [[10, 11, 12]] * 3 + [None] * 3     # exactly the curriculum's steps
    rows = cfg.prompts_per_step * cfg.group_size
    two_digit = [r["samples_two_digit"] for r in checkpoint.MetricsLog(tmp_path / "metrics.jsonl").read()]
    assert two_digit[:3] == [rows] * 3             # the curriculum: two-digit targets only
    assert min(two_digit[3:]) < rows               # then every target again (seeded: some one-digit)


def test_a_ramped_curriculum_lets_the_other_targets_in_step_by_step(tmp_path, monkeypatch):
    from course_utils import train
    from course_utils.config import load_config

    scales = []
    batch = train.curriculum.TargetPriority.batch
    monkeypatch.setattr(train.curriculum.TargetPriority, "batch", lambda self, *a, only=None,
                        others_scale=0.0, **k: (scales.append(others_scale if only else None),
                                                batch(self, *a, only=only, others_scale=others_scale, **k))[1])
    cfg = load_config("smoke", out_dir=str(tmp_path), digit_sum_min=3, digit_sum_max=12,
                      target_sampling="prioritized", hard_first_steps=4, hard_first_ramp=True,
                      max_steps=6, train_prompts=32)
    train.train(cfg, progress=False)
    assert scales == [0.0, 0.25, 0.5, 0.75, None, None]   # k / hard_first_steps, then no curriculum


def test_the_curriculum_resumes_bitwise_across_its_end(resume_pair):
    (ra, rb), (a, b) = resume_pair(target_sampling="prioritized", hard_first_steps=3,
                                   digit_sum_max=12, train_prompts=32)
    for key in ("samples_two_digit", "reward_mean", "loss"):
        assert [r[key] for r in ra] == [r[key] for r in rb], key
    assert all(torch.equal(a[k], b[k]) for k in a)
