"""Every figure a lesson's prose quotes, computed from a stored result file.

A lesson writes ``{{fig:NAME}}`` where a number belongs; ``build.py`` fills it in from
``figures()``. The T4 plan's figures come from ``course_utils.plan`` (arithmetic, the same
functions the lesson's cells print from), the rest from ``notebooks/results/``. No figure is
typed into prose: ``tests/test_figures.py`` fails on one that is, so a re-run that changes a
result changes the sentence that quotes it.
"""

from __future__ import annotations

import collections
import json
import math
import re
import statistics
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def _json(relative: str) -> dict:
    return json.loads((RESULTS / relative).read_text())


def _table_cell(relative: str, row: str, column: int) -> str:
    """A cell of a markdown table in a stored report: the row whose first cell is ``row``."""
    for line in (RESULTS / relative).read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if cells and cells[0] == row:
            return cells[column]
    raise KeyError(f"{relative} has no table row {row!r}")


def _mean_std(values: list[float], fmt: str) -> str:
    return f"{statistics.mean(values):{fmt}} ± {statistics.stdev(values):{fmt.lstrip('+')}}"


def _word(n: int) -> str:
    """A count as the prose spells it: 'three' (numerals above twelve)."""
    words = "zero one two three four five six seven eight nine ten eleven twelve".split()
    return words[n] if 0 <= n < len(words) else f"{n}"


def _seeds(values: list, fmt: str = "") -> str:
    """'11, 6 and 10' (None for 'never')."""
    words = ["never" if v is None else f"{v:{fmt}}" for v in values]
    return ", ".join(words[:-1]) + " and " + words[-1] if len(words) > 1 else words[0]


def _paired(a: list[float], b: list[float], fmt: str = "+.3f") -> str:
    """Arm a minus arm b over shared seeds, as tracks.differs computes it (course_utils.stats):
    '+0.059, 95% t-interval [+0.019, +0.099]'."""
    from course_utils import stats

    cmp = stats.paired(a, b)
    low, high = cmp.interval
    return f"{cmp.mean:{fmt}}, 95% t-interval [{low:{fmt}}, {high:{fmt}}]"


def _detectable(a: list[float], b: list[float], fmt: str = ".3f") -> str:
    """The smallest difference the seeds could detect (80% power, from the observed spread)."""
    from course_utils import stats

    return f"{stats.paired(a, b).detectable:{fmt}}"


def _seeds_above(a: list[float], b: list[float]) -> str:
    """On how many seeds arm a ended above arm b: 'every one of the 3', or 'k of the n' (the
    prose says "above"; a rerun that flips the direction changes the count, not the word)."""
    above = sum(x > y for x, y in zip(a, b))
    return f"every one of the {len(a)}" if above == len(a) else f"{above} of the {len(a)}"


def plan_figures() -> dict[str, str]:
    """Lesson 7, section 2: the T4 preset's memory and time plan."""
    from course_utils import plan
    from course_utils.config import PRESETS, Config

    arch, t4 = plan.QWEN25_05B, Config.from_dict(PRESETS["t4"])
    prompt_len = plan.qwen25_prompt_len(t4)   # as in the lesson's cell
    persistent = 4 + 4 + 8 + 2     # fp32 weight, gradient, AdamW's two moments, fp16 copy
    accum8 = Config.from_dict({**PRESETS["t4"], "grad_accum": 8})
    mem8 = plan.memory_plan(arch, accum8, prompt_len, t4.max_new_tokens)
    mem = plan.memory_plan(arch, t4, prompt_len, t4.max_new_tokens)
    timing = plan.time_plan(arch, t4, prompt_len, t4.max_new_tokens)
    room = lambda m: f"{1 - plan.reserved_bytes(m) / plan.T4.reservable_bytes:.0%}"
    return {
        "plan.bytes_per_param": f"{persistent}",
        "plan.params_m": f"{arch.n_params / 1e6:.0f}M",
        "plan.persistent_gib": f"{persistent * arch.n_params / plan.GiB:.1f}",
        "plan.vocab": f"{arch.vocab:,}",
        "plan.logits_mb_per_token": f"{arch.vocab * 4 / 1e6:.1f}",
        "plan.t4_prompts": f"{t4.train_prompts:,}",
        "plan.t4_steps": f"{t4.total_steps}",
        "plan.t4_hours": f"{timing['run hours']:.1f}",
        "plan.t4_total_gib": f"{plan.T4.total_memory_gib:.2f}",
        "plan.t4_outside_gib": f"{plan.T4.outside_allocator_gib:.1f}",
        "plan.t4_reservable_gib": f"{plan.T4.reservable_bytes / plan.GiB:.2f}",
        "plan.t4_cache_pct": f"{plan.T4.allocator_cache:.0%}",
        "plan.t4_snippet_tokens": f"{t4.prompt_tokens}",
        "plan.t4_frame_tokens": f"{prompt_len - t4.prompt_tokens}",
        "plan.t4_reserved_gib": f"{plan.reserved_bytes(mem) / plan.GiB:.1f}",
        "plan.t4_headroom_pct": room(mem),
        "plan.accum8_logits_gib": f"{mem8['logits (completion positions)'] / plan.GiB:.1f}",
        "plan.accum8_reserved_gib": f"{plan.reserved_bytes(mem8) / plan.GiB:.1f}",
        "plan.accum8_headroom_pct": room(mem8),
        "plan.lora16_params_m": f"{arch.lora_params(16) / 1e6:.1f}M",
    }


def gpu_check_figures() -> dict[str, str]:
    """Lesson 7, section 4: benchmarks/gpu_check.py's stored runs on a GPU emulating a T4, at the
    t4 preset (grad_accum 16) and with twice the rows per micro-batch (grad_accum 8)."""
    runs = {"gpu": _json("gpu-check.json"), "gpu.accum8": _json("gpu-check-grad-accum-8.json")}
    out = {}
    for prefix, r in runs.items():
        m, p = r["measured"], r["planned"]
        out.update({
            f"{prefix}.reserved_gib": f"{m['reserved_gib']:.2f}",
            f"{prefix}.plan_reserved_gib": f"{p['reserved_gib']:.2f}",
            f"{prefix}.reserved_vs_plan": f"{m['reserved_gib'] / p['reserved_gib'] - 1:+.1%}",
            f"{prefix}.allocated_gib": f"{m['allocated_gib']:.2f}",
            f"{prefix}.plan_tensors_gib": f"{p['tensors_gib']:.2f}",
            f"{prefix}.allocated_vs_plan": f"{m['allocated_gib'] / p['tensors_gib'] - 1:+.1%}",
            f"{prefix}.cache_pct": f"{m['allocator_cache']:.0%}",
            f"{prefix}.rows": f"{r['micro_batch_rows']}",
        })
    r = runs["gpu"]
    copies = r["probes"]["autocast_copies"]
    out.update({
        "gpu.name": r["emulation"]["gpu"],
        "gpu.cap_gib": f"{r['emulation']['allocator_cap_gib']:.2f}",
        "gpu.outside_gib": f"{r['measured']['outside_allocator_gib']:.2f}",
        "gpu.steps": _word(r["steps"]),
        "gpu.prompt_len": f"{r['prompt_len']}",
        "gpu.copies_gib": " and ".join(f"{x:.2f}" for x in copies["forward_extra_gib"]),
        "gpu.plan_copies_gib": f"{copies['planned_copies_gib']:.2f}",
        "gpu.copies_held_after_gib": f"{max(copies['held_after_gib']):.2f}",
        "gpu.step_s": f"{statistics.median(r['step_seconds']):.1f}",
        "gpu.plan_t4_step_s": f"{r['planned']['seconds_per_step_t4']:.1f}",
        "gpu.nonfinite_skipped": _word(r["nonfinite_skipped"]),
        "gpu.scaler_scale": " and ".join(f"{s:g}" for s in sorted(set(r["scaler_scale"]))),
    })
    return out


