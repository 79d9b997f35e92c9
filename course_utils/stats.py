"""Comparing two arms run on the same seeds: the one statistics helper of the course.

Two training recipes run on the same seeds see the same prompts and the same first samples,
so their results are *paired*: what carries the evidence is each seed's difference, not the
two clouds of results. ``paired(a, b)`` takes the per-seed values of two arms (``a[i]`` and
``b[i]`` from seed i) and reports

* every seed's difference (always printed: with five seeds, the reader should see all five);
* the mean difference with a Student-t interval on n - 1 degrees of freedom;
* an exact sign-flip permutation test (under "no difference", each seed's difference is as
  likely to have either sign; all 2**n sign patterns are enumerated for n <= 16);
* the smallest difference this design could detect (two-sided 5% test, 80% power, using the
  observed spread of the differences), printed beside every "no difference detected", because
  three seeds that cannot see a 60-point gap do not show that there is none.

No scipy: the t quantile comes from the regularized incomplete beta function below (checked
against tabulated values in ``tests/test_stats.py``).
"""

from __future__ import annotations

import itertools
import math
import random
import statistics
from dataclasses import dataclass

EXACT_UP_TO = 16  # seeds; beyond this the permutation test samples sign patterns
SIGN_SAMPLES = 200_000  # sign patterns drawn when there are more seeds than EXACT_UP_TO


# --- Student's t distribution, from the incomplete beta function ----------------------------

def _beta_continued_fraction(a: float, b: float, x: float) -> float:
    """Lentz's continued fraction for the incomplete beta function (Numerical Recipes 6.4)."""
    tiny, qab, qap, qam = 1e-300, a + b, a + 1.0, a - 1.0
    c, d = 1.0, 1.0 - qab * x / qap
    d = 1.0 / (d if abs(d) > tiny else tiny)
    h = d
    for m in range(1, 300):
        m2 = 2 * m
        for aa in (m * (b - m) * x / ((qam + m2) * (a + m2)),
                   -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2))):
            d = 1.0 + aa * d
            d = 1.0 / (d if abs(d) > tiny else tiny)
            c = 1.0 + aa / c
            c = c if abs(c) > tiny else tiny
            h *= d * c
        if abs(d * c - 1.0) < 1e-15:
            break
    return h


def _incomplete_beta(a: float, b: float, x: float) -> float:
    """I_x(a, b), the regularized incomplete beta function."""
    if x <= 0.0:
        return 0.0
    if x >= 1.0:
        return 1.0
    log_front = math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b) + a * math.log(x) + b * math.log1p(-x)
    if x < (a + 1.0) / (a + b + 2.0):
        return math.exp(log_front) * _beta_continued_fraction(a, b, x) / a
    return 1.0 - math.exp(log_front) * _beta_continued_fraction(b, a, 1.0 - x) / b


def t_cdf(t: float, df: int) -> float:
    """P(T <= t) for Student's t with ``df`` degrees of freedom."""
    tail = 0.5 * _incomplete_beta(df / 2.0, 0.5, df / (df + t * t))
    return 1.0 - tail if t > 0 else tail


def t_quantile(p: float, df: int) -> float:
    """The t value below which a share ``p`` of Student's t(df) lies (bisection on t_cdf)."""
    if not 0.0 < p < 1.0:
        raise ValueError(f"p must be in (0, 1), got {p}")
    low, high = -1e7, 1e7   # wide enough for p = 1e-12 at 1 df
    for _ in range(200):
        mid = 0.5 * (low + high)
        low, high = (mid, high) if t_cdf(mid, df) < p else (low, mid)
    return 0.5 * (low + high)


# --- the paired comparison -------------------------------------------------------------------

def sign_flip_p_value(diffs: list[float], seed: int = 0, samples: int = SIGN_SAMPLES) -> float:
    """Two-sided p-value of the paired permutation test: the share of sign patterns whose mean
    difference is at least as far from 0 as the observed one. Exact for n <= EXACT_UP_TO."""
    n = len(diffs)
    observed = abs(sum(diffs)) - 1e-12 * max(1.0, sum(abs(d) for d in diffs))
    if n <= EXACT_UP_TO:
        hits = sum(abs(sum(s * d for s, d in zip(signs, diffs))) >= observed
                   for signs in itertools.product((1, -1), repeat=n))
        return hits / 2 ** n
    rng = random.Random(seed)
    hits = sum(abs(sum(d if rng.random() < 0.5 else -d for d in diffs)) >= observed
               for _ in range(samples))
    return (hits + 1) / (samples + 1)


