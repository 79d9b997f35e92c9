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


# --- lesson 7, 6.6: the probes against the token-cap hack ----------------------------------------

def probe_run(folder, name: str, config: dict, precision: str | None, truncated: list[float],
              tokens: list[float], samples: list[dict], after: dict):
    """A finished probe's files with the fields cap_probes and completions_by_target read."""
    run = folder / name
    run.mkdir()
    (run / "config.json").write_text(json.dumps(config))
    summary = {"after": {"greedy": {**after, "samples": samples}}}
    if precision is not None:
        summary["precision"] = precision
    (run / "summary.json").write_text(json.dumps(summary))
    steps = [{"step": i + 1, "truncated_frac": t, "completion_tokens": k, "distinct_frac": 1.0,
              "entropy": 2.0} for i, (t, k) in enumerate(zip(truncated, tokens))]
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in steps))
    return run


def sample(completion: str, target: int) -> dict:
    from course_utils import rewards
    result = rewards.check(completion, 32, target)
    return {"completion": completion, "target_digit_sum": target, "target_chars": 32,
            "n_chars": result.n_chars, "digit_sum": result.digit_sum}


PASS_10 = "19 characters! That's ingenious!"   # 32 characters, digit sum 10
assert len(PASS_10) == 32


@pytest.mark.parametrize("n_steps", [5, 8])
def test_cap_probes_names_each_change_and_reads_the_last_steps(tmp_path, n_steps):
    recipe = {"seed": 10, "out_dir": "a", "lr": 1e-5, "overlong_penalty": 0.0, "overlong_buffer": 0}
    after = {"pass_both": 0.25, "pass_both_one_digit": 0.0, "pass_both_two_digit": 0.5,
             "distinct_completions": 2}
    samples = [sample(PASS_10, 10), sample(PASS_10, 11), sample("x | y\nz", 3)]
    # the stored run predates overlong_* and the precision field: neither is a change
    old = probe_run(tmp_path, "old", {"seed": 13, "out_dir": "b", "lr": 1e-5}, None,
                    [0.0] * (n_steps - 5) + [1.0] * 5, [10.0] * (n_steps - 5) + [24.0] * 5,
                    samples, after)
    punished = probe_run(tmp_path, "new", {**recipe, "seed": 13, "out_dir": "c",
                                           "overlong_penalty": 1.0, "overlong_buffer": 5}, "fp32",
                         [0.5] * (n_steps - 5) + [0.0, 0.1, 0.0, 0.1, 0.0],
                         [20.0] * (n_steps - 5) + [8.0, 9.0, 10.0, 9.0, 9.0], samples, after)
    lines = ablation.cap_probes([old, punished], recipe).splitlines()
    assert len(lines) == 4
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in lines[2:]]
    assert rows[0][:6] == ["13", "none", "not recorded", "100%", "24.0", "filling the token cap"]
    assert rows[1][:6] == ["13", "overlong_penalty 1.0, overlong_buffer 5", "fp32", "4%", "9.0",
                           "still exploring"]
    assert rows[1][6:10] == ["25.0%", "0.0%", "50.0%", "2 of 3"]
    assert all(len(r) == 11 for r in rows)


def test_completions_by_target_labels_its_groups_and_keeps_a_reply_in_its_cell(tmp_path):
    after = {"pass_both": 0.0, "pass_both_one_digit": 0.0, "pass_both_two_digit": 0.0,
             "distinct_completions": 1}
    runs = [probe_run(tmp_path, name, {"seed": 13}, "fp32", [0.0], [5.0], samples, after)
            for name, samples in (("a", [sample("a | b\n\nc 3", 3), sample(PASS_10, 10)]),
                                  ("b", [sample("3", 3), sample("19", 10), sample("19", 10)]))]
    table = ablation.completions_by_target(runs, ["control", "punished"]).splitlines()
    assert table[0].startswith("| target digit sum | control: passed") and "| punished: passed" in table[0]
    assert len(table) == 4 and all(line.count("|") == 6 for line in table[2:])
    assert "`a / b  c 3` (3)" in table[2]
    assert table[3].split("|")[2].strip() == "1 of 1" and table[3].split("|")[4].strip() == "0 of 2"
    assert "seed 13: passed" in ablation.completions_by_target(runs).splitlines()[0]
    with pytest.raises(ValueError, match="2 labels for 1 runs"):
        ablation.completions_by_target(runs[:1], ["control", "punished"])


def test_completions_by_target_says_when_the_most_frequent_completion_is_a_tie(tmp_path):
    after = {"pass_both": 0.0, "pass_both_one_digit": 0.0, "pass_both_two_digit": 0.0,
             "distinct_completions": 3}
    samples = [sample("19", 10), sample("28", 10), sample("37", 10), sample("37", 10), sample("3", 3),
               sample("4", 3)]
    run = probe_run(tmp_path, "t", {"seed": 1}, "fp32", [0.0], [5.0], samples, after)
    rows = ablation.completions_by_target([run]).splitlines()
    assert rows[2].endswith("| `3` (3; tied with 1 other at 1 each) |")    # first in prompt order
    assert rows[3].endswith("| `37` (10) |")                                # a clear winner: no mark
    three = [sample("1", 3), sample("2", 3), sample("12", 3)]
    run = probe_run(tmp_path, "u", {"seed": 1}, "fp32", [0.0], [5.0], three, after)
    assert "tied with 2 others at 1 each" in ablation.completions_by_target([run])