def track_figures() -> dict[str, str]:
    """Lesson 8: the learner tracks' stored results (``python -m course_utils.tracks all``)."""
    from course_utils.config import PRESETS, Config

    base = "tracks/base_model/report.md"
    serving, entropy = _json("tracks/serving/result.json"), _json("tracks/entropy/result.json")
    kl, grouping = _json("tracks/kl/result.json"), _json("tracks/grouping/result.json")
    fp32, int8 = serving["fp32"], serving["int8 (dynamic)"]
    rewards, late = entropy["final_reward"], entropy["late_entropy"]
    kl_reward, kl_delta = kl["final_reward"], kl["delta_loglik"]
    est = grouping["exact"]["estimators"]
    grpo, dr = est["per-prompt mean and std (GRPO)"], est["per-prompt mean only (Dr. GRPO)"]
    others = [dr, est["whole-batch mean and std (the seed)"], est["whole-batch mean only"]]
    batch = others[1]
    g_final = grouping["final_reward"]

    def p50(arm: dict, cache: bool) -> float:
        return arm[f"cache={cache}"]["p50_s"] * 1000

    def miss(row: str, column: int, fmt: str) -> str:
        """'104.406 ± 2.993' in the base-model report, reformatted ('104' or '26.5 ± 3.2')."""
        parts = _table_cell(base, f"mean abs(chars - 32) ({row})", column).split(" ± ")
        return " ± ".join(f"{float(p):{fmt}}" for p in parts)

    from course_utils.config import load_config
    from course_utils.tracks import SHORT

    # the tracks' training runs are shared, so every track ran on the same seeds (the base-model
    # track's count is in its report: "SmolLM2 with raw prompts (3 seeds)")
    seed_counts = {len(runs) for result in (entropy["final_reward"], kl_reward, g_final,
                                            _json("tracks/retrieval/result.json")["final_reward"])
                   for runs in result.values()}
    seed_counts.add(int(re.search(r"\((\d+) seeds\)", (RESULTS / base).read_text()).group(1)))
    if len(seed_counts) != 1:
        raise ValueError(f"the stored tracks ran on different numbers of seeds: {seed_counts}")

    return {
        "tracks.steps": f"{load_config('cpu', **SHORT).total_steps}",
        "tracks.seeds": _word(seed_counts.pop()),
        "t4.steps": f"{Config.from_dict(PRESETS['t4']).total_steps}",
        "gpt2.steps": f"{Config.from_dict(PRESETS['gpt2-rtx4070']).total_steps}",
        # 1. base model
        "base.miss_sampled": f"{miss('sampled', 1, '.0f').split()[0]} to {miss('sampled', 2, '.0f').split()[0]}",
        "base.miss_greedy": f"{miss('greedy', 1, '.0f').split()[0]} to {miss('greedy', 2, '.0f').split()[0]}",
        "base.miss_greedy_after": miss("greedy", 2, ".1f"),
        "serving.miss_fp32": f"{fp32['chars_error']:.1f}",
        # 2. serving
        "serving.cache_fp32": f"{p50(fp32, False) / p50(fp32, True):.1f}x",
        "serving.cache_int8": f"{p50(int8, False) / p50(int8, True):.1f}x",
        "serving.p50_fp32": f"{p50(fp32, True):.0f} ms",
        "serving.p50_fp32_nocache": f"{p50(fp32, False):.0f} ms",
        "serving.p50_int8": f"{p50(int8, True):.0f} ms",
        "serving.int8_speedup": f"{p50(fp32, True) / p50(int8, True):.1f}x",
        "serving.mib_fp32": f"{serving['state_dict_mib']['fp32']:.0f} MiB",
        "serving.mib_int8": f"{serving['state_dict_mib']['int8']:.0f} MiB",
        "serving.memory_ratio": f"{serving['state_dict_mib']['fp32'] / serving['state_dict_mib']['int8']:.1f}x",
        "serving.miss_int8": f"{int8['chars_error']:.1f}",
        "serving.reward_fp32": f"{fp32['reward']:.3f}",
        "serving.reward_int8": f"{int8['reward']:.3f}",
        # 3. entropy bonus
        "entropy.steps_none": _seeds(entropy["steps_to_threshold"]["none"]),
        "entropy.late_dynamic": f"{statistics.mean(late['inverse variance (1e-3 / Var)']):.1f}",
        "entropy.late_none": f"{statistics.mean(late['none']):.1f}",
        "entropy.final_constant": f"{statistics.mean(rewards['constant 0.05']):.3f}",
        "entropy.final_none": f"{statistics.mean(rewards['none']):.3f}",
        "entropy.diff_constant_none": _paired(rewards["constant 0.05"], rewards["none"]),
        "entropy.seeds_constant_none": _seeds_above(rewards["constant 0.05"], rewards["none"]),
        # 4. KL schedule
        "kl.delta_plain": _mean_std(kl_delta["plain GRPO (no KL)"], "+.3f"),
        "kl.final_aware": f"{statistics.mean(kl_reward['reward-aware KL 0.04']):.3f}",
        "kl.final_plain": f"{statistics.mean(kl_reward['plain GRPO (no KL)']):.3f}",
        "kl.worse_aware": f"{kl['falsifier']['reward-aware KL 0.04']['worse']} of "
                          f"{kl['falsifier']['reward-aware KL 0.04']['of']}",
        "kl.worse_constant": f"{kl['falsifier']['constant KL 0.04']['worse']} of "
                             f"{kl['falsifier']['constant KL 0.04']['of']}",
        # 5. grouping
        "grouping.batches": f"{grouping['exact']['batches']:,}",
        "grouping.noise_per_prompt": f"{min(grpo['noise_to_signal'], dr['noise_to_signal']):.2f}-"
                                     f"{max(grpo['noise_to_signal'], dr['noise_to_signal']):.2f}",
        "grouping.noise_batch": f"{batch['noise_to_signal']:.2f}",
        "grouping.weights_grpo": _seeds(grpo["weight_per_prompt"], ".2f"),
        "grouping.error_grpo": f"{grpo['direction_error']:.3f}",
        "grouping.error_others": f"{min(e['direction_error'] for e in others):.3f}-"
                                 f"{max(e['direction_error'] for e in others):.3f}",
        "grouping.error_ratio": f"{grpo['direction_error'] / max(e['direction_error'] for e in others):.0f}",
        "grouping.cosine_grpo": f"{grpo['cosine']:.3f}",
        "grouping.final_batch": _mean_std(g_final["whole batch (the seed)"], ".3f"),
        "grouping.final_group": _mean_std(g_final["per-prompt groups (GRPO)"], ".3f"),
        "grouping.diff": _paired(g_final["per-prompt groups (GRPO)"], g_final["whole batch (the seed)"]),
        "grouping.detectable": _detectable(g_final["per-prompt groups (GRPO)"], g_final["whole batch (the seed)"]),
        "grouping.seeds_batch_above": _seeds_above(g_final["whole batch (the seed)"],
                                                   g_final["per-prompt groups (GRPO)"]),
        **retrieval_figures(),
    }


def retrieval_figures() -> dict[str, str]:
    """Lesson 8, section 6: the retrieval track (``python -m course_utils.tracks retrieval``)."""
    r = _json("tracks/retrieval/result.json")
    ex, snr = r["exact"], r["exact"]["snr"]
    rows = ex["baselines"]
    joint, alone = "joint (retriever learns)", "generator only (uniform retriever)"
    by_document = r["reward_by_document"].values()
    return {
        "retrieval.batches": f"{ex['batches']:,}",
        "retrieval.split_error": f"{ex['split_error']:.0e}",
        "retrieval.bias_group": f"{rows['group mean']['retriever']['bias']:.3f}",
        "retrieval.bias_per_document": f"{rows['per-document mean']['retriever']['bias']:.2f}",
        "retrieval.noise_loo": f"{rows['leave-one-out']['retriever']['noise']:.2f}",
        "retrieval.noise_cross": f"{rows['cross-document (retriever only)']['retriever']['noise']:.2f}",
        "retrieval.snr_k2": f"{snr['K=2, success 0.8 vs 0.2']['leave_one_out']:.2f}",
        "retrieval.snr_k16": f"{snr['K=16, success 0.8 vs 0.2']['leave_one_out']:.2f}",
        "retrieval.snr_k4_weak": f"{snr['K=4, success 0.3 vs 0.2']['leave_one_out']:.2f}",
        "retrieval.snr_cross_k16": f"{snr['K=16, success 0.8 vs 0.2']['cross_document']:.2f}",
        "retrieval.steps": f"{r['steps']}",
        "retrieval.p_joint": _mean_std(r["p_helpful"][joint], ".2f"),
        "retrieval.p_uniform": f"{1 / len(r['documents']):.2f}",
        "retrieval.diff_p": _paired(r["p_helpful"][joint], r["p_helpful"][alone], "+.2f"),
        "retrieval.seeds_p": _seeds_above(r["p_helpful"][alone], r["p_helpful"][joint]),
        "retrieval.final_joint": _mean_std(r["final_reward"][joint], ".3f"),
        "retrieval.final_alone": _mean_std(r["final_reward"][alone], ".3f"),
        "retrieval.diff_reward": _paired(r["final_reward"][joint], r["final_reward"][alone]),
        "retrieval.document_rewards": f"{min(by_document):.3f} to {max(by_document):.3f}",
        "retrieval.ess": _mean_std(r["cross_document_ess"], ".2f"),
        "retrieval.retriever_ms": f"{r['retriever_ms']:.1f} ms",
        "retrieval.step_s": f"{statistics.mean(r['seconds_per_step'][joint]):.0f} s",
    }


def cpu_run_figures() -> dict[str, str]:
    """Lesson 7, sections 5 and 6: the stored CPU runs' settings, the ablation's counts."""
    from course_utils.ablation import FULL, diagnose
    from course_utils.config import PRESETS, Config

    shaped = _json("cpu-shaped/config.json")
    known = {k: v for k, v in shaped.items() if k in Config.field_names()}
    ablation = _json("ablation/result.json")
    first = [r["first_pass_step"] for arm in ablation["arms"].values() for r in arm["runs"]]
    main_run = _json("cpu/summary.json")
    cpu = Config.from_dict(PRESETS["cpu"])
    # per arm, each seed's held-out pass rate (both constraints)
    passed = {name: [r["pass_both"] for r in arm["runs"]] for name, arm in ablation["arms"].items()}
    ds, sharp = passed["with dynamic sampling"], passed["with dynamic sampling and the sharp reward"]
    recipe = ablation["arms"][FULL]["runs"]
    # the cpu-shaped run's template (its most frequent held-out completion) against the target
    template = diagnose(RESULTS / "cpu-shaped")
    return {"cpu_shaped.steps": f"{Config.from_dict(known).total_steps}",
            "cpu_shaped.template_miss": _word(abs(template["top_chars"] - shaped["target_chars"])),
            # the stored main-job run's training time per step (its summary.json)
            "cpu.seconds_per_step": f"{main_run['seconds'] / main_run['steps']:.0f}",
            "cpu.prompts_per_step": _word(cpu.prompts_per_step),
            "cpu.group_size": _word(cpu.group_size),
            # the same settings in digits, for the README's "60 GRPO steps of 4 prompts x 8"
            "cpu.steps": f"{cpu.total_steps}",
            "cpu.prompts_per_step_n": f"{cpu.prompts_per_step}",
            "cpu.group_size_n": f"{cpu.group_size}",
            "cpu.lr": re.sub(r"e-0(\d)", r"e-\1", f"{cpu.lr:g}"),   # 6e-5, as the prose writes it
            # the recipe's mean held-out pass rate over the ablation's seeds
            "ablation.recipe_mean": f"{statistics.mean(passed[FULL]):.1%}",
            # the earliest step at which any ablation run sampled a pass (None: never)
            "ablation.earliest_first_pass": f"{min(s for s in first if s is not None)}",
            "ablation.seeds": _word(len(ablation["seeds"])),
            "ablation.seed_list": _seeds(ablation["seeds"]),
            "ablation.df": f"{len(ablation['seeds']) - 1}",      # of a paired t-interval
            # the recipe's seeds that settled on a template passing every one-digit target
            "ablation.template_seeds": _word(sum(r["pass_both_one_digit"] == 1.0 for r in recipe)),
            # the seeds on which the sharp reward ended below dynamic sampling alone
            "ablation.sharp_worse": _word(sum(s < d for s, d in zip(sharp, ds))),
            "ablation.max_sampling_rounds":
                _word(ablation["arms"]["with dynamic sampling"]["overrides"]["max_sampling_rounds"]),
            **probe_figures(passed[FULL])}


