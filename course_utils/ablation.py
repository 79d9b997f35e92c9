"""Why a GRPO run fails and what fixes it: the levers measured on top of the `cpu` preset.

    python -m course_utils.ablation --seeds 0 1 2 --out notebooks/results/ablation

Every arm is the main job (the ``cpu`` preset, same steps, same held-out prompts) with the
changes its name says; each seed's run is kept in ``runs/ablation/<arm>/seed<s>`` and reused if it finished, so
an interrupted command picks up where it stopped. It writes ``result.json`` (every number,
per seed), ``report.md`` (mean ± std over seeds, and each arm against the full recipe) and
``curves.png``. Lesson 7 renders its section from these files. With ``COURSE_SMOKE=1`` it runs
shrunk on the tiny model in seconds.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
from collections import Counter
from pathlib import Path

from . import data, stats, train
from .config import PRESETS, load_config, smoke_mode
from .tracks import finished, plot_curves, records

RUNS = Path("runs/ablation")
FULL = "full recipe (the cpu preset)"
# The levers measured on top of the cpu preset; dynamic sampling bounded at 2 rounds, since
# once the policy has settled most groups have no signal and more rounds only cost generation.
WITH_DS = dict(dynamic_sampling=True, max_sampling_rounds=2)
ARMS: dict[str, dict] = {
    FULL: {},
    "with dynamic sampling": WITH_DS,
    "with dynamic sampling and the sharp reward": dict(**WITH_DS, reward="sharp"),
}
# The arm each one adds a lever to, besides the full recipe: one change at a time is compared.
PARENTS = {"with dynamic sampling and the sharp reward": "with dynamic sampling"}
SMOKE = dict(model="tiny-qwen2", prompt_tokens=16, prompts_per_step=2, group_size=4,
             max_new_tokens=10, train_prompts=4, eval_prompts=4, save_every=2, lr=1e-3)
# What a run is judged on: the held-out greedy evaluation after training.
METRICS = [("pass_both", "both constraints", "{:.1%}"),
           ("pass_both_one_digit", "both, one-digit targets", "{:.1%}"),
           ("pass_both_two_digit", "both, two-digit targets", "{:.1%}"),
           ("pass_length", "length", "{:.1%}"),
           ("pass_digits", "digit sum", "{:.1%}"),
           ("distinct_completions", "distinct completions", "{:.1f}")]


def arm_dir(arm: str, seed: int) -> Path:
    slug = "".join(c if c.isalnum() else "-" for c in arm.lower()).strip("-")
    return RUNS / ("smoke" if smoke_mode() else "full") / slug / f"seed{seed}"


def run_arm(arm: str, seed: int) -> Path:
    """Train one arm for one seed, or reuse the run if it finished; returns its directory."""
    out = arm_dir(arm, seed)
    if finished(out):
        return out
    overrides = {**ARMS[arm], **(SMOKE if smoke_mode() else {})}
    # resume=True: a run that stopped part-way (a crash, Ctrl-C) continues where it stopped
    train.train(load_config("cpu", seed=seed, out_dir=str(out), **overrides), resume=True, progress=False)
    return out


def tail_mean(steps: list[dict], key: str, n: int = 5) -> float:
    """A metric at the end of a run: its mean over the last ``n`` logged steps."""
    return statistics.mean(r[key] for r in steps[-n:])


def top_completion(samples: list[dict]) -> str:
    """The most frequent completion among evaluation samples (ties: the first met, so the
    same on every run)."""
    return Counter(s["completion"] for s in samples).most_common(1)[0][0]


def first_pass_step(steps: list[dict]) -> int | None:
    """The first step at which the policy sampled a completion that passes both constraints
    (in the first round, before dynamic sampling's selection), or None if it never did."""
    return next((r["step"] for r in steps if r["first_round_pass_both"] > 0), None)


def arm_result(run_dir: Path) -> dict:
    """The numbers of one run: held-out greedy metrics after training, and its cost."""
    summary = json.loads((run_dir / "summary.json").read_text())
    steps = records(run_dir)
    after = summary["after"]["greedy"]
    return dict(**{key: after[key] for key, _, _ in METRICS},
                before_pass_both=summary["before"]["greedy"]["pass_both"],
                seconds=summary.get("seconds"), steps=len(steps),
                groups_sampled=sum(r.get("groups_sampled", 0) for r in steps),
                first_pass_step=first_pass_step(steps),
                # what passed a two-digit target, if anything did (lesson 7, 6.4 reads it)
                two_digit_pass_completions=sorted({
                    x["completion"] for x in after["samples"] if x["target_digit_sum"] > 9 and
                    x["n_chars"] == x["target_chars"] and x["digit_sum"] == x["target_digit_sum"]}),
                final_entropy=tail_mean(steps, "entropy"),
                final_zero_std_frac=tail_mean(steps, "zero_std_frac"),
                top_completion=top_completion(after["samples"]))


def diagnose(run_dir: Path, entropy_floor: float = 0.5) -> dict:
    """The signs of a run that has stopped learning, read from its files: when the entropy fell
    below ``entropy_floor`` nats per token (3-step average), how many groups had no signal at
    the end, how long the completions were, and what the policy writes on held-out prompts
    (its most frequent greedy completion, and how many distinct ones there are)."""
    run_dir = Path(run_dir)
    steps = records(run_dir)
    summary = json.loads((run_dir / "summary.json").read_text())
    entropy = [r["entropy"] for r in steps]
    smoothed = [statistics.mean(entropy[max(0, i - 2):i + 1]) for i in range(len(entropy))]
    collapse = next((i + 1 for i, e in enumerate(smoothed) if e < entropy_floor), None)
    after = summary["after"]["greedy"]
    texts = [s["completion"] for s in after["samples"]]
    top = top_completion(after["samples"])
    # dynamic sampling's cost: groups sampled beyond the batch's own, before and after the
    # entropy fell below the floor (0 for runs without it, or logged before it existed)
    B = json.loads((run_dir / "config.json").read_text())["prompts_per_step"]
    extra = [r.get("groups_sampled", B) - B for r in steps]
    split = (collapse or len(steps) + 1) - 1
    return dict(steps=len(steps), entropy_start=entropy[0], entropy_end=tail_mean(steps, "entropy"),
                collapse_step=collapse, entropy_floor=entropy_floor,
                zero_std_end=tail_mean(steps, "zero_std_frac"),
                zero_std_max=max(r["zero_std_frac"] for r in steps),
                tokens_start=steps[0]["completion_tokens"],
                tokens_end=tail_mean(steps, "completion_tokens"),
                extra_groups_before=sum(extra[:split]), extra_groups_after=sum(extra[split:]),
                held_out=len(texts), distinct=len(set(texts)), top_completion=top,
                top_count=texts.count(top), top_chars=len(top.strip()),
                pass_both=after["pass_both"], pass_length=after["pass_length"],
                pass_digits=after["pass_digits"])


# How a single-seed probe of a lever ended, judged on its last 5 steps (lesson 7, 6.3).
COLLAPSED = dict(max_distinct_frac=0.25, max_entropy=0.2)   # one sentence for every prompt
CAP_FILLING = dict(min_truncated_frac=0.9)                  # text cut off at max_new_tokens


def probe_outcome(steps: list[dict]) -> str:
    """Name how a run's last 5 steps look: collapsed onto one sentence, filling the token cap,
    or still exploring (the rules are COLLAPSED and CAP_FILLING above)."""
    if tail_mean(steps, "distinct_frac") <= COLLAPSED["max_distinct_frac"] and \
            tail_mean(steps, "entropy") <= COLLAPSED["max_entropy"]:
        return "collapsed onto one sentence"
    if tail_mean(steps, "truncated_frac") >= CAP_FILLING["min_truncated_frac"]:
        return "filling the token cap"
    return "still exploring"


def stored_runs(folder: Path, marker: str) -> list[Path]:
    """The run folders in ``folder`` that hold ``marker`` (a file every run of a table has)."""
    return sorted(p for p in Path(folder).iterdir() if (p / marker).exists())


def changes(config: dict, ignore: set[str]) -> str:
    """How a stored run's config differs from the cpu preset, as "name value, ..."."""
    preset = load_config("cpu").to_dict()
    return ", ".join(f"{k} {config[k]}" for k in config if k not in ignore and config[k] != preset.get(k))


def probes(folder: Path) -> str:
    """A markdown table of single-seed probes of other levers (one run per sub-folder, each the
    cpu preset with the changes its config.json records), read from their stored files."""
    ignore = {"seed", "out_dir", "max_steps"}
    lines = ["| change to the cpu preset | seed | steps run | sampled pass (both), last 5 steps | "
             "length pass (batch trained on), last 5 | entropy, last 5 | distinct completions "
             "per batch, last 5 | how it ended | held-out greedy pass (both) |", "|" + "---|" * 9]
    for run in stored_runs(folder, "metrics.jsonl"):
        config = json.loads((run / "config.json").read_text())
        steps = records(run)
        mean = lambda key: tail_mean(steps, key)  # noqa: E731
        change = changes(config, ignore)
        summary = json.loads((run / "summary.json").read_text()) if (run / "summary.json").exists() else {}
        held_out = "not evaluated (stopped by hand)"
        if "after" in summary:
            after = summary["after"]["greedy"]
            top = top_completion(after["samples"]).strip().replace("|", "/")
            held_out = f"{after['pass_both']:.1%}, most often `{top}`"
        lines.append(f"| {change} | {config['seed']} | {len(steps)} of {config['max_steps']} | "
                     f"{mean('first_round_pass_both'):.1%} | {mean('pass_length'):.1%} | "
                     f"{mean('entropy'):.2f} | {mean('distinct_frac'):.0%} | {probe_outcome(steps)} | "
                     f"{held_out} |")
    return "\n".join(lines) + "\n"


def template_probes(folder: Path) -> str:
    """A markdown table of the tuning runs aimed at the template (one run per sub-folder, each
    the cpu preset with the changes its config.json records): held-out greedy pass rates split
    by the number of digits the target needs, and what the policy writes, from stored files."""
    ignore = {"seed", "out_dir", "max_steps", "epochs"}
    lines = ["| change to the cpu preset | seed | steps | held-out greedy pass (both) | one-digit "
             "targets | two-digit targets | length pass | digit-sum pass | distinct completions "
             "(of the held-out prompts) | most frequent completion |", "|" + "---|" * 10]
    for run in stored_runs(folder, "summary.json"):
        config = json.loads((run / "config.json").read_text())
        summary = json.loads((run / "summary.json").read_text())
        after = summary["after"]["greedy"]
        change = changes(config, ignore)
        top = top_completion(after["samples"]).strip().replace("|", "/")
        lines.append(f"| {change} | {config['seed']} | {summary['steps']} | {after['pass_both']:.1%} | "
                     f"{after['pass_both_one_digit']:.1%} | {after['pass_both_two_digit']:.1%} | "
                     f"{after['pass_length']:.1%} | {after['pass_digits']:.1%} | "
                     f"{after['distinct_completions']} of {len(after['samples'])} | `{top}` |")
    return "\n".join(lines) + "\n"


def _cell(text: str) -> str:
    """A completion as one markdown table cell: no pipe, no line break."""
    return text.replace("|", "/").replace("\n", " ")


def completions_by_target(runs: list[Path], labels: list[str] | None = None) -> str:
    """What each run's policy writes per target digit sum (held-out, greedy): the prompts with
    that target, how many pass both constraints, and the most frequent completion with the digit
    sum it has (a markdown table, one column group per run, read from stored summaries). Each
    group is named by ``labels``, or by the run's seed."""
    afters = [json.loads((run / "summary.json").read_text())["after"]["greedy"]["samples"]
              for run in runs]
    if labels is None:
        labels = [f"seed {json.loads((run / 'config.json').read_text())['seed']}" for run in runs]
    if len(labels) != len(runs):
        raise ValueError(f"{len(labels)} labels for {len(runs)} runs")
    header = "| target digit sum | " + " | ".join(
        f"{label}: passed | most frequent completion (its digit sum)" for label in labels) + " |"
    # a tie for the most frequent completion is broken by prompt order (top_completion) and
    # said in the cell, so the table never presents an arbitrary pick as the policy's habit
    lines = [header, "|" + "---|" * (1 + 2 * len(runs))]
    targets = sorted({s["target_digit_sum"] for samples in afters for s in samples})
    for target in targets:
        cells = []
        for samples in afters:
            mine = [s for s in samples if s["target_digit_sum"] == target]
            passed = sum(s["n_chars"] == s["target_chars"] and s["digit_sum"] == target for s in mine)
            # most_common keeps first-met order among equal counts: top_completion's tie rule
            counts = Counter(s["completion"] for s in mine).most_common()
            top = counts[0][0].strip() if mine else ""
            sums = {s["digit_sum"] for s in mine if s["completion"].strip() == top}
            tied = sum(n == counts[0][1] for _, n in counts) - 1 if mine else 0
            tie = f"; tied with {tied} other{'s' if tied > 1 else ''} at {counts[0][1]} each" if tied else ""
            cells += [f"{passed} of {len(mine)}", f"`{_cell(top)}` ({', '.join(map(str, sorted(sums)))}{tie})"
                      if mine else "-"]
        lines.append(f"| {target} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def against_preset(runs: list[Path], result: dict) -> str:
    """Held-out greedy pass rates of ``runs`` (one per seed) minus those of the ablation's
    full-recipe arm (``result``, a stored result.json) on the same seeds, through
    ``stats.paired`` (a markdown list: both constraints, then the two-digit targets)."""
    seeds = [json.loads((run / "config.json").read_text())["seed"] for run in runs]
    preset = dict(zip(result["seeds"], result["arms"][FULL]["runs"]))
    if not set(seeds) <= set(preset):
        raise ValueError(f"the preset's stored runs have seeds {sorted(preset)}, not all of {seeds}")
    afters = [json.loads((run / "summary.json").read_text())["after"]["greedy"] for run in runs]
    lines = []
    for key, what in (("pass_both", "both constraints"), ("pass_both_two_digit", "two-digit targets")):
        comparison = stats.paired([a[key] for a in afters], [preset[s][key] for s in seeds])
        values = ", ".join(f"seed {s}: {a[key]:.1%} vs {preset[s][key]:.1%}" for s, a in zip(seeds, afters))
        lines.append(f"- {what} ({values}): {comparison.verdict('{:+.1%}')}")
    return "\n".join(lines) + "\n"


def paired_arms(a: list[Path], b: list[Path], names: tuple[str, str]) -> str:
    """Two arms run on the same seeds (``a[i]`` and ``b[i]`` share a seed): a markdown table of
    each seed's held-out greedy pass rates and distinct completions in both arms, and each arm's
    entropy over its last 5 logged steps; then arm a minus arm b, paired by seed through
    ``stats.paired``, for both constraints and for the two-digit targets."""
    def read(run: Path) -> tuple[int, dict, list[dict]]:
        config = json.loads((run / "config.json").read_text())
        return config["seed"], json.loads((run / "summary.json").read_text())["after"]["greedy"], records(run)
    rows_a, rows_b = [read(r) for r in a], [read(r) for r in b]
    if [s for s, _, _ in rows_a] != [s for s, _, _ in rows_b] or len(rows_a) < 2:
        raise ValueError(f"paired arms need the same seeds, in order, at least 2: "
                         f"{[s for s, _, _ in rows_a]} and {[s for s, _, _ in rows_b]}")
    A, B = names
    lines = [f"| seed | {A}: both | {A}: one-digit | {A}: two-digit | {A}: distinct | {A}: entropy, "
             f"last 5 steps | {B}: both | {B}: one-digit | {B}: two-digit | {B}: distinct | {B}: "
             f"entropy, last 5 steps |", "|" + "---|" * 11]
    for (seed, x, sx), (_, y, sy) in zip(rows_a, rows_b):
        cells = []
        for after, steps in ((x, sx), (y, sy)):
            cells += [f"{after['pass_both']:.1%}", f"{after['pass_both_one_digit']:.1%}",
                      f"{after['pass_both_two_digit']:.1%}", f"{after['distinct_completions']}",
                      f"{tail_mean(steps, 'entropy'):.2f}"]
        lines.append(f"| {seed} | " + " | ".join(cells) + " |")
    lines.append("")
    for key, what in (("pass_both", "both constraints"), ("pass_both_two_digit", "two-digit targets")):
        comparison = stats.paired([x[key] for _, x, _ in rows_a], [y[key] for _, y, _ in rows_b])
        lines.append(f"- {A} minus {B}, {what}: {comparison.verdict('{:+.1%}')}")
    return "\n".join(lines) + "\n"


def cap_probes(runs: list[Path], recipe: dict) -> str:
    """A markdown table of single-seed probes against the token-cap hack (lesson 7, 6.6): each
    run's change to the frozen recipe (``recipe``, a stored config), the precision it computed
    in, how its last 5 steps look (the share cut off at the cap, the tokens per reply,
    ``probe_outcome``), and its held-out greedy pass rates and completions, from stored files."""
    ignore = {"seed", "out_dir"}
    lines = ["| seed | change to the frozen recipe | precision | cut off at the cap, last 5 steps | "
             "tokens per reply, last 5 | how it ended | held-out greedy pass (both) | one-digit "
             "targets | two-digit targets | distinct completions | most frequent completion |",
             "|" + "---|" * 11]
    for run in runs:
        config = json.loads((run / "config.json").read_text())
        summary = json.loads((run / "summary.json").read_text())
        after, steps = summary["after"]["greedy"], records(run)
        change = ", ".join(f"{k} {config[k]}" for k in config
                           if k not in ignore and config[k] != recipe.get(k)) or "none"
        top = _cell(top_completion(after["samples"]).strip())
        lines.append(f"| {config['seed']} | {change} | {summary.get('precision', 'not recorded')} | "
                     f"{tail_mean(steps, 'truncated_frac'):.0%} | "
                     f"{tail_mean(steps, 'completion_tokens'):.1f} | {probe_outcome(steps)} | "
                     f"{after['pass_both']:.1%} | {after['pass_both_one_digit']:.1%} | "
                     f"{after['pass_both_two_digit']:.1%} | {after['distinct_completions']} of "
                     f"{len(after['samples'])} | `{top}` |")
    return "\n".join(lines) + "\n"


def sampled_passes(run: Path, width: int = 10) -> list[dict]:
    """How a run's sampled replies fared in training, ``width`` logged steps at a time: the
    first and last step of each window, and the replies to one-digit and two-digit targets
    that passed both constraints, out of those sampled. Each step samples prompts_per_step x
    group_size replies; with dynamic sampling the batch varies, and the log cannot say it."""
    config = json.loads((run / "config.json").read_text())
    if config.get("dynamic_sampling"):
        raise ValueError(f"{run}: dynamic sampling varies the batch, so its passes cannot be counted from the log")
    per_step = config["prompts_per_step"] * config["group_size"]
    steps, windows = records(run), []
    for start in range(0, len(steps), width):
        window = steps[start:start + width]
        two_sampled = sum(r["samples_two_digit"] for r in window)
        two_passed = sum(r["passes_two_digit"] for r in window)
        passed = sum(round(r["pass_both"] * per_step) for r in window)
        windows.append({"first": window[0]["step"], "last": window[-1]["step"],
                        "one_passed": passed - two_passed, "one_sampled": per_step * len(window) - two_sampled,
                        "two_passed": two_passed, "two_sampled": two_sampled})
    return windows


def sampled_passes_table(runs: list[Path], labels: list[str], width: int = 10) -> str:
    """``sampled_passes`` of several runs side by side (a markdown table: one row per window
    of ``width`` steps, for each run the share of one-digit and of two-digit replies passed)."""
    if len(labels) != len(runs):
        raise ValueError(f"{len(labels)} labels for {len(runs)} runs")
    tables = [sampled_passes(run, width) for run in runs]
    if len({len(t) for t in tables}) != 1:
        raise ValueError("the runs logged different numbers of steps")
    share = lambda passed, sampled: f"{passed / sampled:.0%}" if sampled else "-"  # noqa: E731
    lines = ["| steps | " + " | ".join(f"{label}: one-digit | {label}: two-digit" for label in labels) + " |",
             "|" + "---|" * (1 + 2 * len(runs))]
    for row in zip(*tables):
        cells = [c for w in row for c in (share(w["one_passed"], w["one_sampled"]),
                                          share(w["two_passed"], w["two_sampled"]))]
        lines.append(f"| {row[0]['first']}-{row[0]['last']} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def seed_table(runs: list[Path], level: float = 0.95) -> str:
    """One recipe over several seeds (one run per seed): a markdown table of each seed's
    held-out greedy pass rates (both constraints, then split by the digits a target needs), its
    distinct completions, its most frequent one, how many sampled completions passed a two-digit
    target in training, how its last steps look (``probe_outcome``), and its wall time; then the mean over seeds with a Student-t interval on
    n - 1 degrees of freedom (clipped to the possible 0-100%), and the worst seed. Nothing here
    is paired: it describes one arm."""
    if len(runs) < 2:
        raise ValueError(f"a seed table needs at least 2 runs, got {len(runs)}")
    keys = ("pass_both", "pass_both_one_digit", "pass_both_two_digit")
    lines = ["| seed | held-out greedy pass (both) | one-digit targets | two-digit targets | distinct "
             "completions | most frequent completion | two-digit passes sampled in training | how "
             "it ended | seconds |", "|" + "---|" * 9]
    values: dict[str, list[float]] = {k: [] for k in keys}
    for run in runs:
        config = json.loads((run / "config.json").read_text())
        summary = json.loads((run / "summary.json").read_text())
        after, steps = summary["after"]["greedy"], records(run)
        for k in keys:
            values[k].append(after[k])
        top = _cell(top_completion(after["samples"]).strip())
        lines.append(f"| {config['seed']} | {after['pass_both']:.1%} | {after['pass_both_one_digit']:.1%} | "
                     f"{after['pass_both_two_digit']:.1%} | {after['distinct_completions']} of "
                     f"{len(after['samples'])} | `{top}` | {sum(r['passes_two_digit'] for r in steps)} of "
                     f"{sum(r['samples_two_digit'] for r in steps)} | {probe_outcome(steps)} | "
                     f"{summary['seconds']:.0f} |")
    n = len(runs)
    t = stats.t_quantile(0.5 + level / 2, n - 1)

    def mean_cell(k: str) -> str:
        m, half = statistics.fmean(values[k]), t * statistics.stdev(values[k]) / math.sqrt(n)
        return f"{m:.1%} [{max(0.0, m - half):.1%}, {min(1.0, m + half):.1%}]"
    lines.append(f"| mean, {level:.0%} t-interval ({n - 1} df) | " +
                 " | ".join(mean_cell(k) for k in keys) + " | | | | | |")
    lines.append("| worst seed | " + " | ".join(f"{min(values[k]):.1%}" for k in keys) + " | | | | | |")
    return "\n".join(lines) + "\n"


def template_probe_logs(folder: Path) -> str:
    """What the template probes' training logs say about the two-digit targets: how many
    completions were sampled for them and how many passed, their share of the samples early and
    late, and the entropy and adaptive entropy weight late in the run (a markdown list)."""
    lines = []
    for run in stored_runs(folder, "metrics.jsonl"):
        config = json.loads((run / "config.json").read_text())
        steps = records(run)
        quarter = max(1, len(steps) // 4)
        per_step = config["prompts_per_step"] * config["group_size"]

        def share(rows: list[dict]) -> float:
            return sum(r["samples_two_digit"] for r in rows) / (len(rows) * per_step)
        lines.append(
            f"- `{run.name}`: {sum(r['samples_two_digit'] for r in steps)} sampled completions "
            f"for two-digit targets, {sum(r['passes_two_digit'] for r in steps)} of them passing; "
            f"the two-digit targets' share of the samples {share(steps[:quarter]):.0%} in the "
            f"first quarter of the run and {share(steps[-quarter:]):.0%} in the last; entropy in "
            f"the last quarter {tail_mean(steps, 'entropy', quarter):.2f} nats per token "
            f"(entropy_target {config['entropy_target']}), adaptive entropy weight at most "
            f"{max(r['entropy_weight'] for r in steps):.3f} (cap {config['entropy_weight_max']})")
    return "\n".join(lines) + "\n"


def ablation(seeds: list[int], out: Path, arms: list[str] | None = None,
             train_missing: bool = True) -> dict:
    """Train (or reuse) every arm for every seed, then write the report; ``arms`` restricts
    the arms (by their names in ``ARMS``), the full recipe always included. With
    ``train_missing=False`` only finished runs are reported, and the table says how many
    seeds each arm has."""
    chosen = [FULL] + [a for a in (arms or ARMS) if a != FULL]
    unknown = [a for a in chosen if a not in ARMS]
    if unknown:
        raise SystemExit(f"error: unknown arm(s) {unknown}; arms: {list(ARMS)}")
    if train_missing:
        dirs = {arm: [run_arm(arm, s) for s in seeds] for arm in chosen}
    else:
        dirs = {arm: [arm_dir(arm, s) for s in seeds if finished(arm_dir(arm, s))] for arm in chosen}
        dirs = {arm: ds for arm, ds in dirs.items() if ds}
    results = {arm: [arm_result(d) for d in ds] for arm, ds in dirs.items()}
    plot_curves(dirs, [("first_round_pass_both", "sampled pass rate (both), before selection"),
                       ("entropy", "entropy (nats/token)"), ("zero_std_frac", "groups without signal"),
                       ("chars_abs_error", "|chars - 32|")], out / "curves.png")
    first_summary = json.loads((next(iter(dirs.values()))[0] / "summary.json").read_text())
    held = first_summary["after"]["greedy"]
    result = dict(seeds=seeds, arms={arm: dict(overrides=ARMS[arm], runs=rows, dirs=[str(d) for d in dirs[arm]])
                                     for arm, rows in results.items()},
                  preset=PRESETS["cpu"],
                  held_out=dict(prompts=len(held["samples"]), snippets=held["distinct_snippets"]))
    return write_report(result, out)


def held_out_size(result: dict) -> dict:
    """The held-out set's size: as stored, or (for a result.json written before it was stored)
    that of the cpu preset the result records, which every stored arm used."""
    if "held_out" in result:
        return result["held_out"]
    snippets = sum(data.is_held_out(s) for s in data.offline_snippets())
    prompts = result.get("preset", PRESETS["cpu"])["eval_prompts"]
    return dict(prompts=prompts, snippets=min(prompts, snippets))


def comparisons(result: dict) -> list[str]:
    """Each arm against the full recipe, and against the arm it adds one lever to (``PARENTS``),
    paired by seed (``course_utils.stats``): the arms share seeds, so they share prompts,
    targets and, until they part, samples. Only the seeds both arms have are compared, and of
    those only the ones whose held-out set has the kind of target compared."""
    arms = result["arms"]
    seeds = lambda arm: [Path(d).name.removeprefix("seed") for d in arms[arm]["dirs"]]  # noqa: E731
    pairs = [(arm, FULL) for arm in arms if arm != FULL and FULL in arms]
    pairs += [(arm, parent) for arm, parent in PARENTS.items() if arm in arms and parent in arms]
    lines = []
    for arm, base in pairs:
        for key, label in (("pass_both", "held-out pass rate (both)"),
                           ("pass_both_two_digit", "two-digit targets")):
            value = lambda a: {s: r[key] for s, r in zip(seeds(a), arms[a]["runs"])}  # noqa: E731
            a, b = value(arm), value(base)
            shared = [s for s in seeds(arm) if s in b]
            usable = [s for s in shared if math.isfinite(a[s]) and math.isfinite(b[s])]
            lacking = f" (no such target on seed(s) {', '.join(sorted(set(shared) - set(usable)))})" \
                if len(usable) < len(shared) else ""
            if len(usable) < 2:
                verdict = f"{len(usable)} shared seed(s) with such targets: too few to compare"
            else:
                verdict = stats.paired([a[s] for s in usable], [b[s] for s in usable]).verdict("{:+.1%}")
            name = "the full recipe" if base == FULL else f"the arm '{base}'"
            lines.append(f"- {arm} minus {name}, {label}, seeds {', '.join(usable)}{lacking}: {verdict}")
    return lines


def write_report(result: dict, out: Path) -> dict:
    """``report.md`` and ``result.json`` in ``out`` from the per-seed results (``curves.png`` is
    drawn by ``ablation`` from the runs themselves). ``--rerender`` calls this on a stored
    result.json, so a change to the report's wording or statistics needs no run."""
    arms = result["arms"]
    header = ("| arm | seeds | both constraints, per seed | first sampled pass, step per seed | " +
              " | ".join(label for _, label, _ in METRICS) + " | seconds | groups sampled |")
    lines = [header, "|" + "---|" * (len(METRICS) + 6)]
    for arm, row in arms.items():
        rows = row["runs"]
        cells = []
        for key, _, fmt in METRICS:
            values = [r[key] for r in rows if not math.isnan(r[key])]  # nan: no such target
            if not values:
                cells.append("n/a")
                continue
            cell = fmt.format(statistics.mean(values))
            if len(values) > 1:  # one seed has no spread to show
                cell += " ± " + fmt.format(statistics.stdev(values))
            cells.append(cell)
        seconds = statistics.mean(r["seconds"] for r in rows)
        groups = statistics.mean(r["groups_sampled"] for r in rows)
        seeds_of = ", ".join(Path(d).name.removeprefix("seed") for d in row["dirs"])
        per_seed = ", ".join(f"{r['pass_both']:.1%}" for r in rows)
        first = ", ".join(str(r["first_pass_step"] or "never") for r in rows)
        lines.append(f"| {arm} | {seeds_of} | {per_seed} | {first} | " + " | ".join(cells) +
                     f" | {seconds:.0f} | {groups:.0f} |")
    result = {**result, "verdicts": comparisons(result)}
    missing = [arm for arm in ARMS if arm not in arms]
    held = held_out_size(result)
    report = (f"Held-out greedy evaluation after training ({held['prompts']} prompts built "
              f"from {held['snippets']} distinct held-out snippets, each with its own "
              "drawn digit-sum target; mean ± std over the seeds listed, the "
              "value alone for one seed; every "
              "arm is the `cpu` preset with the changes its name says; first sampled pass: the first training step "
              "whose first round of samples held a completion passing both constraints; seconds: "
              "wall time of a run, evaluation included, not a speed comparison, since some runs "
              "shared the machine with other work; groups sampled: over the whole run, the "
              "cost that does compare). Each arm against the full recipe, seed by seed "
              "(`course_utils.stats.paired`: 95% t-interval on n - 1 degrees of freedom, exact "
              "sign-flip test, and the smallest difference the seeds could detect):\n\n" +
              "\n".join(lines) + "\n\n" +
              ("\n".join(result["verdicts"]) + "\n" if result["verdicts"] else "") +
              (f"\nNot run yet: {', '.join(missing)}.\n" if missing else ""))
    out.mkdir(parents=True, exist_ok=True)
    (out / "report.md").write_text(report)
    (out / "result.json").write_text(json.dumps(result, indent=2))
    print(report)
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m course_utils.ablation", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--out", type=Path, default=Path("runs/ablation/report"))
    parser.add_argument("--arms", nargs="+", default=None, help="arm names (default: all)")
    parser.add_argument("--report-only", action="store_true",
                        help="train nothing: report the runs that have finished")
    parser.add_argument("--rerender", action="store_true",
                        help="train and read no run: rewrite report.md from the result.json in --out")
    args = parser.parse_args(argv)
    if args.rerender:
        stored = args.out / "result.json"
        if not stored.is_file():
            raise SystemExit(f"error: --rerender needs {stored}; run the ablation into --out first")
        write_report(json.loads(stored.read_text()), args.out)
        return 0
    ablation(args.seeds, args.out, args.arms, train_missing=not args.report_only)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
