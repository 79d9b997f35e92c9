"""ablation.seed_table: one recipe over several seeds, each value read from the run's files."""

import json
import math
import statistics

import pytest

from course_utils import ablation, stats


def fake_run(folder, seed: int, both: float, one: float, two: float, completions: list[str],
             two_digit_passes: list[int], seconds: float = 900.0, truncated: float = 0.0):
    """A finished run's files with the fields seed_table reads, nothing more."""
    run = folder / f"seed{seed}"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"seed": seed}))
    samples = [{"completion": c, "target_digit_sum": 5, "target_chars": 32, "n_chars": len(c),
                "digit_sum": 5} for c in completions]
    after = {"pass_both": both, "pass_both_one_digit": one, "pass_both_two_digit": two,
             "distinct_completions": len(set(completions)), "samples": samples}
    (run / "summary.json").write_text(json.dumps({"after": {"greedy": after}, "seconds": seconds}))
    steps = [{"step": i + 1, "passes_two_digit": p, "samples_two_digit": 8, "distinct_frac": 1.0,
              "entropy": 2.0, "truncated_frac": truncated} for i, p in enumerate(two_digit_passes)]
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in steps))
    return run


@pytest.mark.parametrize("values", [
    [(0.9, 1.0, 0.7), (0.5, 0.8, 0.1), (0.75, 0.9, 0.4)],
    [(0.2, 0.3, 0.0), (0.4, 0.6, 0.0), (0.3, 0.5, 0.1), (0.9, 1.0, 0.8), (0.6, 0.7, 0.5)],
])
def test_every_seed_and_the_mean_with_its_t_interval_and_the_worst(tmp_path, values):
    runs = [fake_run(tmp_path, 10 + i, *v, ["a b 1", "a b 1", f"c {i}"], [i, 1, 0], 800.0 + i,
                     truncated=0.95 if i == 1 else 0.1) for i, v in enumerate(values)]
    lines = ablation.seed_table(runs).splitlines()
    assert len(lines) == 2 + len(values) + 2
    for i, (row, (both, one, two)) in enumerate(zip(lines[2:], values)):
        cells = [c.strip() for c in row.strip("|").split("|")]
        assert cells == [str(10 + i), f"{both:.1%}", f"{one:.1%}", f"{two:.1%}", "2 of 3", "`a b 1`",
                         f"{i + 1} of 24",
                         "filling the token cap" if i == 1 else "still exploring", f"{800 + i}"]
    n = len(values)
    mean_cells = [c.strip() for c in lines[-2].strip("|").split("|")]
    assert mean_cells[0] == f"mean, 95% t-interval ({n - 1} df)"
    for k in range(3):
        column = [v[k] for v in values]
        m = statistics.fmean(column)
        half = stats.t_quantile(0.975, n - 1) * statistics.stdev(column) / math.sqrt(n)
        assert mean_cells[1 + k] == f"{m:.1%} [{max(0, m - half):.1%}, {min(1, m + half):.1%}]"
    worst = [c.strip() for c in lines[-1].strip("|").split("|")]
    assert worst[:4] == ["worst seed"] + [f"{min(v[k] for v in values):.1%}" for k in range(3)]


def test_the_interval_is_clipped_to_what_a_rate_can_be(tmp_path):
    runs = [fake_run(tmp_path, s, both, 1.0, two, ["x"], [0]) for s, both, two in
            [(0, 1.0, 0.0), (1, 0.2, 0.0), (2, 0.9, 0.9)]]
    mean_row = ablation.seed_table(runs).splitlines()[-2]
    assert "[0.0%," in mean_row and "100.0%]" in mean_row   # both ends would pass the bounds
    assert "-" not in mean_row.split("|", 2)[2]


def test_a_table_needs_two_seeds_and_a_reply_with_a_bar_does_not_break_the_table(tmp_path):
    with pytest.raises(ValueError, match="at least 2 runs"):
        ablation.seed_table([fake_run(tmp_path, 0, 0.5, 0.5, 0.5, ["x"], [0])])
    runs = [fake_run(tmp_path, s, 0.5, 0.5, 0.5, ["a | b\nc"], [0]) for s in (1, 2)]
    row = ablation.seed_table(runs).splitlines()[2]
    assert "`a / b c`" in row and row.count("|") == 10