def probe_figures(recipe_passed: list[float]) -> dict[str, str]:
    """Lesson 7, section 6.3: the single-seed probes of other levers and the rule that names
    how each ended (``course_utils.ablation.probe_outcome``)."""
    import inspect

    from course_utils import ablation

    folder = RESULTS / "probes"
    # the probes whose only lever is temperature 0.7 (on the course's earlier recipe)
    temperature = {int(m.group(1)): folder / m.group(0) for p in sorted(folder.iterdir())
                   if (m := re.fullmatch(r"temperature-0\.7-seed(\d+)", p.name))}
    filling = [run for run in temperature.values()
               if ablation.probe_outcome(ablation.records(run)) == "filling the token cap"]
    if len(filling) != 1:
        raise ValueError(f"lesson 7 describes one temperature-0.7 probe filling the token cap, found {filling}")
    noise = _json(f"probes/{filling[0].name}/summary.json")["after"]["greedy"]["pass_both"]
    clip_higher = _json("probes/two-updates-clip-higher-seed1/config.json")
    return {"probes.temperature_seeds": _seeds(sorted(temperature)),
            # the recipe's seeds that the cap-filling probe passes more held-out prompts than
            "probes.noise_above_recipe": _word(sum(noise > f for f in recipe_passed)),
            "probes.clip_higher_updates": _word(clip_higher["updates_per_batch"]),
            "probes.window": f"{inspect.signature(ablation.tail_mean).parameters['n'].default}",
            "probes.collapsed_distinct": f"{ablation.COLLAPSED['max_distinct_frac']:.0%}",
            "probes.collapsed_entropy": f"{ablation.COLLAPSED['max_entropy']}",
            "probes.cap_share": f"{ablation.CAP_FILLING['min_truncated_frac']:.0%}"}


def counted_kl_runs() -> list[Path]:
    """The counted-credit runs with the KL term, one per tuning seed (lesson 7, 6.4)."""
    return sorted((RESULTS / "counted-probes").glob("steps150-counted-prioritized-adaptive-kl-seed*"))


def fresh_runs() -> list[Path]:
    """The counted-KL recipe, frozen, on fresh seeds never used to choose it (lesson 7, 6.5)."""
    return sorted((RESULTS / "fresh-seeds").glob("counted-kl-seed*"),
                  key=lambda p: int(p.name.removeprefix("counted-kl-seed")))


def frozen_recipe() -> dict:
    """The frozen counted-KL recipe's settings: a fresh-seed run's stored config (every one of
    them has the same but the seed and out_dir, as tests/test_figures.py checks), with the
    defaults of fields added since, which were off when they did not exist (overlong_penalty)."""
    from course_utils.config import Config

    return {**Config().to_dict(), **_json(f"fresh-seeds/{fresh_runs()[0].name}/config.json")}


# lesson 7, 6.6: per seed, the control (the frozen recipe on this machine) and the probe (the
# recipe with DAPO's overlong punishment), in notebooks/results/cap-probes. Seed 13 filled the cap
# in section 6.5 (so it is no longer fresh); seed 15 was never run before the probe was fixed.
CAP_PAIRS = {13: ("recipe-fp32-seed13", "overlong-punishment-seed13"),
             15: ("recipe-fp32-seed15", "overlong-punishment-seed15")}
CAP_PROBE_SEED, CAP_FRESH_SEED = 13, 15
CAP_CONTROL, CAP_PUNISHED = CAP_PAIRS[CAP_PROBE_SEED]
# a window of training steps "passes most one-digit targets" when its sampled replies pass at
# least this share of them (ablation.sampled_passes, 10 steps a window)
CAP_MOST = 0.5


def cap_probe_runs() -> list[Path]:
    """Lesson 7, 6.6: the frozen recipe's stored fresh-seed run on the probe's seed (a seed that
    filled the cap, so no longer fresh), then for each seed of CAP_PAIRS the control and the
    recipe with DAPO's overlong punishment."""
    stored = [run for run in fresh_runs()
              if _json(f"fresh-seeds/{run.name}/config.json")["seed"] == CAP_PROBE_SEED]
    return stored + [RESULTS / "cap-probes" / name for pair in CAP_PAIRS.values() for name in pair]


def cap_pair_runs(seed: int) -> list[Path]:
    """One seed's control, then its run with the punishment."""
    return [RESULTS / "cap-probes" / name for name in CAP_PAIRS[seed]]


def cap_labels(runs: list[Path]) -> list[str]:
    """Column names for cap-probe runs: seed and arm."""
    def label(run: Path) -> str:
        seed = _json(f"{run.parent.name}/{run.name}/config.json")["seed"]
        arm = ("stored run" if run.parent.name == "fresh-seeds" else
               "control" if run.name == CAP_PAIRS[seed][0] else "punished")
        return f"seed {seed}, {arm}"
    return [label(run) for run in runs]


def _check_cap_pairs() -> None:
    """What 6.6 says of its runs: each probe is the frozen recipe plus the overlong punishment,
    each control the frozen recipe, on the probe's seed, machine and precision."""
    recipe = frozen_recipe()
    for seed, (control, punished) in CAP_PAIRS.items():
        config, control_config = (_json(f"cap-probes/{name}/config.json") for name in (punished, control))
        changed = {k for k in config if config[k] != recipe[k]} - {"seed", "out_dir"}
        if changed != {"overlong_penalty", "overlong_buffer"}:
            raise ValueError(f"lesson 7, 6.6 says the probe changes only the overlong punishment; "
                             f"{punished} changes {changed}")
        if {k for k in control_config if control_config[k] != recipe[k]} - {"seed", "out_dir"} or \
                control_config["seed"] != config["seed"] or config["seed"] != seed:
            raise ValueError(f"lesson 7, 6.6's control must be the frozen recipe on the probe's seed: {control}")
        summaries = [_json(f"cap-probes/{name}/summary.json") for name in (control, punished)]
        machines = {(s.get("precision"), s.get("cpu_capability")) for s in summaries}
        if len(machines) != 1:
            raise ValueError(f"the probe and its control ran in different precisions or CPUs: {machines}")


def _one_digit_stretch(run: Path) -> tuple[int, int, float, float, float]:
    """The stretch of training in which a run's sampled replies passed most one-digit targets
    (every 10-step window from the first such window to the last at CAP_MOST or more), its
    share of one-digit passes, and the one-digit and two-digit shares after it."""
    from course_utils import ablation

    windows = ablation.sampled_passes(run)
    most = [i for i, w in enumerate(windows) if w["one_passed"] >= CAP_MOST * w["one_sampled"]]
    if not most or most != list(range(most[0], most[-1] + 1)) or most[-1] == len(windows) - 1:
        raise ValueError(f"lesson 7, 6.6 describes one stretch of one-digit passes that ended before "
                         f"the run did; {run.name} has windows {most}")
    share = lambda ws, k: sum(w[f"{k}_passed"] for w in ws) / sum(w[f"{k}_sampled"] for w in ws)  # noqa: E731
    inside, after = windows[most[0]:most[-1] + 1], windows[most[-1] + 1:]
    return inside[0]["first"], inside[-1]["last"], share(inside, "one"), share(after, "one"), share(after, "two")