def logged_run(folder, name: str, steps: list[tuple[float, int, int]], **config):
    """A run whose log has, per step, pass_both, samples_two_digit and passes_two_digit."""
    run = folder / name
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"prompts_per_step": 2, "group_size": 4, "seed": 0, **config}))
    (run / "metrics.jsonl").write_text("".join(
        json.dumps({"step": i + 1, "pass_both": p, "samples_two_digit": n2, "passes_two_digit": k2}) + "\n"
        for i, (p, n2, k2) in enumerate(steps)))
    return run


def test_sampled_passes_counts_each_window_by_hand(tmp_path):
    # 8 replies a step: step 1 passes 3 (1 of them two-digit, of 4 two-digit sampled), step 2
    # passes 8 of 8 with no two-digit target, step 3 passes none of 8, all two-digit
    run = logged_run(tmp_path, "a", [(3 / 8, 4, 1), (1.0, 0, 0), (0.0, 8, 0)])
    assert ablation.sampled_passes(run, width=2) == [
        {"first": 1, "last": 2, "one_passed": 10, "one_sampled": 12, "two_passed": 1, "two_sampled": 4},
        {"first": 3, "last": 3, "one_passed": 0, "one_sampled": 0, "two_passed": 0, "two_sampled": 8}]
    table = ablation.sampled_passes_table([run, run], ["x", "y"], width=2).splitlines()
    assert table[2] == "| 1-2 | 83% | 25% | 83% | 25% |"
    assert table[3] == "| 3-3 | - | 0% | - | 0% |"     # nothing sampled is not 0% passed


def test_sampled_passes_refuses_what_the_log_cannot_count(tmp_path):
    with pytest.raises(ValueError, match="dynamic sampling"):
        ablation.sampled_passes(logged_run(tmp_path, "d", [(0.5, 4, 1)], dynamic_sampling=True))
    a, b = logged_run(tmp_path, "a", [(0.5, 4, 1)]), logged_run(tmp_path, "b", [(0.5, 4, 1)] * 12)
    with pytest.raises(ValueError, match="different numbers of steps"):
        ablation.sampled_passes_table([a, b], ["a", "b"])
    with pytest.raises(ValueError, match="1 labels for 2 runs"):
        ablation.sampled_passes_table([a, a], ["a"])


@pytest.mark.parametrize("values", [
    [((0.7, 1.0, 0.0), (0.1, 0.1, 0.0)), ((0.8, 0.9, 0.5), (0.2, 0.3, 0.0)),
     ((0.4, 0.5, 0.1), (0.4, 0.4, 0.3))],
    [((0.9, 1.0, 0.7), (0.0, 0.0, 0.0)), ((0.3, 0.4, 0.0), (0.6, 0.7, 0.2))],
])
def test_paired_arms_lists_both_arms_per_seed_and_pairs_a_minus_b(tmp_path, values):
    (tmp_path / "a").mkdir(), (tmp_path / "b").mkdir()
    a = [fake_run(tmp_path / "a", 20 + i, *x, ["p 1", "q 2"], [0]) for i, (x, _) in enumerate(values)]
    b = [fake_run(tmp_path / "b", 20 + i, *y, ["r 3"], [0]) for i, (_, y) in enumerate(values)]
    lines = ablation.paired_arms(a, b, ("fp32", "bf16")).splitlines()
    assert lines[0].startswith("| seed | fp32: both") and "| bf16: both |" in lines[0]
    for i, (x, y) in enumerate(values):
        cells = [c.strip() for c in lines[2 + i].strip("|").split("|")]
        assert cells == [str(20 + i), *(f"{v:.1%}" for v in x), "2", "2.00", *(f"{v:.1%}" for v in y), "1", "2.00"]
    verdicts = lines[2 + len(values) + 1:]
    for line, k, what in zip(verdicts, (0, 2), ("both constraints", "two-digit targets")):
        expected = stats.paired([x[k] for x, _ in values], [y[k] for _, y in values]).verdict("{:+.1%}")
        assert line == f"- fp32 minus bf16, {what}: {expected}"
    assert len(verdicts) == 2


def test_paired_arms_refuses_arms_on_different_seeds(tmp_path):
    (tmp_path / "a").mkdir(), (tmp_path / "b").mkdir()
    a = [fake_run(tmp_path / "a", s, 0.5, 0.5, 0.0, ["x"], [0]) for s in (1, 2)]
    b = [fake_run(tmp_path / "b", s, 0.5, 0.5, 0.0, ["x"], [0]) for s in (2, 1)]
    with pytest.raises(ValueError, match="same seeds"):
        ablation.paired_arms(a, b, ("a", "b"))
    with pytest.raises(ValueError, match="at least 2"):
        ablation.paired_arms(a[:1], a[:1], ("a", "b"))