@dataclass(frozen=True)
class PairedComparison:
    """Arm a minus arm b, seed by seed (see the module docstring)."""
    a: tuple[float, ...]
    b: tuple[float, ...]
    level: float
    unit: str = "seed"      # what pairs the values: "seed", or "prompt" for two policies scored on the same prompts

    @property
    def n(self) -> int:
        return len(self.a)

    @property
    def diffs(self) -> tuple[float, ...]:
        return tuple(x - y for x, y in zip(self.a, self.b))

    @property
    def mean(self) -> float:
        return statistics.fmean(self.diffs)

    @property
    def sd(self) -> float:
        return statistics.stdev(self.diffs)

    @property
    def half_width(self) -> float:
        """Half the width of the t-interval on n - 1 degrees of freedom."""
        return t_quantile(0.5 + self.level / 2, self.n - 1) * self.sd / math.sqrt(self.n)

    @property
    def interval(self) -> tuple[float, float]:
        return self.mean - self.half_width, self.mean + self.half_width

    @property
    def p_value(self) -> float:
        """The exact sign-flip permutation test's two-sided p-value."""
        return sign_flip_p_value(list(self.diffs))

    @property
    def detectable(self) -> float:
        """About the smallest true mean difference a two-sided test at 1 - level would find
        with 80% power: (t_{1-alpha/2} + t_{0.8}) sd / sqrt(n), estimated from the observed spread
        of the differences (simulated power at that size is 77-80% for 3-10 seeds)."""
        df = self.n - 1
        return (t_quantile(0.5 + self.level / 2, df) + t_quantile(0.8, df)) * self.sd / math.sqrt(self.n)

    @property
    def significant(self) -> bool:
        """The t-interval excludes 0 (and the differences are not all zero)."""
        low, high = self.interval
        return self.sd > 0 and (low > 0 or high < 0) or (self.sd == 0 and self.mean != 0)

    @property
    def p_floor(self) -> float:
        """The smallest p-value the sign-flip test can give here: 2 ** (1 - m), where m counts
        the seeds whose difference is not zero (a zero difference has no sign to flip); with
        more seeds than EXACT_UP_TO the test samples sign patterns, and its floor is
        1 / (SIGN_SAMPLES + 1)."""
        m = sum(d != 0 for d in self.diffs)
        exact = 2.0 ** (1 - m) if m else 1.0
        return exact if self.n <= EXACT_UP_TO else max(exact, 1.0 / (SIGN_SAMPLES + 1))

    def verdict(self, fmt: str = "{:+.3f}") -> str:
        """One line: the per-seed (per-unit) differences, mean and interval, p-value, and the verdict, with
        the smallest detectable difference beside a "no difference detected"."""
        per_seed = ", ".join(fmt.format(d) for d in self.diffs)
        if self.sd == 0:
            what = "identical on every" if self.mean == 0 else "the same difference on every"
            return f"per-{self.unit} differences [{per_seed}]: {what} {self.unit}"
        low, high = self.interval
        alpha = 1 - self.level
        nonzero = sum(d != 0 for d in self.diffs)
        units = f"{self.unit}s"
        seeds = f"{self.n} {units}" if nonzero == self.n else f"{nonzero} of {self.n} {units} differing"
        head = (f"per-{self.unit} differences [{per_seed}], mean {fmt.format(self.mean)}, "
                f"{self.level:.0%} t-interval [{fmt.format(low)}, {fmt.format(high)}] "
                f"({self.n - 1} df), sign-flip p = {self.p_value:.3g} (its smallest possible with "
                f"{seeds}: {self.p_floor:.3g})")
        if self.significant and self.p_value <= alpha:
            return head + "; the t-interval excludes 0: a difference"
        if self.significant:
            # the t-interval assumes roughly normal differences; the sign-flip test assumes only
            # that each is as likely either sign
            why = (f"it cannot go below {self.p_floor:.3g} with {seeds}" if self.p_floor > alpha
                   else "these differences are not extreme enough for it")
            return head + (f"; the t-interval excludes 0: a difference if the per-{self.unit} differences "
                           f"are roughly normal, which the sign-flip test does not confirm: {why}")
        if self.p_value <= alpha:
            return head + ("; the t-interval includes 0 but the sign-flip test finds a difference: "
                           f"the differences lean one way, and their spread (often one {self.unit} far "
                           f"from the others) widens the t-interval; read the per-{self.unit} values")
        return head + (f"; the t-interval includes 0: no difference detected (a t-test on these "
                       f"{units} would detect about {fmt.format(self.detectable).lstrip('+')} at 80% "
                       f"power if the true spread were the observed one, itself a rough estimate "
                       f"from {self.n - 1} df)")


def paired(a: list[float], b: list[float], level: float = 0.95, unit: str = "seed") -> PairedComparison:
    """Compare arm ``a`` with arm ``b`` over shared seeds (``a[i]``, ``b[i]`` from seed i), or over
    whatever else pairs them (``unit``: "prompt" when two policies are scored on the same
    held-out prompts)."""
    a, b = tuple(float(x) for x in a), tuple(float(x) for x in b)
    if len(a) != len(b):
        raise ValueError(f"paired arms need one value per shared seed; got {len(a)} and {len(b)}")
    if len(a) < 2:
        raise ValueError("a paired comparison needs at least 2 seeds")
    if not all(math.isfinite(x) for x in a + b):
        raise ValueError("paired arms must hold finite numbers")
    if not 0.5 <= level < 1:
        raise ValueError(f"level must be in [0.5, 1), got {level}")
    return PairedComparison(a=a, b=b, level=level, unit=unit)