def cap_figures() -> dict[str, str]:
    """Lesson 7, 6.6, and the README: the overlong-punishment probes and their controls."""
    import inspect

    from course_utils import ablation, rewards, stats

    _check_cap_pairs()
    stored = cap_probe_runs()[0]
    after = lambda run: _json(f"{run.parent.name}/{run.name}/summary.json")["after"]["greedy"]  # noqa: E731
    config = _json(f"cap-probes/{CAP_PUNISHED}/config.json")
    control, punished = cap_pair_runs(CAP_PROBE_SEED)
    fresh_control, fresh_punished = cap_pair_runs(CAP_FRESH_SEED)
    samples = after(punished)["samples"]
    # what 6.6 says the probe writes: one reply for every two-digit target, and one-digit
    # replies that all miss the length by the same few characters
    two = {(x["completion"].strip(), x["digit_sum"]) for x in samples if x["target_digit_sum"] >= 10}
    one_short = {x["target_chars"] - x["n_chars"] for x in samples if x["target_digit_sum"] < 10}
    if len(two) != 1 or len(one_short) != 1:
        raise ValueError(f"lesson 7, 6.6 describes one two-digit reply and one length miss; "
                         f"found {two} and {one_short}")
    steps = ablation.records(punished)
    shortest = min(steps, key=lambda r: r["completion_tokens"])
    control_steps = ablation.records(control)
    # the step by which the punishment had driven replies off the cap: the first step at which
    # the probe's replies were shorter than half its first step's
    off_cap = next(r for r in steps if r["completion_tokens"] < steps[0]["completion_tokens"] / 2)
    start, end, one_inside, one_after, two_after = _one_digit_stretch(punished)
    # what a reply that is one bare digit, the target's own, earns under the counted credit
    bare = rewards.counted_score(rewards.check("5", 32, 5), 32, 5)
    fresh_samples = after(fresh_punished)["samples"]
    fresh_two = {(x["completion"].strip(), x["digit_sum"]) for x in fresh_samples if x["target_digit_sum"] >= 10}
    if len(fresh_two) != 1:
        raise ValueError(f"lesson 7, 6.6 describes one two-digit reply on seed {CAP_FRESH_SEED}; found {fresh_two}")
    # what 6.6 says seed 15's probe writes for one-digit targets: the target digit and a 0 in
    # one 32-character frame
    fresh_one = [x for x in fresh_samples if x["target_digit_sum"] < 10]
    frames = {re.sub(r"[0-9]", "N", x["completion"].strip()) for x in fresh_samples}
    if len(frames) != 1 or any(re.findall(r"[0-9]", x["completion"]) != [str(x["target_digit_sum"]), "0"]
                               for x in fresh_one):
        raise ValueError(f"lesson 7, 6.6 says seed {CAP_FRESH_SEED}'s probe writes the target digit and a 0 "
                         f"in one frame; found frames {frames}")
    example = min(fresh_one, key=lambda x: x["target_digit_sum"])
    pairs = [[after(run) for run in cap_pair_runs(seed)] for seed in CAP_PAIRS]
    both = stats.paired([p["pass_both"] for _, p in pairs], [c["pass_both"] for c, _ in pairs])
    whole_cut = lambda run: statistics.mean(r["truncated_frac"] for r in ablation.records(run))  # noqa: E731
    runs = {"stored": stored, "control": control, "punished": punished,
            "fresh_control": fresh_control, "fresh_punished": fresh_punished}
    return {"cap.seed": f"{CAP_PROBE_SEED}",
            "cap.fresh_seed": f"{CAP_FRESH_SEED}",
            "cap.pairs": _word(len(CAP_PAIRS)),
            "cap.bare_digit": f"{bare:.2f}",
            "cap.two_digit_reply": next(iter(two))[0],
            "cap.two_digit_sum": f"{next(iter(two))[1]}",
            "cap.one_digit_short": _word(next(iter(one_short))),
            "cap.first_tokens": f"{steps[0]['completion_tokens']:.1f}",
            "cap.first_cut": f"{steps[0]['truncated_frac']:.0%}",
            "cap.off_cap_step": f"{off_cap['step']}",
            "cap.off_cap_tokens": f"{off_cap['completion_tokens']:.1f}",
            "cap.control_off_cap_tokens": f"{control_steps[off_cap['step'] - 1]['completion_tokens']:.1f}",
            "cap.shortest_tokens": f"{shortest['completion_tokens']:.1f}",
            "cap.shortest_step": f"{shortest['step']}",
            "cap.stretch_start": f"{start}",
            "cap.stretch_end": f"{end}",
            "cap.stretch_one": f"{one_inside:.0%}",
            "cap.after_one": f"{one_after:.0%}",
            "cap.after_two": f"{two_after:.0%}",
            "cap.most": f"{CAP_MOST:.0%}",
            "cap.penalty": f"{config['overlong_penalty']:g}",
            "cap.buffer": f"{config['overlong_buffer']}",
            "cap.max_new_tokens": f"{config['max_new_tokens']}",
            "cap.ramp_start": f"{config['max_new_tokens'] - config['overlong_buffer']}",
            "cap.precision": _json(f"cap-probes/{CAP_PUNISHED}/summary.json")["precision"],
            "cap.fresh_two_digit_reply": next(iter(fresh_two))[0],
            "cap.fresh_two_digit_sum": f"{next(iter(fresh_two))[1]}",
            "cap.fresh_example": example["completion"].strip(),
            "cap.fresh_example_target": f"{example['target_digit_sum']}",
            "cap.paired_mean": f"{both.mean:+.1%}",
            "cap.paired_p": f"{both.p_value:.3g}",
            "cap.paired_floor": f"{both.p_floor:.3g}",
            "cap.paired_df": _word(both.n - 1),
            "cap.window": f"{inspect.signature(ablation.sampled_passes).parameters['width'].default}",
            **{f"cap.{name}_{key}": f"{after(run)[field]:.1%}" for name, run in runs.items()
               for key, field in (("pass", "pass_both"), ("one", "pass_both_one_digit"),
                                  ("two", "pass_both_two_digit"))},
            **{f"cap.{name}_cut": f"{ablation.tail_mean(ablation.records(run), 'truncated_frac'):.0%}"
               for name, run in runs.items()},
            **{f"cap.{name}_whole_cut": f"{whole_cut(run):.0%}" for name, run in runs.items()}}


# lesson 7, 6.7: the recipe with 6.6's overlong punishment on the same seeds in both precisions,
# one run after the other on one CPU with bf16 matrix units (notebooks/results/precision-pairs).
PRECISION_SEEDS = (16, 17, 18, 19, 20)


def precision_pair_runs() -> tuple[list[Path], list[Path]]:
    """The fp32 runs, then the bf16 runs, in the order of PRECISION_SEEDS (those stored)."""
    folder = RESULTS / "precision-pairs"
    seeds = [s for s in PRECISION_SEEDS if (folder / f"punished-bf16-seed{s}" / "summary.json").exists()]
    return ([folder / f"punished-fp32-seed{s}" for s in seeds],
            [folder / f"punished-bf16-seed{s}" for s in seeds])


def _config_with_defaults(run: str) -> dict:
    """A stored run's config with every field added since at its default, so a run that turned
    on a later option (is_correction, say) is not taken for a recipe that predates it."""
    from course_utils.config import Config

    return {**Config().to_dict(), **_json(f"{run}/config.json")}


def punished_recipe() -> dict:
    """6.6's recipe with the overlong punishment: its probe's settings but the seed and out_dir."""
    return {k: v for k, v in _config_with_defaults(f"cap-probes/{CAP_PUNISHED}").items()
            if k not in ("seed", "out_dir")}


def _check_precision_pairs() -> None:
    """What 6.7 says of its runs: each is 6.6's punished recipe on its seed, the pair differs in
    the precision alone, and both ran on the same CPU capability, one in each precision."""
    punished = punished_recipe()
    for fp32, bf16 in zip(*precision_pair_runs()):
        configs = [_config_with_defaults(f"precision-pairs/{run.name}") for run in (fp32, bf16)]
        summaries = [_json(f"precision-pairs/{run.name}/summary.json") for run in (fp32, bf16)]
        for config in configs:
            changed = {k for k in punished if config[k] != punished[k]} - {"precision"}
            if changed or config["seed"] != configs[0]["seed"]:
                raise ValueError(f"lesson 7, 6.7 says each run is 6.6's punished recipe on its seed; "
                                 f"{config['out_dir']} changes {changed}")
        if [s["precision"] for s in summaries] != ["fp32", "bf16"] or \
                summaries[0]["cpu_capability"] != summaries[1]["cpu_capability"]:
            raise ValueError(f"lesson 7, 6.7's pairs are fp32 and bf16 on one CPU: {fp32.name} "
                             f"{[(s['precision'], s['cpu_capability']) for s in summaries]}")


def precision_figures() -> dict[str, str]:
    """Lesson 7, 6.7, and the README: the punished recipe in fp32 and in bf16, paired by seed."""
    from course_utils import ablation, stats

    _check_precision_pairs()
    fp32, bf16 = precision_pair_runs()
    if len(fp32) < 2:
        raise ValueError("lesson 7, 6.7 needs at least two stored pairs in results/precision-pairs")
    runs = fp32 + bf16
    summary = {run: _json(f"precision-pairs/{run.name}/summary.json") for run in runs}
    after = {run: summary[run]["after"]["greedy"] for run in runs}
    seconds = lambda arm: statistics.mean(summary[run]["seconds"] for run in arm)  # noqa: E731
    # what 6.7 says: fp32 minus bf16 changes sign from seed to seed; a run that passes two-digit
    # targets passes one target sum only; and the template (every one-digit target passed) came
    # with fp32 alone on some seeds and with bf16 alone on others
    diffs = [after[f]["pass_both"] - after[b]["pass_both"] for f, b in zip(fp32, bf16)]
    if not (any(d > 0 for d in diffs) and any(d < 0 for d in diffs)):
        raise ValueError(f"lesson 7, 6.7 says the sign of fp32 minus bf16 changes from seed to seed: {diffs}")
    two_digit_runs = [r for r in runs if after[r]["pass_both_two_digit"] > 0]
    for r in two_digit_runs:
        sums = {x["digit_sum"] for x in after[r]["samples"] if x["target_digit_sum"] >= 10 and
                x["digit_sum"] == x["target_digit_sum"] and x["n_chars"] == x["target_chars"]}
        if len(sums) != 1:
            raise ValueError(f"lesson 7, 6.7 says {r.name} passes one two-digit target sum; it passes {sums}")
    template = [r for r in runs if after[r]["pass_both_one_digit"] == 1.0]
    others = [r for r in runs if r not in template]
    only_fp32 = sum(f in template and b not in template for f, b in zip(fp32, bf16))
    only_bf16 = sum(b in template and f not in template for f, b in zip(fp32, bf16))
    if not (only_fp32 and only_bf16):
        raise ValueError(f"lesson 7, 6.7 says the template came with fp32 on some seeds and with bf16 on "
                         f"others; fp32 only on {only_fp32}, bf16 only on {only_bf16}")
    # the exact sign test on the discordant seeds (McNemar's exact test) is the sign-flip test
    # on their +1 / -1 differences
    template_p = stats.sign_flip_p_value([1.0] * only_fp32 + [-1.0] * only_bf16)
    logged = [ablation.records(r) for r in bf16]
    gaps = [statistics.mean(x["sampler_gap_abs"] for x in steps) for steps in logged
            if all("sampler_gap_abs" in x for x in steps)]
    # benchmarks/logprob_gap.py on the untrained policy (benchmarks/RESULTS.md)
    untrained = json.loads((RESULTS.parents[1] / "benchmarks" / "logprob_gap.json").read_text())
    weight_sd = untrained["sequence log weight sum_t (trainer - sampler)"]["sd"]
    both = stats.paired([after[r]["pass_both"] for r in fp32], [after[r]["pass_both"] for r in bf16])
    return {"precision.seed_list": _seeds([_json(f"precision-pairs/{r.name}/config.json")["seed"] for r in fp32]),
            "precision.capability": summary[fp32[0]]["cpu_capability"],
            "precision.runs": _word(len(runs)),
            "precision.abs_diff_mean": f"{100 * statistics.mean(abs(d) for d in diffs):.1f}",
            "precision.max_abs_diff": f"{100 * max(abs(d) for d in diffs):.0f}",
            "precision.min_abs_diff": f"{100 * min(abs(d) for d in diffs):.0f}",
            "precision.template_runs": _word(len(template)),
            "precision.template_pass_low": f"{min(after[r]['pass_both'] for r in template):.1%}",
            "precision.template_pass_high": f"{max(after[r]['pass_both'] for r in template):.1%}",
            "precision.other_pass_high": f"{max(after[r]['pass_both'] for r in others):.1%}",
            "precision.other_one_high": f"{max(after[r]['pass_both_one_digit'] for r in others):.1%}",
            "precision.two_digit_runs": _word(len(two_digit_runs)),
            "precision.two_digit_best": f"{max([after[r]['pass_both_two_digit'] for r in two_digit_runs] or [0]):.1%}",
            "precision.only_fp32": _word(only_fp32), "precision.only_bf16": _word(only_bf16),
            "precision.template_sign_p": f"{template_p:.3g}",
            "precision.paired_pass_df": _word(both.n - 1),
            "precision.gap_runs": _word(len(gaps)),
            "precision.gap_mean": f"{statistics.mean(gaps):.3f}" if gaps else "not logged",
            "precision.gap_untrained": f"{untrained['trainer - sampler']['mean_abs']:.3f}",
            "precision.sequence_weight_sd": f"{weight_sd:.2f}",
            "precision.weight_low": f"{math.exp(-weight_sd):.2f}",
            "precision.weight_high": f"{math.exp(weight_sd):.2f}",
            "precision.fp32_seconds": f"{seconds(fp32):.0f}",
            "precision.bf16_seconds": f"{seconds(bf16):.0f}",
            "precision.seconds_ratio": f"{seconds(fp32) / seconds(bf16):.2f}"}


