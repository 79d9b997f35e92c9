"""The paired-comparison helper: quantiles against tables, the false-positive rate of a null,
and a planted difference found at the rate the helper says it would be."""

import math
import random
import statistics

import pytest

from course_utils import stats


@pytest.mark.parametrize("p, df, table", [(0.975, 1, 12.706), (0.975, 4, 2.776), (0.975, 9, 2.262),
                                          (0.975, 19, 2.093), (0.8, 4, 0.941), (0.8, 9, 0.883),
                                          (0.95, 2, 2.920), (0.5, 7, 0.0)])
def test_t_quantile_matches_tables(p, df, table):
    assert stats.t_quantile(p, df) == pytest.approx(table, abs=1e-3)


def test_t_cdf_is_symmetric_and_monotone():
    for df in (1, 3, 10):
        assert stats.t_cdf(0.0, df) == pytest.approx(0.5)
        assert stats.t_cdf(1.3, df) + stats.t_cdf(-1.3, df) == pytest.approx(1.0)
        values = [stats.t_cdf(t, df) for t in (-3, -1, 0, 1, 3)]
        assert values == sorted(values)


def test_sign_flip_p_value_by_hand():
    # 3 positive differences: of the 8 sign patterns only all-plus and all-minus reach |sum| = 6
    assert stats.sign_flip_p_value([1.0, 2.0, 3.0]) == pytest.approx(2 / 8)
    assert stats.sign_flip_p_value([1.0, -1.0]) == pytest.approx(1.0)


def _simulate(effect: float, sigma: float, n: int, trials: int, seed: int) -> tuple[float, float]:
    """Rejection rates of the t-interval and of the permutation test over simulated designs."""
    rng = random.Random(seed)
    t_hits = perm_hits = 0
    for _ in range(trials):
        base = [rng.gauss(0, 1) for _ in range(n)]       # seed effects shared by both arms
        a = [x + effect + rng.gauss(0, sigma / math.sqrt(2)) for x in base]
        b = [x + rng.gauss(0, sigma / math.sqrt(2)) for x in base]
        cmp = stats.paired(a, b)
        t_hits += cmp.significant
        perm_hits += cmp.p_value < 0.05
    return t_hits / trials, perm_hits / trials


def test_null_is_rejected_at_most_five_percent_of_the_time():
    t_rate, perm_rate = _simulate(effect=0.0, sigma=1.0, n=8, trials=1500, seed=1)
    # 5% nominal; 1500 trials give a binomial standard error of 0.56 points
    assert t_rate <= 0.05 + 3 * math.sqrt(0.05 * 0.95 / 1500)
    assert perm_rate <= 0.05 + 3 * math.sqrt(0.05 * 0.95 / 1500)


def test_planted_difference_is_found_at_the_stated_rate():
    # the helper says a design with this spread detects `detectable` at 80% power; plant the
    # difference computed from the true spread and count how often it is found
    n, sigma = 10, 1.0
    df = n - 1
    planted = (stats.t_quantile(0.975, df) + stats.t_quantile(0.8, df)) * sigma / math.sqrt(n)
    t_rate, _ = _simulate(effect=planted, sigma=sigma, n=n, trials=1500, seed=2)
    assert 0.72 <= t_rate <= 0.88


def test_verdict_names_the_detectable_difference_and_shows_every_seed():
    cmp = stats.paired([0.1, 0.5, 0.2], [0.3, 0.2, 0.4])
    text = cmp.verdict()
    assert "no difference detected" in text and "would detect about" in text
    for d in cmp.diffs:
        assert f"{d:+.3f}" in text
    assert "2 df" in text
    clear = stats.paired([1.0, 1.1, 0.9, 1.05, 0.97, 1.2], [0.0, 0.05, -0.1, 0.02, 0.1, 0.0])
    assert clear.verdict().endswith("excludes 0: a difference")
    assert stats.paired([1, 2], [1, 2]).verdict().endswith("identical on every seed")
    # three seeds, all differences positive: the t-interval excludes 0, but the sign-flip test
    # cannot go below 0.25, and the verdict says the call rests on normality
    few = stats.paired([1.0, 1.1, 0.95], [0.0, 0.05, 0.02]).verdict()
    assert "excludes 0: a difference if the per-seed differences are roughly normal" in few
    assert "it cannot go below 0.25 with 3 seeds" in few
    # the other disagreement: six differences of one sign, one far out, widen the t-interval
    skewed = stats.paired([1, 1, 1, 1, 1, 10], [0] * 6)
    assert skewed.p_value == 2 / 2 ** 6 and skewed.interval[0] < 0
    assert "includes 0 but the sign-flip test finds a difference" in skewed.verdict()