# lesson 7, 6.8: the gated credit (rewards.gated_score) as the one change to 6.6's punished
# recipe, in bf16 on one CPU with bf16 units (notebooks/results/gated). Screened on 6.7's seeds
# against their stored bf16 runs, then frozen and run on fresh seeds beside the punished recipe,
# the two runs of a seed one after the other.
GATED_TUNING_SEEDS = (16, 17, 18, 19)
GATED_FRESH_SEEDS = (21, 22, 23, 24, 25)
# what issue 23 asks of a recipe on fresh seeds: a mean pass rate and a worst seed
SHIP_MEAN, SHIP_WORST = 0.80, 0.60


def gated_pair_runs(stage: str) -> tuple[list[Path], list[Path]]:
    """(gated runs, counted runs) paired by seed: 'tuning' against 6.7's bf16 runs, 'fresh'
    both in results/gated/fresh. Every seed of the stage must have both runs stored."""
    if stage == "tuning":
        seeds = GATED_TUNING_SEEDS
        gated = [RESULTS / "gated" / "tuning" / f"gated-seed{s}" for s in seeds]
        counted = [RESULTS / "precision-pairs" / f"punished-bf16-seed{s}" for s in seeds]
    elif stage == "fresh":
        seeds = GATED_FRESH_SEEDS
        gated = [RESULTS / "gated" / "fresh" / f"gated-seed{s}" for s in seeds]
        counted = [RESULTS / "gated" / "fresh" / f"punished-seed{s}" for s in seeds]
    else:
        raise ValueError(f"stage must be 'tuning' or 'fresh', got {stage!r}")
    missing = [_relative(r) for r in gated + counted if not (r / "summary.json").exists()]
    if missing:
        raise ValueError(f"lesson 7, 6.8's {stage} seeds {seeds} need both runs of each pair: missing {missing}")
    return gated, counted


def _relative(run: Path) -> str:
    return str(run.relative_to(RESULTS))


def _check_gated_pairs(stage: str) -> None:
    """What 6.8 says of its runs: each counted run is 6.6's punished recipe in bf16 on its
    seed, each gated run is its twin with reward='gated' and nothing else changed, and both ran
    in bf16 on the same CPU capability."""
    recipe = punished_recipe()
    seeds = GATED_TUNING_SEEDS if stage == "tuning" else GATED_FRESH_SEEDS
    for seed, gated_run, counted_run in zip(seeds, *gated_pair_runs(stage)):
        g, c = (_config_with_defaults(_relative(r)) for r in (gated_run, counted_run))
        if {k for k in recipe if c[k] != recipe[k]} or c["seed"] != seed:
            raise ValueError(f"lesson 7, 6.8 says {counted_run.name} is 6.6's punished recipe on seed {seed}")
        if {k for k in recipe if g[k] != recipe[k]} != {"reward"} or g["reward"] != "gated" or g["seed"] != seed:
            raise ValueError(f"lesson 7, 6.8 says {gated_run.name} is {counted_run.name} with "
                             f"reward='gated' and nothing else changed")
        summaries = [_json(f"{_relative(r)}/summary.json") for r in (gated_run, counted_run)]
        machines = {(s["precision"], s["cpu_capability"]) for s in summaries}
        if machines != {("bf16", summaries[0]["cpu_capability"])}:
            raise ValueError(f"lesson 7, 6.8's pairs both ran in bf16 on one CPU: {gated_run.name} {machines}")


# both runs of a pair ran on one machine; wall times within this ratio of each other say so
# (the two machines behind 6.8's fresh seeds differ by almost 2x)
SAME_MACHINE_SECONDS = 1.25
BF16_UNITS_WORDS = {"AMX": "AMX", "AVX512-BF16": "AVX512-BF16 and no AMX", "none": "no bf16 units"}


def gated_fresh_machines() -> dict[str, str]:
    """Which machine each fresh pair of 6.8 ran on (results/gated/fresh/machines.json, written
    from the session logs: the runs predate summary.json's 'cpu'), checked against what the runs
    themselves say: a summary's 'cpu' where it has one, and wall times (both runs of a pair, and
    all runs listed on one machine, within SAME_MACHINE_SECONDS of each other)."""
    pairs = gated_pair_runs("fresh")   # refuses a pair with a run missing before anything else
    listed = {int(seed): m for seed, m in _json("gated/fresh/machines.json")["seeds"].items()}
    if set(listed) != set(GATED_FRESH_SEEDS):
        raise ValueError(f"lesson 7, 6.8 names the machine of every fresh pair: machines.json lists "
                         f"seeds {sorted(listed)}, not {list(GATED_FRESH_SEEDS)}")
    seconds, pass_both, by_machine = {}, {}, collections.defaultdict(list)
    for seed, *runs in zip(GATED_FRESH_SEEDS, *pairs):
        summaries = [_json(f"{_relative(r)}/summary.json") for r in runs]
        for run, summary in zip(runs, summaries):
            if "cpu" in summary and summary["cpu"] != listed[seed]:
                raise ValueError(f"lesson 7, 6.8 says {run.name} ran on {listed[seed]}; it says {summary['cpu']}")
        pair = [s["seconds"] for s in summaries]
        if max(pair) > SAME_MACHINE_SECONDS * min(pair):
            raise ValueError(f"lesson 7, 6.8 says both runs of seed {seed}'s pair ran on one machine; "
                             f"their wall times differ: {pair}")
        seconds[seed] = statistics.mean(pair)
        pass_both[seed] = [s["after"]["greedy"]["pass_both"] for s in summaries]   # gated, counted
        by_machine[(listed[seed]["model"], listed[seed]["bf16_units"])].append(seed)
    for seeds in by_machine.values():
        times = [seconds[s] for s in seeds]
        if max(times) > SAME_MACHINE_SECONDS * min(times):
            raise ValueError(f"lesson 7, 6.8 says seeds {seeds} ran on one machine; their wall times differ: {times}")
    if len(by_machine) != 2:
        raise ValueError(f"lesson 7, 6.8 says the fresh pairs ran on two machines: {dict(by_machine)}")
    (fast, fast_seeds), (slow, slow_seeds) = sorted(by_machine.items(), key=lambda m: seconds[m[1][0]])
    def named(machine: tuple[str, str], seeds: list[int]) -> str:
        return f"seed{'s' if len(seeds) > 1 else ''} {_seeds(seeds)} on an {machine[0]} with {BF16_UNITS_WORDS[machine[1]]}"
    ratio = statistics.mean(seconds[s] for s in slow_seeds) / statistics.mean(seconds[s] for s in fast_seeds)
    if len(slow_seeds) != 1:
        raise ValueError(f"lesson 7, 6.8 says one fresh pair ran on the slower machine: seeds {slow_seeds}")
    gated_pass, counted_pass = pass_both[slow_seeds[0]]
    slow_diff = 100 * (gated_pass - counted_pass)
    return {"gated.fresh_machines": f"{named(fast, fast_seeds)}, {named(slow, slow_seeds)}",
            "gated.same_machine": f"{SAME_MACHINE_SECONDS:g}", "gated.fresh_slow_diff": f"{slow_diff:+.1f}",
            "gated.fresh_slow_seeds": _seeds(slow_seeds), "gated.fresh_machine_seconds_ratio": f"{ratio:.1f}"}


# 6.8 counts a run as a template run when it passes at least this share of its one-digit
# targets held out (6.7's template runs pass all of them, the others few: tests/test_figures.py
# checks that no stored run falls near the line)
TEMPLATE_ONE_DIGIT = 0.9


def dead_end(after: dict) -> str | None:
    """How a run that found no template ended (held-out greedy): 'length' when more replies met
    the length than the digit sum (the length learned first, the digits left out), 'digits'
    when fewer, 'tie' when as many; None for a template run (TEMPLATE_ONE_DIGIT or more of the
    one-digit targets passed)."""
    if after["pass_both_one_digit"] >= TEMPLATE_ONE_DIGIT:
        return None
    if after["pass_length"] == after["pass_digits"]:
        return "tie"
    return "length" if after["pass_length"] > after["pass_digits"] else "digits"


def _digit_free(run: Path) -> bool:
    """Whether most of a run's held-out greedy replies hold no digit (seed 18's bf16 dead end)."""
    from course_utils import rewards

    samples = _json(f"{_relative(run)}/summary.json")["after"]["greedy"]["samples"]
    free = sum(not rewards.check(x["completion"], x["target_chars"], x["target_digit_sum"]).n_digits
               for x in samples)
    return 2 * free > len(samples)


def _ends(runs: list[Path]) -> list[str | None]:
    ends = [dead_end(_json(f"{_relative(r)}/summary.json")["after"]["greedy"]) for r in runs]
    if "tie" in ends:
        raise ValueError(f"lesson 7, 6.8 sorts every run without a template into length first or "
                         f"digits first; one of {[r.name for r in runs]} is a tie")
    return ends


# a run "settles" on a frame when one frame (the reply with its digits taken out) is written for
# more than half the held-out prompts; two-digit targets "end on one digit sum" when at least
# this share of their replies have one and the same digit sum
ONE_SUM_SHARE = 0.75


def _frame(reply: str) -> str:
    return re.sub(r"\d", "", reply.strip())


def _settled_frame(samples: list[dict]) -> tuple[str, int] | None:
    """The frame a run wrote for most held-out prompts, with how many; None if no frame was."""
    frame, count = collections.Counter(_frame(x["completion"]) for x in samples).most_common(1)[0]
    return (frame, count) if 2 * count > len(samples) else None


def _two_digit_sum(samples: list[dict]) -> tuple[int, float]:
    """The digit sum most two-digit targets' replies have, and the share of them that have it."""
    sums = [x["digit_sum"] for x in samples if x["target_digit_sum"] >= 10]
    top, count = collections.Counter(sums).most_common(1)[0]
    return top, count / len(sums)


def _fixed_number(label: str, run: Path, samples: list[dict]) -> str:
    """'gated seed 24 writes one frame for 56 of 64 prompts, as "..." (digit sum 8) for 32 of them':
    the sentence frame a length-first run settled on (written for more than half the prompts),
    and its most frequent reply, of the right length, with a digit, and at least half of the
    frame's prompts (refused otherwise)."""
    from course_utils import rewards

    settled = _settled_frame(samples)
    reply, count = collections.Counter(x["completion"] for x in samples).most_common(1)[0]
    top = rewards.check(reply, samples[0]["target_chars"], 0)
    # the number is fixed: its most frequent reply is at least half of what the frame was written for
    if settled is None or _frame(reply) != settled[0] or 2 * count < settled[1] or not top.n_digits \
            or not top.length_ok:
        raise ValueError(f"lesson 7, 6.8 says {run.name} settled on one frame of the right length with "
                         f"a fixed number for most prompts: {reply!r} {count} times, frame {settled}")
    seed = _json(f"{_relative(run)}/config.json")["seed"]
    return (f'{label} seed {seed} writes one frame for {settled[1]} of {len(samples)} prompts, as "{reply}" '
            f'(digit sum {top.digit_sum}) for {count} of them')


def _digits_first_figures(runs: list[Path], greedy: dict) -> dict[str, str]:
    """6.8's gated runs that ended digits first: which never settled on one frame, and which
    settled on a frame one character short of the target with a one-digit number in it."""
    settled = {r: _settled_frame(greedy[r]["samples"]) for r in runs}
    unsettled = [_json(f"{_relative(r)}/config.json")["seed"] for r, frame in settled.items() if frame is None]
    short, short_chars = [], set()
    for run, frame in settled.items():
        if frame is None:
            continue
        samples = greedy[run]["samples"]
        one_digit = [x for x in samples if _frame(x["completion"]) == frame[0] and x["target_digit_sum"] < 10]
        lengths = {x["n_chars"] for x in one_digit}
        if lengths != {samples[0]["target_chars"] - 1}:
            raise ValueError(f"lesson 7, 6.8 says {run.name} settled on a frame one character short with a "
                             f"one-digit number: lengths {lengths}")
        short_chars |= lengths
        reply = collections.Counter(x["completion"].strip() for x in one_digit).most_common(1)[0][0]
        short.append(f'seed {_json(f"{_relative(run)}/config.json")["seed"]} wrote one frame for {frame[1]} of '
                     f'{len(samples)} prompts ("{reply}" for a one-digit target)')
    if not unsettled or not short:
        raise ValueError(f"lesson 7, 6.8 says of the gated digits-first runs some never settled on a frame "
                         f"and one settled on a frame one character short: {settled}")
    return {"gated.digits_first_runs": _word(len(runs)),
            "gated.digits_first_unsettled": f"seed{'s' if len(unsettled) > 1 else ''} {_seeds(unsettled)}",
            "gated.digits_first_short": "; ".join(short), "gated.digits_first_short_chars": f"{min(short_chars)}"}


def _one_sum_figures(arms: dict[str, list[Path]], greedy: dict) -> dict[str, str]:
    """6.8's two-digit targets: in most runs of either arm, at least ONE_SUM_SHARE of their
    held-out replies have one and the same digit sum, whatever the target."""
    one_sum = {arm: [_two_digit_sum(greedy[r]["samples"]) for r in runs] for arm, runs in arms.items()}
    one_sum_runs = {arm: [total for total, share in v if share >= ONE_SUM_SHARE] for arm, v in one_sum.items()}
    if any(2 * len(v) <= len(arms[arm]) for arm, v in one_sum_runs.items()):
        raise ValueError(f"lesson 7, 6.8 says most runs of both arms end their two-digit targets on one "
                         f"digit sum: {one_sum}")
    common, common_count = collections.Counter(sum(one_sum_runs.values(), [])).most_common(1)[0]
    return {"gated.one_sum_share": f"{ONE_SUM_SHARE:.0%}",
            "gated.one_sum_gated": _word(len(one_sum_runs["gated"])),
            "gated.one_sum_counted": _word(len(one_sum_runs["counted"])),
            "gated.one_sum_common": f"{common}", "gated.one_sum_common_runs": _word(common_count),
            "gated.one_sum_all_runs": _word(sum(map(len, one_sum_runs.values())))}


def gated_figures() -> dict[str, str]:
    """Lesson 7, 6.8, and the README: the gated credit against the counted one, paired by seed."""
    from course_utils import ablation, rewards, stats

    figs, greedy = gated_fresh_machines(), {}   # greedy: each run's held-out greedy results, read once
    two_shares = {"tuning": [], "fresh": []}      # per run: the sampled two-digit replies that passed
    for stage in ("tuning", "fresh"):
        _check_gated_pairs(stage)
        gated, counted = gated_pair_runs(stage)
        after = {r: _json(f"{_relative(r)}/summary.json")["after"]["greedy"] for r in gated + counted}
        greedy |= after
        both = stats.paired([after[r]["pass_both"] for r in gated], [after[r]["pass_both"] for r in counted])
        if stage == "fresh" and both.significant:
            raise ValueError(f"lesson 7, 6.8 and the README say the fresh seeds detect no difference: {both}")
        for arm, runs in (("gated", gated), ("counted", counted)):
            passes, ends = [after[r]["pass_both"] for r in runs], _ends(runs)
            # two-digit passes sampled in training, per seed: the signal that the greedy reply
            # held out may or may not keep
            logs = [ablation.records(r) for r in runs]
            sampled_two = [sum(x["passes_two_digit"] for x in log) for log in logs]
            two_shares[stage] += [n / sum(x["samples_two_digit"] for x in log) for n, log in zip(sampled_two, logs)]
            figs |= {f"gated.{stage}_{arm}_mean": f"{statistics.mean(passes):.1%}",
                     f"gated.{stage}_{arm}_worst": f"{min(passes):.1%}",
                     f"gated.{stage}_{arm}_two_mean":
                         f"{statistics.mean(after[r]['pass_both_two_digit'] for r in runs):.1%}",
                     f"gated.{stage}_{arm}_templates": _word(ends.count(None)),
                     f"gated.{stage}_{arm}_n_template": f"{ends.count(None)}",
                     f"gated.{stage}_{arm}_n_length": f"{ends.count('length')}",
                     f"gated.{stage}_{arm}_n_digits": f"{ends.count('digits')}",
                     f"gated.{stage}_{arm}_length_first": _word(ends.count("length")),
                     f"gated.{stage}_{arm}_digits_first": _word(ends.count("digits")),
                     f"gated.{stage}_{arm}_two_sampled": _seeds(sampled_two)}
        figs |= {f"gated.{stage}_seed_list": _seeds([_json(f"{_relative(r)}/config.json")["seed"] for r in gated]),
                 f"gated.{stage}_diff_mean": f"{100 * both.mean:+.1f}",
                 f"gated.{stage}_p": f"{both.p_value:.3g}"}
    figs["gated.fresh_two_sampled_max_share"] = f"{max(two_shares['fresh']):.1%}"
    # what 6.8's verdict says: no gated run ended on replies without a digit (the end the gate
    # was built against; a counted run did), the runs that ended length first wrote one sentence
    # with one fixed number, the template did not become likely (at most half the fresh gated
    # runs found it), and no recipe met the bar on fresh seeds
    pairs = {stage: gated_pair_runs(stage) for stage in ("tuning", "fresh")}
    arms = {arm: pairs["tuning"][i] + pairs["fresh"][i] for i, arm in enumerate(("gated", "counted"))}
    ends = {arm: _ends(runs) for arm, runs in arms.items()}
    free = {arm: [r for r in runs if _digit_free(r)] for arm, runs in arms.items()}
    fresh_free = [r for arm in pairs["fresh"] for r in arm if _digit_free(r)]
    if free["gated"] or not free["counted"] or fresh_free:
        raise ValueError(f"lesson 7, 6.8 says no gated run and no fresh run ended on replies without a digit, "
                         f"and a counted screen run did: {({arm: [r.name for r in runs] for arm, runs in free.items()})}")
    fixed = [(arm, r) for arm, runs in arms.items() for r, end in zip(runs, ends[arm])
             if end == "length" and r not in free[arm]]
    examples = [_fixed_number(arm, run, greedy[run]["samples"]) for arm, run in fixed]
    if not any(arm == "gated" for arm, _ in fixed):
        raise ValueError("lesson 7, 6.8 says a gated run ended length first on a fixed number")
    fresh = {arm: [greedy[r]["pass_both"] for r in runs] for arm, runs in zip(("gated", "counted"), pairs["fresh"])}
    if 2 * ends["gated"][len(GATED_TUNING_SEEDS):].count(None) > len(GATED_FRESH_SEEDS):
        raise ValueError("lesson 7, 6.8 says the template did not become the likely path on fresh seeds")
    if any(statistics.mean(p) >= SHIP_MEAN and min(p) >= SHIP_WORST for p in fresh.values()):
        raise ValueError(f"lesson 7, 6.8 says neither recipe met the bar on fresh seeds: {fresh}")
    # the same form in 6.7's fp32 runs, before the gate existed
    fp32 = precision_pair_runs()[0]
    earlier = [_fixed_number("fp32", r, _json(f"{_relative(r)}/summary.json")["after"]["greedy"]["samples"])
               for r, end in zip(fp32, _ends(fp32)) if end == "length" and not _digit_free(r)]
    if not earlier:
        raise ValueError("lesson 7, 6.8 says one of 6.7's fp32 runs already ended on a fixed-number sentence")
    figs |= {"gated.precision_fixed_number": "; ".join(earlier)}
    figs |= _digits_first_figures([r for r, end in zip(arms["gated"], ends["gated"]) if end == "digits"], greedy)
    figs |= _one_sum_figures(arms, greedy)
    figs |= {f"gated.{arm}_runs": _word(len(runs)) for arm, runs in arms.items()}
    figs |= {"gated.counted_digit_free": _word(len(free["counted"])),
             "gated.fixed_number_examples": "; ".join(examples)}
    # a reply one character off with the right digit: the two credits agree wherever the digits
    # are right (D = 1), so the gate changes nothing for a near miss of that kind
    one_off = rewards.check("x" * 30 + "7", 32, 7)
    if rewards.gated_score(one_off, 32, 7) != rewards.counted_score(one_off, 32, 7):
        raise ValueError("lesson 7, 6.8 says both credits pay a reply with the right digits alike")
    figs |= {"gated.one_off": f"{rewards.gated_score(one_off, 32, 7):.2f}",
         "gated.template_share": f"{TEMPLATE_ONE_DIGIT:.0%}", "gated.bar_mean": f"{SHIP_MEAN:.0%}", "gated.bar_worst": f"{SHIP_WORST:.0%}"}
    # 6.7's eight runs by how they ended, and the length-first dead end: its reply, what each
    # credit pays it, and its training log (the length learned while no sampled reply had the
    # right digit sum, and none had it afterwards)
    ends = _ends(sum(precision_pair_runs(), []))
    figs |= {"gated.precision_runs": _word(len(ends)), "gated.precision_templates": _word(ends.count(None)),
             "gated.precision_length_first": _word(ends.count("length")),
             "gated.precision_digits_first": _word(ends.count("digits"))}
    dead = RESULTS / "precision-pairs" / "punished-bf16-seed18"
    dead_after = _json(f"{_relative(dead)}/summary.json")["after"]["greedy"]
    sample = dead_after["samples"][0]
    targets = (sample["target_chars"], sample["target_digit_sum"])
    result = rewards.check(sample["completion"], *targets)
    if dead_end(dead_after) != "length" or result.n_digits or not result.length_ok or \
            len({x["completion"] for x in dead_after["samples"]}) != 1:
        raise ValueError(f"lesson 7, 6.8 says {dead.name} writes one reply of the right length "
                         f"without a digit for every prompt")
    steps = ablation.records(dead)
    config = _json(f"{_relative(dead)}/config.json")
    batch = config["prompts_per_step"] * config["group_size"]
    # the exact digit sum was as rare before the length was learned as after (the graded digit
    # credit's near sums are not logged, so this says nothing of them)
    length_step = next(x["step"] for x in steps if x["pass_length"] >= 0.5)
    earlier_steps = [x for x in steps if x["step"] < length_step]
    later = [x for x in steps if x["step"] >= length_step]
    early_hits = sum(round(x["pass_digits"] * batch) for x in earlier_steps)
    digit_hits = sum(round(x["pass_digits"] * batch) for x in later)
    if digit_hits > 0.01 * batch * len(later) or early_hits > 0.01 * batch * len(earlier_steps):
        raise ValueError(f"lesson 7, 6.8 says {dead.name} almost never sampled the right digit sum, "
                         f"before or after it learned the length: {early_hits} and {digit_hits} times")
    return figs | {"gated.dead_end": sample["completion"], "gated.dead_end_literal": repr(sample["completion"]),
                   "gated.dead_end_seed": f"{config['seed']}", "gated.dead_end_sum": f"{targets[1]}",
                   "gated.dead_end_length_step": f"{length_step}",
                   "gated.dead_end_steps": f"{len(steps)}", "gated.dead_end_digit_hits": f"{digit_hits}",
                   "gated.dead_end_later_samples": f"{batch * len(later):,}",
                   "gated.dead_end_early_hits": f"{early_hits}",
                   "gated.dead_end_early_samples": f"{batch * len(earlier_steps):,}",
                   "gated.dead_end_counted": f"{rewards.counted_score(result, *targets):.2f}",
                   "gated.dead_end_gated": f"{rewards.gated_score(result, *targets):.2f}"}