def test_the_sign_flip_floor_counts_only_seeds_that_differ():
    """A zero difference has no sign to flip: with two of three seeds differing the smallest
    possible p is 0.5, and with one it is 1, which the verdict must say."""
    two = stats.paired([0.0, -0.078, -0.125], [0.0, 0.0, 0.0])
    assert two.p_floor == 0.5 and two.p_value == 0.5
    assert "smallest possible with 2 of 3 seeds differing: 0.5" in two.verdict()
    one = stats.paired([0.0, 0.0, -0.333], [0.0, 0.0, 0.0])
    assert one.p_floor == 1.0 == one.p_value
    assert stats.paired([1.0, 2.0, 3.0], [0.0, 1.0, 1.0]).p_floor == 0.25


def test_the_sign_flip_floor_of_a_sampled_test_is_one_over_its_samples_plus_one():
    """Beyond EXACT_UP_TO seeds the test samples sign patterns: it cannot report a p-value below
    1 / (samples + 1), however many seeds differ, and the verdict must not claim one."""
    n = stats.EXACT_UP_TO + 4
    comparison = stats.paired([float(i + 1) for i in range(n)], [0.0] * n)
    assert comparison.p_floor == 1.0 / (stats.SIGN_SAMPLES + 1) > 2.0 ** (1 - n)
    assert comparison.p_value == pytest.approx(comparison.p_floor)
    assert f"{comparison.p_floor:.3g}" in comparison.verdict()


def test_interval_by_hand():
    a, b = [3.0, 5.0, 4.0, 6.0], [1.0, 2.0, 2.0, 3.0]
    cmp = stats.paired(a, b)
    d = [2.0, 3.0, 2.0, 3.0]
    half = 3.182 * statistics.stdev(d) / 2
    assert cmp.mean == pytest.approx(2.5)
    assert cmp.interval == pytest.approx((2.5 - half, 2.5 + half), abs=1e-3)


@pytest.mark.parametrize("a, b, match", [([1.0, 2.0], [1.0], "one value per shared seed"),
                                         ([1.0], [2.0], "at least 2 seeds"),
                                         ([1.0, float("nan")], [1.0, 2.0], "finite")])
def test_bad_input_is_refused(a, b, match):
    with pytest.raises(ValueError, match=match):
        stats.paired(a, b)


def test_the_sign_flip_test_finds_a_clear_difference_and_states_its_floor():
    # all eight differences positive: only the all-plus and all-minus patterns are as extreme
    diffs = [1.0, 1.2, 0.9, 1.1, 1.3, 0.8, 1.0, 1.05]
    assert stats.sign_flip_p_value(diffs) == 2 / 2 ** 8
    assert stats.sign_flip_p_value([1.0, -1.0, 0.5, -0.5]) == 1.0   # symmetric: nothing to see
    text = stats.paired([1.0, 1.1, 0.9], [0.0, 0.0, 0.0]).verdict()
    assert "smallest possible with 3 seeds: 0.25" in text          # 3 seeds cannot reach p < 0.05


def test_extreme_t_quantiles_are_not_cut_off():
    assert abs(stats.t_quantile(0.99995, 1) - 6366.2) < 0.5      # tables: t_{.99995, 1} = 6366.2


def test_a_comparison_paired_by_prompt_says_prompts_not_seeds():
    """Two policies scored on the same held-out prompts are paired by prompt; the verdict says so."""
    before = [0.1 * i for i in range(8)]
    after = [x + 0.05 + 0.01 * (-1) ** i for i, x in enumerate(before)]
    verdict = stats.paired(after, before, unit="prompt").verdict()
    assert "per-prompt differences" in verdict and "8 prompts" in verdict
    assert "seed" not in verdict
    same = stats.paired([1.0, 2.0], [1.0, 2.0], unit="prompt").verdict()
    assert same.endswith("identical on every prompt")