# lesson 7, 6.9: 6.8's gated recipe with the policy term only at the forks (the top fifth of a
# step's tokens by entropy, top_entropy_quantile), screened on 6.8's tuning seeds against their
# stored gated runs (benchmarks/forks_runs.py). The controls were not rerun in full: a rerun of
# one for its first steps on the forks runs' machine matched it bitwise.
FORKS_SEEDS = GATED_TUNING_SEEDS
FORKS_QUANTILE = 0.2
FORKS_RERUN = "forks/rerun-gated-seed16-steps5"
# the keys of a step's log that the machine's speed moves and its arithmetic does not
TIMING_KEYS = {"gen_time", "train_time", "step_time", "tokens_per_s"}


def forks_pair_runs() -> tuple[list[Path], list[Path]]:
    """(forks runs, their controls: 6.8's gated tuning runs), paired by seed."""
    if not set(FORKS_SEEDS) <= set(GATED_TUNING_SEEDS):
        raise ValueError(f"lesson 7, 6.9's seeds {FORKS_SEEDS} are 6.8's tuning seeds {GATED_TUNING_SEEDS}, "
                         f"whose gated runs are its controls")
    forks = [RESULTS / "forks" / f"forks-seed{s}" for s in FORKS_SEEDS]
    missing = [_relative(r) for r in forks if not (r / "summary.json").exists()]
    if missing:
        raise ValueError(f"lesson 7, 6.9 needs a forks run on every seed {FORKS_SEEDS}: missing {missing} "
                         f"(python benchmarks/forks_runs.py --seed N)")
    return forks, [RESULTS / "gated" / "tuning" / f"gated-seed{s}" for s in FORKS_SEEDS]


def _check_forks_pairs() -> None:
    """What 6.9 says of its runs: each forks run is its seed's gated run with
    top_entropy_quantile = FORKS_QUANTILE and nothing else changed, in bf16 on a CPU with AMX;
    and the stored control, rerun on such a CPU for its first steps, matched bitwise."""
    for seed, forks, control in zip(FORKS_SEEDS, *forks_pair_runs()):
        f, c = (_config_with_defaults(_relative(r)) for r in (forks, control))
        changed = {k for k in c if k != "out_dir" and f[k] != c[k]}
        if changed != {"top_entropy_quantile"} or f["top_entropy_quantile"] != FORKS_QUANTILE or f["seed"] != seed:
            raise ValueError(f"lesson 7, 6.9 says {forks.name} is {control.name} with top_entropy_quantile="
                             f"{FORKS_QUANTILE} and nothing else changed; it changes {sorted(changed)}")
        summary = _json(f"{_relative(forks)}/summary.json")
        if summary["precision"] != "bf16" or summary.get("cpu", {}).get("bf16_units") != "AMX":
            raise ValueError(f"lesson 7, 6.9 says {forks.name} ran in bf16 on a CPU with AMX: "
                             f"{summary['precision']}, {summary.get('cpu')}")
    rerun = RESULTS / FORKS_RERUN
    config = _config_with_defaults(FORKS_RERUN)
    control = RESULTS / "gated" / "tuning" / f"gated-seed{config['seed']}"
    if {k for k, v in _config_with_defaults(_relative(control)).items()
            if k not in ("out_dir", "max_steps") and config[k] != v}:
        raise ValueError(f"lesson 7, 6.9 says {FORKS_RERUN} reruns {control.name}")
    if _json(f"{FORKS_RERUN}/summary.json").get("cpu", {}).get("bf16_units") != "AMX":
        raise ValueError(f"lesson 7, 6.9 says {FORKS_RERUN} ran on a CPU with AMX")
    from course_utils import ablation
    # every number the stored log holds, timings aside (the rerun's log has keys added since)
    again, stored = ablation.records(rerun), ablation.records(control)[:config["max_steps"]]
    same = len(again) == config["max_steps"] and all(
        x[k] == y.get(k) for x, y in zip(stored, again) for k in x
        if k not in TIMING_KEYS and not k.startswith("time_"))
    if not same:
        raise ValueError(f"lesson 7, 6.9 says {FORKS_RERUN} matches {control.name}'s first "
                         f"{config['max_steps']} steps bitwise")


BARE_CHARS, ECHO_CHARS = 5, 40


def forks_figures() -> dict[str, str]:
    """Lesson 7, 6.9: the forks arm against 6.8's gated runs on the tuning seeds, and the checks
    of what its prose says of them."""
    from course_utils import ablation, rewards, stats

    _check_forks_pairs()
    forks, control = forks_pair_runs()
    arms = {"forks": forks, "gated": control}
    after = {r: _json(f"{_relative(r)}/summary.json")["after"]["greedy"] for r in forks + control}
    logs = {r: ablation.records(r) for r in forks + control}
    # the replies sampled in training that passed both constraints, all and two-digit ones
    # (ablation.sampled_passes, in one window per run)
    trained = {r: ablation.sampled_passes(r, width=len(logs[r]))[0] for r in forks + control}
    sampled = {arm: [trained[r]["one_passed"] + trained[r]["two_passed"] for r in runs] for arm, runs in arms.items()}
    entropy_end = {r: ablation.tail_mean(logs[r], "entropy") for r in forks + control}
    truncated = {r: statistics.mean(x["truncated_frac"] for x in logs[r]) for r in forks + control}
    figs = {"forks.seed_list": _seeds(list(FORKS_SEEDS)), "forks.quantile": f"{FORKS_QUANTILE}",
            "forks.share": f"{FORKS_QUANTILE:.0%}",
            "forks.rerun_steps": f"{_config_with_defaults(FORKS_RERUN)['max_steps']}",
            "forks.forks_sampled_max": f"{max(sampled['forks'])}",
            "forks.gated_sampled_min": f"{min(sampled['gated'])}"}
    for arm, runs in arms.items():
        def per_run(value, fmt=""):   # one value per seed, as "a, b and c"
            return _seeds([value(r) for r in runs], fmt)
        figs |= {f"forks.{arm}_mean": f"{statistics.mean(after[r]['pass_both'] for r in runs):.1%}",
                 f"forks.{arm}_worst": f"{min(after[r]['pass_both'] for r in runs):.1%}",
                 f"forks.{arm}_two_mean": f"{statistics.mean(after[r]['pass_both_two_digit'] for r in runs):.1%}",
                 f"forks.{arm}_sampled": _seeds(sampled[arm]),
                 f"forks.{arm}_two_of": per_run(lambda r: f"{trained[r]['two_passed']} of "
                                                          f"{trained[r]['two_sampled']:,}"),
                 f"forks.{arm}_digits_sampled": per_run(lambda r: statistics.mean(x["pass_digits"] for x in logs[r]), ".0%"),
                 f"forks.{arm}_entropy_end": per_run(entropy_end.get, ".2f"),
                 f"forks.{arm}_tokens": per_run(lambda r: ablation.tail_mean(logs[r], "completion_tokens"), ".1f"),
                 f"forks.{arm}_truncated": per_run(truncated.get, ".0%"),
                 f"forks.{arm}_length_ok": per_run(lambda r: after[r]["pass_length"], ".1%"),
                 f"forks.{arm}_kl": per_run(lambda r: statistics.mean(x["kl"] for x in logs[r]), ".2f"),
                 f"forks.{arm}_bonus_steps": per_run(lambda r: sum(x["entropy_weight"] > 0 for x in logs[r]))}
    # what 6.9's prose says of every pair: the forks run ended with a higher entropy, had more
    # replies cut off at the cap in training and fewer of the right length held out; no forks
    # run passed a held-out prompt or sampled as many passes as any control; its adaptive bonus
    # never switched on; and the verdict, dropping the lever, needs it to have done worse
    pairs = list(zip(forks, control))
    for what, value in (("ended with a higher entropy", entropy_end), ("had more replies cut off", truncated)):
        if not all(value[f] > value[c] for f, c in pairs):
            raise ValueError(f"lesson 7, 6.9 says every forks run {what} than its control: "
                             f"{[[value[r] for r in pair] for pair in pairs]}")
    length_ok = [[after[r]["pass_length"] for r in pair] for pair in pairs]
    if not all(f < c for f, c in length_ok):
        raise ValueError(f"lesson 7, 6.9 says every forks run had fewer held-out replies of the right length: {length_ok}")
    both = stats.paired([after[r]["pass_both"] for r in forks], [after[r]["pass_both"] for r in control])
    if not both.mean < 0:
        raise ValueError(f"lesson 7, 6.9 drops the lever because it did worse on these seeds: {both}")
    if any(after[r]["pass_both"] > 0 for r in forks) or max(sampled["forks"]) >= min(sampled["gated"]):
        raise ValueError(f"lesson 7, 6.9 says no forks run passed a held-out prompt, and each sampled fewer "
                         f"passing replies than any control: {sampled}")
    if any(x["entropy_weight"] > 0 for r in forks for x in logs[r]):
        raise ValueError("lesson 7, 6.9 says the adaptive entropy bonus never switched on in a forks run")
    figs["forks.seeds_below"] = _seeds_above([after[r]["pass_both"] for r in control],
                                             [after[r]["pass_both"] for r in forks])
    # the forks runs' held-out replies: bare digits (at most BARE_CHARS characters) and long ones
    # (ECHO_CHARS or more), and what the gated credit pays a bare right digit
    samples = [after[r]["samples"] for r in forks]
    config = _json(f"{_relative(forks[0])}/config.json")
    bare = rewards.check("7", config["target_chars"], 7)
    figs |= {"forks.bare": _seeds([sum(x["n_chars"] <= BARE_CHARS for x in s) for s in samples]),
             "forks.echo": _seeds([sum(x["n_chars"] >= ECHO_CHARS for x in s) for s in samples]),
             "forks.held_out": f"{len(samples[0])}", "forks.bare_chars": f"{BARE_CHARS}",
             "forks.echo_chars": f"{ECHO_CHARS}", "forks.target_chars": f"{config['target_chars']}",
             "forks.bare_gated": f"{rewards.gated_score(bare, config['target_chars'], 7):.2f}",
             "forks.samples_per_run": f"{config['max_steps'] * config['prompts_per_step'] * config['group_size']:,}",
             "forks.kl_coef": f"{config['kl_coef']}",
             # the base model's replies: the first step samples before any update
             "forks.first_truncated": _seeds([logs[r][0]["truncated_frac"] for r in forks], ".0%")}
    # the share of a step's tokens the mask kept; with the denominators unchanged the policy term
    # shrinks to about that share while the KL keeps its weight, so against the policy term the
    # KL weighs about 1 / kept times as much; and the tokens of a reply the policy term reached
    kept = [statistics.mean(x["high_entropy_frac"] for x in logs[r]) for r in forks]
    kept_per_reply = [statistics.mean(x["high_entropy_frac"] * x["completion_tokens"] for x in logs[r]) for r in forks]
    return figs | {"forks.kept": _seeds(kept, ".1%"), "forks.kl_scale": f"{1 / statistics.mean(kept):.0f}",
                   "forks.kept_per_reply": _seeds(kept_per_reply, ".1f")}


def fresh_preset() -> dict:
    """The cpu preset on the same fresh seeds, as ``python -m course_utils.ablation --seeds 10 11
    12 13 14 --arms "full recipe (the cpu preset)" --out notebooks/results/fresh-seeds/preset``
    stored it (its result.json)."""
    return _json("fresh-seeds/preset/result.json")


def fresh_figures() -> dict[str, str]:
    """Lesson 7, section 6.5, and the README: the counted-KL recipe, frozen, on fresh seeds
    (``notebooks/results/fresh-seeds``), against the same recipe on its tuning seeds and the
    cpu preset on the fresh ones."""
    from course_utils import ablation

    fresh, tuning = fresh_runs(), counted_kl_runs()
    after = lambda run: _json(f"{run.parent.name}/{run.name}/summary.json")["after"]["greedy"]  # noqa: E731
    fresh_after, tuning_after = [after(r) for r in fresh], [after(r) for r in tuning]
    fresh_passed, tuning_passed = [a["pass_both"] for a in fresh_after], [a["pass_both"] for a in tuning_after]
    seeds = [_json(f"fresh-seeds/{run.name}/config.json")["seed"] for run in fresh]
    endings = [ablation.probe_outcome(ablation.records(run)) for run in fresh]
    preset = fresh_preset()
    if preset["seeds"] != seeds:
        raise ValueError(f"the preset's fresh-seed runs have seeds {preset['seeds']}, the recipe's {seeds}")
    preset_passed = [run["pass_both"] for run in preset["arms"][ablation.FULL]["runs"]]
    return {"fresh.seed_list": _seeds(seeds),
            "fresh.seeds": _word(len(fresh)),
            "fresh.mean": f"{statistics.mean(fresh_passed):.1%}",
            "fresh.two_digit_mean": f"{statistics.mean(a['pass_both_two_digit'] for a in fresh_after):.1%}",
            "fresh.worst": f"{min(fresh_passed):.1%}",
            "fresh.tuning_mean": f"{statistics.mean(tuning_passed):.1%}",
            "fresh.tuning_worst": f"{min(tuning_passed):.1%}",
            # how many fresh seeds ended filling the token cap (ablation.probe_outcome's rule)
            "fresh.cap_filling": _word(endings.count("filling the token cap")),
            # seeds whose greedy replies pass every one-digit target held out
            "fresh.template_seeds": _word(sum(a["pass_both_one_digit"] == 1 for a in fresh_after)),
            "fresh.tuning_template_seeds": _word(sum(a["pass_both_one_digit"] == 1 for a in tuning_after)),
            "fresh.tuning_seeds": _word(len(tuning)),
            "fresh.preset_mean": f"{statistics.mean(preset_passed):.1%}",
            "fresh.preset_worst": f"{min(preset_passed):.1%}",
            "fresh.order_chance": _order_chance(tuning_passed, fresh_passed)}


def _order_chance(tuning: list[float], fresh: list[float]) -> str:
    """Lesson 7, 6.5: every tuning seed passes more than every fresh seed. Were the labels
    exchangeable (tuning no better than fresh), each of the C(n, k) ways to pick which k of the
    n seeds are the tuning ones would be equally likely, and exactly one puts all k on top: an
    exact one-sided permutation p-value of 1 / C(n, k)."""
    if min(tuning) <= max(fresh):
        raise ValueError("lesson 7 says every tuning seed passes more than every fresh seed; "
                         f"tuning {tuning}, fresh {fresh}")
    return f"1 in {math.comb(len(tuning) + len(fresh), len(tuning))}"


def data_figures() -> dict[str, str]:
    """The offline prompt set: how many snippets the held-out prompts are built from."""
    from course_utils import data

    held_out = [s for s in data.offline_snippets() if data.is_held_out(s)]
    return {"data.held_out_snippets": f"{len(held_out)}"}


def figures() -> dict[str, str]:
    return {**plan_figures(), **gpu_check_figures(), **track_figures(), **cpu_run_figures(), **data_figures(),
            **fresh_figures(), **cap_figures(), **precision_figures(), **gated_figures(), **forks_figures()}


def fill(text: str, source: str) -> str:
    """Replace every ``{{fig:NAME}}`` in a lesson's text; an unknown name is an error."""
    known = figures()
    unknown = sorted(set(re.findall(r"\{\{fig:([\w.]+)\}\}", text)) - set(known))
    if unknown:
        raise ValueError(f"{source}: unknown figure(s) {unknown}; add them to notebooks/figures.py")
    return re.sub(r"\{\{fig:([\w.]+)\}\}", lambda m: known[m.group(1)], text)
