"""The learner tracks of lesson 8: each experiment as a function that writes its numbers and
plots to a folder, so the notebook, the command line and a test all run the same code.

    python -m course_utils.tracks all --out notebooks/results/tracks        # about 75 minutes, 2 cores
    python -m course_utils.tracks grouping --seeds 0 1 2

Training runs are the ``cpu`` preset shortened (``SHORT``) and kept in ``runs/tracks/``; a run
whose summary already exists is reused, so the tracks share runs (plain GRPO, seed s, is the
"no entropy bonus", "per-prompt groups" and "no KL" arm at once) and an interrupted command picks
up where it stopped. With ``COURSE_SMOKE=1`` everything shrinks to seconds on the tiny model.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from pathlib import Path

import torch

from . import data, models, stats, train
from .config import load_config, smoke_mode

# The cpu preset as these tracks were run (the shaped reward, no dynamic sampling: the preset
# before lesson 7's fixes), shortened to 12 steps of 4 prompts x 8 (2-4 minutes a run on 2
# cores). Pinned here, so the stored results stay reproducible whatever the preset becomes.
SHORT = dict(train_prompts=48, max_steps=None, eval_prompts=32, save_every=12, reward="shaped",
             dynamic_sampling=False, lr=3e-5, max_new_tokens=32)
SMOKE = dict(model="tiny-qwen2", prompt_tokens=16, prompts_per_step=2, group_size=4,
             max_new_tokens=10, train_prompts=4, eval_prompts=4, save_every=2, lr=1e-3)
RUNS = Path("runs/tracks")


# --- shared helpers ----------------------------------------------------------------------------

def base_settings() -> dict:
    """The settings every track's runs share (on top of the cpu preset)."""
    return {**SHORT, **(SMOKE if smoke_mode() else {})}


def finished(run_dir: Path) -> bool:
    """Whether a run got as far as its final evaluation (then it is reused, not retrained)."""
    summary = Path(run_dir) / "summary.json"
    return summary.exists() and "after" in json.loads(summary.read_text())


def run(name: str, seed: int, **overrides) -> Path:
    """Train one arm for one seed (or reuse it if its summary exists); returns its directory."""
    out = RUNS / ("smoke" if smoke_mode() else "full") / name / f"seed{seed}"
    if finished(out):
        return out
    # a progress bar for real runs (minutes each); none in smoke mode, where runs take seconds
    # resume=True: a run that stopped part-way (a crash, Ctrl-C) continues where it stopped
    train.train(load_config("cpu", seed=seed, out_dir=str(out), **{**base_settings(), **overrides}),
                resume=True, progress=not smoke_mode())
    return out


def records(run_dir: Path) -> list[dict]:
    return [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


def summary(run_dir: Path) -> dict:
    return json.loads((run_dir / "summary.json").read_text())


def final_rewards(arms: dict[str, list[Path]]) -> dict[str, list[float]]:
    """Per arm, the held-out greedy mean reward after training, one value per seed."""
    return {arm: [summary(d)["after"]["greedy"]["reward_mean"] for d in dirs] for arm, dirs in arms.items()}


def sample_reward(sample: dict) -> float:
    """The shaped reward of one evaluation sample, recomputed from its completion and targets."""
    check = train.rewards.check(sample["completion"], sample["target_chars"], sample["target_digit_sum"])
    return train.rewards.shaped_score(check, sample["target_chars"], sample["target_digit_sum"])


def mean_std(values: list[float]) -> str:
    if len(values) < 2:
        return f"{values[0]:.3f}"
    return f"{statistics.mean(values):.3f} ± {statistics.stdev(values):.3f}"


def differs(a: list[float], b: list[float]) -> str:
    """The verdict on arm ``a`` against arm ``b``, run on the same seeds in the same order: a
    paired comparison (``course_utils.stats.paired``), every seed's difference shown, a
    t-interval on n - 1 degrees of freedom, the exact sign-flip p-value, and beside a "no
    difference detected" the difference the seeds could have detected."""
    if len(a) != len(b):
        raise ValueError(f"paired arms need the same seeds; got {len(a)} and {len(b)} values")
    if len(a) < 2:
        return "too few seeds to tell"
    return stats.paired(a, b).verdict()


# Every comparison a track's report prints, as data, so a stored report's verdicts can be
# recomputed from its result.json alone (``rerender_verdicts``): (label, (key, arm a), (key, arm b)).
JOINT, ALONE = "joint (retriever learns)", "generator only (uniform retriever)"
RETRIEVER_COST = "the retriever's update took"
VERDICTS: dict[str, list[tuple[str, tuple[str, str], tuple[str, str]]]] = {
    "grouping": [("per-prompt vs whole batch", ("final_reward", "per-prompt groups (GRPO)"),
                  ("final_reward", "whole batch (the seed)"))],
    "entropy": [("inverse variance vs none (final reward)",
                 ("final_reward", "inverse variance (1e-3 / Var)"), ("final_reward", "none")),
                ("inverse variance vs constant (final reward)",
                 ("final_reward", "inverse variance (1e-3 / Var)"), ("final_reward", "constant 0.05")),
                # not planned: added after the stored results were seen (lesson 8 says so)
                ("constant vs none (final reward; a comparison chosen after seeing the results)",
                 ("final_reward", "constant 0.05"), ("final_reward", "none"))],
    "kl": [("reward-aware vs constant KL (Δ log-likelihood)", ("delta_loglik", "reward-aware KL 0.04"),
            ("delta_loglik", "constant KL 0.04")),
           ("reward-aware KL vs plain (final reward)", ("final_reward", "reward-aware KL 0.04"),
            ("final_reward", "plain GRPO (no KL)"))],
    "retrieval": [("joint vs generator only, reward", ("final_reward", JOINT), ("final_reward", ALONE)),
                  ("joint vs generator only, P(passing example)", ("p_helpful", JOINT),
                   ("p_helpful", ALONE))],
}


def verdict_lines(track: str, result: dict) -> str:
    """The report's comparison lines for ``track``, from its result (``VERDICTS``)."""
    lines = [f"{label}: {differs(result[ka][a], result[kb][b])}"
             for label, (ka, a), (kb, b) in VERDICTS[track]]
    return "\n\n".join(lines)


def rerender_verdicts(track: str, folder: Path) -> str:
    """Rewrite the comparison lines of a stored report from its result.json: every line that
    starts with one of the track's labels is replaced, in place, by the recomputed lines."""
    folder = Path(folder)
    result = json.loads((folder / "result.json").read_text())
    labels = tuple(f"{label}:" for label, _, _ in VERDICTS[track])
    if track == "retrieval":   # its cost figure shared the old comparison line; now its own
        labels += (RETRIEVER_COST,)
    lines = (folder / "report.md").read_text().split("\n")
    kept, at = [], None
    for line in lines:
        if line.startswith(labels):
            at = len(kept) if at is None else at
            continue
        kept.append(line)
    if at is None:
        raise ValueError(f"{folder / 'report.md'} has no comparison line of the {track} track")
    # the blank lines that separated the old comparison lines collapse to one
    while at < len(kept) - 1 and kept[at] == "" and kept[at + 1] == "":
        del kept[at]
    new = verdict_lines(track, result).split("\n")
    if track == "retrieval":   # its cost figure shared the old comparison line
        new += ["", f"{RETRIEVER_COST} {result['retriever_ms']:.1f} ms a step"]
    report = "\n".join(kept[:at] + new + kept[at:])
    (folder / "report.md").write_text(report)
    return report


def plot_curves(arms: dict[str, list[Path]], keys: list[tuple[str, str]], path: Path,
                smooth: int = 3) -> None:
    """One panel per metric; per arm the mean over seeds (line) and the range (band)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, len(keys), figsize=(4.3 * len(keys), 3.0), squeeze=False)
    for ax, (key, title) in zip(axes[0], keys):
        for arm, dirs in arms.items():
            curves = [[r.get(key, float("nan")) for r in records(d)] for d in dirs]
            n = min(len(c) for c in curves)
            curves = [[statistics.mean(c[max(0, i - smooth + 1):i + 1]) for i in range(n)] for c in curves]
            steps = list(range(1, n + 1))
            mean = [statistics.mean(c[i] for c in curves) for i in range(n)]
            line, = ax.plot(steps, mean, label=arm)
            ax.fill_between(steps, [min(c[i] for c in curves) for i in range(n)],
                            [max(c[i] for c in curves) for i in range(n)], alpha=0.2, color=line.get_color())
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("step")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def steps_to(run_dir: Path, key: str, threshold: float, smooth: int = 3) -> float:
    """First step at which the moving average of ``key`` reaches ``threshold`` (inf if never)."""
    values = [r[key] for r in records(run_dir)]
    for i in range(len(values)):
        if statistics.mean(values[max(0, i - smooth + 1):i + 1]) >= threshold:
            return i + 1
    return math.inf


def write(out: Path, report: str, result: dict) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "report.md").write_text(report)
    (out / "result.json").write_text(json.dumps(result, indent=2))
    print(report)


# --- track: per-prompt groups or whole-batch normalization -------------------------------------

def exact_grouping(group_size: int = 8, batches: int = 20_000, seed: int = 0) -> dict:
    """Bias and variance of four advantage normalizations against the exact gradient, on a
    problem small enough to have one: 4 prompts of different difficulty, each a softmax over 6
    answers of which 5, 3, 2 or 1 are right (reward 1, else 0), from a random starting policy. One batch = every prompt with G samples; the estimate is
    1/(K G) sum_i A_i grad log pi(a_i | prompt), averaged over ``batches`` batches."""
    gen = torch.Generator().manual_seed(seed)
    K, A = 4, 6
    reward = torch.zeros(K, A)
    for k, n_right in enumerate((5, 3, 2, 1)):        # easy ... hard
        reward[k, :n_right] = 1.0
    theta = torch.randn(K, A, generator=gen, dtype=torch.float64) * 0.8
    pi = theta.softmax(-1)
    exact = (pi * (reward - (pi * reward).sum(-1, keepdim=True))) / K   # d/dtheta of mean_k E[r]
    actions = torch.multinomial(pi.repeat(batches, 1), group_size, replacement=True, generator=gen)
    actions = actions.view(batches, K, group_size)
    r = reward.double()[torch.arange(K)[None, :, None], actions]         # [M, K, G]
    eps = 1e-4
    g_mean, g_std = r.mean(-1, keepdim=True), r.std(-1, keepdim=True)
    flat = r.reshape(batches, -1)
    b_mean, b_std = flat.mean(-1)[:, None, None], flat.std(-1)[:, None, None]
    group_constant = (r.amax(-1, keepdim=True) == r.amin(-1, keepdim=True))
    advantages = {
        "per-prompt mean and std (GRPO)": torch.where(group_constant, 0.0, (r - g_mean) / (g_std + eps)),
        "per-prompt mean only (Dr. GRPO)": r - g_mean,
        "whole-batch mean and std (the seed)": (r - b_mean) / (b_std + eps),
        "whole-batch mean only": r - b_mean,
    }
    one_hot = torch.nn.functional.one_hot(actions, A).double()            # [M, K, G, A]
    score = one_hot - pi[None, :, None, :]                                # grad log pi per sample
    rows = {}
    for name, adv in advantages.items():
        g = (adv[..., None] * score).sum(2) / (K * group_size)            # [M, K, A]
        mean = g.mean(0)
        cos = float((mean * exact).sum() / (mean.norm() * exact.norm()))
        # the best rescaling c* mean of the estimate, to separate direction from size
        c = float((mean * exact).sum() / (mean * mean).sum())
        direction_error = float((c * mean - exact).norm() / exact.norm())
        noise = float(((g - mean) ** 2).sum((1, 2)).mean().sqrt() / mean.norm())
        per_prompt = (mean.norm(dim=-1) / exact.norm(dim=-1)).tolist()
        rows[name] = dict(cosine=cos, direction_error=direction_error, noise_to_signal=noise, rescale=c,
                          weight_per_prompt=[w / per_prompt[0] for w in per_prompt])
    return dict(pass_probability=(pi * reward).sum(-1).tolist(), estimators=rows,
                group_size=group_size, batches=batches)


def grouping(seeds: list[int], out: Path) -> dict:
    exact = exact_grouping(batches=2_000 if smoke_mode() else 20_000)
    arms = {"per-prompt groups (GRPO)": [run("plain", s) for s in seeds],
            "whole batch (the seed)": [run("batch-norm", s, advantage_center="batch",
                                           advantage_scale="batch") for s in seeds]}
    plot_curves(arms, [("reward_mean", "training reward"), ("chars_abs_error", "|chars - target|"),
                       ("adv_abs_mean", "mean |advantage|")], out / "curves.png")
    final = final_rewards(arms)
    lines = ["| estimator | cosine to exact gradient | direction error | noise / signal | weight of prompts easy → hard |",
             "|---|---|---|---|---|"]
    for name, row in exact["estimators"].items():
        weights = ", ".join(f"{w:.2f}" for w in row["weight_per_prompt"])
        lines.append(f"| {name} | {row['cosine']:.3f} | {row['direction_error']:.3f} | "
                     f"{row['noise_to_signal']:.2f} | {weights} |")
    p = ", ".join(f"{x:.2f}" for x in exact["pass_probability"])
    report = (f"**Exact comparison** ({exact['batches']:,} batches of 4 prompts x {exact['group_size']}; "
              f"pass probabilities of the prompts at the start: {p}):\n\n" + "\n".join(lines) +
              f"\n\n**Real runs** (SmolLM2, {len(seeds)} seeds): held-out greedy mean reward after training\n\n"
              "| arm | reward |\n|---|---|\n" +
              "\n".join(f"| {arm} | {mean_std(v)} |" for arm, v in final.items()) +
              "\n\n" + verdict_lines("grouping", dict(final_reward=final)) + "\n")
    result = dict(exact=exact, final_reward=final)
    write(out, report, result)
    return result


# --- track: entropy bonus, dynamic vs constant vs none ----------------------------------------

# The dynamic weight is entropy_coef / Var(r). At the start of these runs Var(r) is about 0.02,
# so coef 1e-3 gives ~0.05: the constant arm uses that value, so the two differ in *how* the
# weight moves, not in its typical size.
ENTROPY_ARMS = {"none": {}, "constant 0.05": dict(entropy_bonus="constant", entropy_coef=0.05),
                "inverse variance (1e-3 / Var)": dict(entropy_bonus="inverse_variance",
                                                      entropy_coef=1e-3, entropy_weight_max=0.2)}
REWARD_THRESHOLD = 0.6


def entropy(seeds: list[int], out: Path) -> dict:
    arms = {arm: [run("plain" if not kw else "entropy-" + kw["entropy_bonus"], s, **kw) for s in seeds]
            for arm, kw in ENTROPY_ARMS.items()}
    plot_curves(arms, [("reward_mean", "training reward"), ("reward_std", "reward std"),
                       ("entropy", "token entropy"), ("entropy_weight", "entropy weight")],
                out / "curves.png")
    steps = {arm: [steps_to(d, "reward_mean", REWARD_THRESHOLD) for d in dirs] for arm, dirs in arms.items()}
    final = final_rewards(arms)
    ent = {arm: [statistics.mean(r["entropy"] for r in records(d)[-4:]) for d in dirs] for arm, dirs in arms.items()}
    rows = [f"| {arm} | {', '.join('never' if math.isinf(x) else str(x) for x in steps[arm])} | "
            f"{mean_std(final[arm])} | {mean_std(ent[arm])} |" for arm in arms]
    report = (f"Steps until the training reward (3-step average) reaches {REWARD_THRESHOLD}, "
              f"held-out greedy reward after training, token entropy over the last 4 steps "
              f"({len(seeds)} seeds):\n\n| arm | steps to threshold, per seed | final reward | "
              "late entropy |\n|---|---|---|---|\n" + "\n".join(rows) +
              "\n\n" + verdict_lines("entropy", dict(final_reward=final)) + "\n")
    result = dict(steps_to_threshold={k: [None if math.isinf(x) else x for x in v] for k, v in steps.items()},
                  final_reward=final, late_entropy=ent)
    write(out, report, result)
    return result


# --- track: a reward-aware KL schedule, and its falsifier --------------------------------------

KL_ARMS = {"plain GRPO (no KL)": {}, "constant KL 0.04": dict(kl_coef=0.04),
           "reward-aware KL 0.04": dict(kl_coef=0.04, kl_schedule="reward_aware")}


@torch.no_grad()
def text_loglik(model, tokenizer, lines: list[str]) -> float:
    """Mean log-likelihood per token of ``lines`` (each scored on its own, first token given)."""
    total, count = 0.0, 0
    for line in lines:
        ids = tokenizer(line, return_tensors="pt", add_special_tokens=False).input_ids
        logits = model(input_ids=ids).logits[0, :-1].float()
        total += float(logits.log_softmax(-1).gather(-1, ids[0, 1:, None]).sum())
        count += ids.shape[1] - 1
    return total / count


def facts() -> list[str]:
    path = Path(__file__).with_name("assets") / "facts.txt"
    return [line for line in path.read_text().splitlines() if line.strip()]


def kl_schedule(seeds: list[int], out: Path) -> dict:
    arms = {arm: [run("plain" if not kw else "kl-" + kw.get("kl_schedule", "constant"), s, **kw) for s in seeds]
            for arm, kw in KL_ARMS.items()}
    plot_curves(arms, [("reward_mean", "training reward"), ("kl", "k3 KL to the reference"),
                       ("kl_coef", "KL coefficient")], out / "curves.png")
    cfg = load_config("cpu", **base_settings())
    tokenizer = models.load_tokenizer(cfg.model)
    lines = facts()[:4] if smoke_mode() else facts()
    reference = text_loglik(models.load_policy(cfg.model), tokenizer, lines)
    final, falsifier = final_rewards(arms), {}
    knowledge = {arm: [text_loglik(models.load_policy(str(d / "checkpoint")), tokenizer, lines) - reference
                       for d in dirs] for arm, dirs in arms.items()}
    for arm in list(arms)[1:]:   # per held-out prompt, greedy reward against plain GRPO, same seed
        worse, total = [], 0
        for plain_dir, dir_ in zip(arms["plain GRPO (no KL)"], arms[arm]):
            a = summary(plain_dir)["after"]["greedy"]["samples"]
            b = summary(dir_)["after"]["greedy"]["samples"]
            for x, y in zip(a, b):
                rx, ry = sample_reward(x), sample_reward(y)
                total += 1
                if ry < rx - 1e-9:
                    worse.append(dict(snippet=y["snippet"], plain=round(rx, 3), constrained=round(ry, 3)))
        falsifier[arm] = dict(worse=len(worse), of=total, examples=worse[:5])
    rows = [f"| {arm} | {mean_std(final[arm])} | {mean_std(knowledge[arm])} | " +
            (f"{falsifier[arm]['worse']} of {falsifier[arm]['of']}" if arm in falsifier else "-") + " |"
            for arm in arms]
    report = (f"Held-out greedy reward, change in log-likelihood per token of {len(lines)} factual "
              f"sentences against the pre-trained model (0 = knowledge untouched; more negative = "
              f"more forgotten), and the falsifier: held-out prompts where the arm's greedy "
              f"completion scores lower than plain GRPO's ({len(seeds)} seeds):\n\n"
              "| arm | final reward | Δ log-likelihood of facts | prompts worse than plain GRPO |\n"
              "|---|---|---|---|\n" + "\n".join(rows) + "\n\n" +
              verdict_lines("kl", dict(final_reward=final, delta_loglik=knowledge)) + "\n")
    result = dict(final_reward=final, delta_loglik=knowledge, falsifier=falsifier, reference_loglik=reference)
    write(out, report, result)
    return result


# --- track: the CS student's base model with a fixed rule --------------------------------------

def base_model(seeds: list[int], out: Path) -> dict:
    """The gpt2-rtx4070 recipe's shape on the embedded model: raw prompts (no chat template, no
    instruction: the rule is fixed, 32 characters and digit sum 10), 8 prompts per step."""
    kw = dict(prompt_style="raw", target_chars=32, digit_sum_min=10, digit_sum_max=10,
              prompts_per_step=8 if not smoke_mode() else 2, train_prompts=96 if not smoke_mode() else 4)
    arms = {"raw prompts, fixed rule": [run("raw", s, **kw) for s in seeds]}
    plot_curves(arms, [("reward_mean", "training reward"), ("chars_abs_error", "|chars - target|"),
                       ("completion_tokens", "completion tokens")], out / "curves.png")
    rows = []
    for mode in ("sampled", "greedy"):
        for key, label in (("reward_mean", "mean reward"), ("chars_abs_error", "mean abs(chars - 32)"),
                           ("pass_both", "both constraints")):
            before = [summary(d)["before"][mode][key] for d in arms["raw prompts, fixed rule"]]
            after = [summary(d)["after"][mode][key] for d in arms["raw prompts, fixed rule"]]
            rows.append(f"| {label} ({mode}) | {mean_std(before)} | {mean_std(after)} |")
    from . import plan
    from transformers import GPT2Config
    gpt2 = GPT2Config()
    arch = plan.Architecture(n_params=124_439_808, hidden=gpt2.n_embd, layers=gpt2.n_layer,
                             kv_dim=gpt2.n_embd, intermediate=4 * gpt2.n_embd, vocab=gpt2.vocab_size)
    preset = load_config("gpt2-rtx4070")
    mem = plan.memory_plan(arch, preset, prompt_len=128, completion_len=preset.max_new_tokens)
    peak = plan.peak_bytes(mem) / plan.GiB
    report = (f"SmolLM2 with raw prompts ({len(seeds)} seeds), held-out before → after:\n\n"
              "| metric | before | after |\n|---|---|---|\n" + "\n".join(rows) +
              f"\n\nMemory plan of the `gpt2-rtx4070` preset (gpt2, 124M parameters, 8 prompts x 8 "
              f"in one micro-batch, 128-token prompts, bf16 autocast over fp32 master weights; "
              f"the activation count is the Llama-style block's, an approximation for gpt2): about "
              f"{peak:.1f} GiB peak against the RTX 4070's 12 GB.\n")
    result = dict(peak_gib_gpt2=peak)
    write(out, report, result)
    return result


# --- track: the applied engineer's int8 serving ------------------------------------------------

def _latencies(model, tokenizer, prompts: list[str], max_new_tokens: int, use_cache: bool) -> list[float]:
    times = []
    for text in prompts:
        ids = tokenizer(text, return_tensors="pt", add_special_tokens=False)
        start = time.perf_counter()
        model.generate(**ids, max_new_tokens=max_new_tokens, min_new_tokens=max_new_tokens,
                       do_sample=False, use_cache=use_cache, pad_token_id=tokenizer.pad_token_id)
        times.append(time.perf_counter() - start)
    return times


def _weight_bytes(model) -> int:
    """Bytes of every weight, quantized ones included (they hide inside packed parameters),
    each stored tensor counted once (SmolLM2's embedding and output layer share one)."""
    seen, total = set(), 0
    for module in model.modules():
        weight = getattr(module, "weight", None)
        weight = weight() if callable(weight) else weight
        if not torch.is_tensor(weight):
            continue
        if not weight.is_quantized:           # (a packed int8 weight has no shareable pointer)
            if weight.data_ptr() in seen:
                continue
            seen.add(weight.data_ptr())
        total += weight.numel() * weight.element_size()
    return total


def quantize_int8(model):
    """CPU int8: every nn.Linear's weights stored as int8 with one scale per output row, and
    activations quantized on the fly (torch's dynamic quantization). On a GPU the same step is
    bitsandbytes' 8-bit loading (``load_in_8bit``)."""
    import warnings

    from torch.ao.quantization import quantize_dynamic

    with warnings.catch_warnings():   # torch points to torchao as the future home of this API
        warnings.simplefilter("ignore")
        return quantize_dynamic(model, {torch.nn.Linear}, dtype=torch.qint8)


def serving(seeds: list[int], out: Path) -> dict:
    """Quantize the plain GRPO policy of the first seed, serve it with transformers generation,
    with and without the KV cache; latency percentiles, throughput and the pass rate."""
    trained = run("plain", seeds[0]) / "checkpoint"
    cfg = load_config("cpu", **base_settings())
    tokenizer = models.load_tokenizer(cfg.model)
    prompts = data.make_prompts(cfg, tokenizer, held_out=True)
    n_requests, new_tokens = (4, 4) if smoke_mode() else (24, 24)
    texts = [p.text for p in prompts][:n_requests]
    fp32 = models.load_policy(str(trained))
    int8 = quantize_int8(models.load_policy(str(trained)))
    eos = models.eos_token_ids(fp32, tokenizer)
    rows, result = [], {}
    for name, model in (("fp32", fp32), ("int8 (dynamic)", int8)):
        ev = train.evaluate(model, tokenizer, prompts, cfg, eos, greedy=True)
        entry = dict(reward=ev["reward_mean"], pass_both=ev["pass_both"], chars_error=ev["chars_abs_error"])
        for cache in (True, False):
            lat = sorted(_latencies(model, tokenizer, texts, new_tokens, cache))
            p50, p95 = lat[len(lat) // 2], lat[min(len(lat) - 1, math.ceil(0.95 * len(lat)) - 1)]
            entry[f"cache={cache}"] = dict(p50_s=p50, p95_s=p95, tokens_per_s=new_tokens * len(lat) / sum(lat))
            rows.append(f"| {name} | {'on' if cache else 'off'} | {p50 * 1000:.0f} | {p95 * 1000:.0f} | "
                        f"{new_tokens * len(lat) / sum(lat):.1f} | {ev['reward_mean']:.3f} | "
                        f"{ev['chars_abs_error']:.1f} |")
        result[name] = entry
    size = {name: _weight_bytes(m) for name, m in (("fp32", fp32), ("int8", int8))}
    n_int8 = sum(1 for m in int8.modules() if "quantized" in type(m).__module__ and hasattr(m, "weight"))
    report = (f"One request at a time, {new_tokens} new tokens each (greedy, forced length), "
              f"{len(texts)} requests; quality on {len(prompts)} held-out prompts (greedy):\n\n"
              "| weights | KV cache | p50 ms | p95 ms | tokens/s | mean reward | mean abs(chars - target) |\n"
              "|---|---|---|---|---|---|---|\n" + "\n".join(rows) +
              f"\n\nweights in memory: fp32 {size['fp32'] / 2**20:.0f} MiB, int8 {size['int8'] / 2**20:.0f} MiB "
              f"({n_int8} linear layers quantized, the output layer among them; the embedding stays fp32)\n")
    result["state_dict_mib"] = {k: v / 2 ** 20 for k, v in size.items()}
    write(out, report, result)
    return result


# --- track: the policy gradient of a retrieval-augmented policy -------------------------------

def _two_stage(success: list[float]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A uniform retriever over len(success) documents, a generator that answers right (y = 0,
    reward 1) with probability success[d] given document d, else wrong (y = 1, reward 0)."""
    p = torch.tensor(success, dtype=torch.float64)
    theta = torch.stack([p.log(), (1 - p).log()], -1)
    return torch.zeros(len(success), dtype=torch.float64), theta, torch.tensor([1.0, 0.0], dtype=torch.float64)


def exact_retrieval(batches: int = 20_000, group: int = 8, seed: int = 0) -> dict:
    """The decomposition against autograd on random problems, then bias and noise of each part
    under four baselines and of the cross-document estimator, then the retriever's
    signal-to-noise ratio against the number of documents and the generator's quality."""
    from . import retrieval

    gen = torch.Generator().manual_seed(seed)
    split_error = 0.0
    for _ in range(5):   # random problems: K documents, Y answers, any rewards
        K, Y = int(torch.randint(2, 7, (1,), generator=gen)), int(torch.randint(2, 6, (1,), generator=gen))
        phi, theta = torch.randn(K, generator=gen, dtype=torch.float64), torch.randn(K, Y, generator=gen, dtype=torch.float64)
        reward = torch.rand(Y, generator=gen, dtype=torch.float64)
        parts, exact = retrieval.score_function_parts(phi, theta, reward), retrieval.exact_gradients(phi, theta, reward)
        split_error = max(split_error, *(float((a - b).abs().max()) for a, b in zip(parts, exact)))

    success = [0.8, 0.5, 0.3, 0.1]
    phi, theta, reward = _two_stage(success)
    d, y = retrieval.sample(phi, theta, batches, group, gen)
    exact_phi, exact_theta = retrieval.exact_gradients(phi, theta, reward)
    rows = {}
    for kind in retrieval.BASELINES:
        g_phi, g_theta = retrieval.estimates(phi, theta, reward, d, y, kind)
        rows[kind] = dict(retriever=retrieval.summarize(g_phi, exact_phi),
                          generator=retrieval.summarize(g_theta, exact_theta))
    rows["cross-document (retriever only)"] = dict(retriever=retrieval.summarize(
        retrieval.cross_document_retriever_estimate(phi, theta, reward, d, y), exact_phi))

    snr = {}
    for K in (2, 4, 8, 16):
        for good in (0.3, 0.5, 0.8):
            phi_k, theta_k, reward_k = _two_stage([good] + [0.2] * (K - 1))
            dk, yk = retrieval.sample(phi_k, theta_k, batches // 4, group, gen)
            exact_k, _ = retrieval.exact_gradients(phi_k, theta_k, reward_k)
            loo, _ = retrieval.estimates(phi_k, theta_k, reward_k, dk, yk, "leave-one-out")
            cross = retrieval.cross_document_retriever_estimate(phi_k, theta_k, reward_k, dk, yk)
            snr[f"K={K}, success {good} vs 0.2"] = dict(
                K=K, good=good, leave_one_out=retrieval.summarize(loo, exact_k)["snr"],
                cross_document=retrieval.summarize(cross, exact_k)["snr"])
    return dict(split_error=split_error, success=success, group=group, batches=batches,
                baselines=rows, snr=snr)


def retrieval_report(exact: dict) -> str:
    lines = ["| baseline | retriever: bias (± SE) | retriever: noise | generator: bias (± SE) | generator: noise |",
             "|---|---|---|---|---|"]
    for kind, row in exact["baselines"].items():
        r, g = row["retriever"], row.get("generator")
        gen_cells = f"{g['bias']:.3f} (± {g['bias_se']:.3f}) | {g['noise']:.2f}" if g else "n/a | n/a"
        lines.append(f"| {kind} | {r['bias']:.3f} (± {r['bias_se']:.3f}) | {r['noise']:.2f} | {gen_cells} |")
    snr = ["| documents K | generator: success with the helpful document vs the others | "
           "retriever SNR, leave-one-out | retriever SNR, cross-document |", "|---|---|---|---|"]
    for row in exact["snr"].values():
        snr.append(f"| {row['K']} | {row['good']} vs 0.2 | {row['leave_one_out']:.2f} | {row['cross_document']:.2f} |")
    success = ", ".join(f"{p}" for p in exact["success"])
    return (f"**The decomposition.** On 5 random two-stage problems, the retriever's and the generator's "
            f"parts of E[R grad log pi(d, y)] equal autograd's grad_phi J and grad_theta J to "
            f"{exact['split_error']:.1e} (float64).\n\n"
            f"**Baselines** ({exact['batches']:,} groups of {exact['group']} rollouts; a uniform retriever over "
            f"4 documents, with which the generator answers right with probability {success}). Bias and "
            f"noise are relative to the exact gradient's norm; the bias's standard error is the Monte "
            f"Carlo floor.\n\n" + "\n".join(lines) +
            f"\n\n**The retriever's signal** (one group of {exact['group']} rollouts, signal-to-noise ratio "
            f"= |exact| / spread of one estimate; one helpful document, the others 0.2):\n\n" + "\n".join(snr) + "\n")


# The documents of the real run, by kind. The retriever chooses a kind; the document itself is
# built for the prompt (its example reply meets that prompt's targets).
DOCUMENTS = ("an example reply that passes", "an example reply of the wrong length",
             "an unrelated sentence", "the rule restated")


def valid_reply(target_chars: int, target_digit_sum: int) -> str:
    """A reply the checker passes: the digits that make up the target sum, in a sentence cut to
    the target length (its last character is never a space, which would be stripped)."""
    digits = "9" * (target_digit_sum // 9) + (str(target_digit_sum % 9) if target_digit_sum % 9 else "")
    text = f"Only {digits} more stops along the harbor path before dusk"[:target_chars]
    return text[:-1] + "s" if text.endswith(" ") else text


def document(prompt: data.Prompt, kind: int) -> str:
    reply = valid_reply(prompt.target_chars, prompt.target_digit_sum)
    return [f"An example of a reply that follows the rule: {reply}",
            f"An example of a reply: {reply} and a few more words after it",
            "Tide tables for the harbor are printed every week in the local paper.",
            "Count every character of the reply, spaces included, and add up its digits."][kind]


def with_document(tokenizer, prompt: data.Prompt, kind: int) -> str:
    """The prompt's instruction with the retrieved document after it, in the chat template."""
    content = (data.instruction(prompt.snippet, prompt.target_chars, prompt.target_digit_sum) +
               f"\n\nA note that may help: {document(prompt, kind)}")
    return tokenizer.apply_chat_template([{"role": "user", "content": content}], tokenize=False,
                                         add_generation_prompt=True)


def retrieval_config(seed: int):
    """The cpu preset with 2 prompts per step and the main job's 24 new tokens (shrunk in smoke)."""
    return load_config("cpu", seed=seed, **{"prompts_per_step": 2, "max_new_tokens": 24,
                                           **(SMOKE if smoke_mode() else {})})


def retrieval_run(seed: int, learn_retriever: bool, steps: int) -> dict:
    """GRPO on SmolLM2 with a retriever over the document kinds, trained jointly (one advantage,
    each part its own score) or frozen at uniform. Returns the per-step curves."""
    from . import losses, rollout

    cfg = retrieval_config(seed)
    tokenizer = models.load_tokenizer(cfg.model)
    torch.manual_seed(seed)
    model = models.load_policy(cfg.model, seed=seed)
    eos = models.eos_token_ids(model, tokenizer)
    optimizer = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    phi = torch.zeros(len(DOCUMENTS), requires_grad=True)      # the retriever's logits
    phi_optimizer = torch.optim.Adam([phi], lr=0.2)
    prompts = data.make_prompts(cfg, tokenizer, held_out=False)
    gen = torch.Generator().manual_seed(seed)
    G = cfg.group_size
    curves = {"reward": [], "p_documents": [], "seconds": [], "retriever_seconds": []}
    reward_by_document = [[0.0, 0] for _ in DOCUMENTS]
    for step in range(steps):
        start = time.perf_counter()
        batch = train.batch_for_step(step, prompts, cfg)
        kinds = torch.multinomial(phi.detach().softmax(-1).expand(len(batch), -1), G,
                                  replacement=True, generator=gen)           # [B, G]
        texts = [with_document(tokenizer, p, int(k)) for p, row in zip(batch, kinds) for k in row]
        ro = rollout.rollout(model, tokenizer, texts, group_size=1, max_new_tokens=cfg.max_new_tokens,
                             eos_ids=eos, temperature=cfg.temperature, generator=gen)
        r = train.score([p for p in batch for _ in range(G)], ro.texts, cfg.reward)["rewards"]
        # one baseline per prompt, over its G rollouts whatever document each retrieved. The
        # group mean includes each rollout's own reward, so both parts shrink by (G-1)/G (the
        # exact table's "group mean" bias); it is not a per-document baseline, which would
        # remove most of the retriever's signal. Leave-one-out would be unbiased.
        advantages, _ = losses.group_advantages(r, G)
        optimizer.zero_grad(set_to_none=True)
        logprobs, _ = rollout.completion_logprobs(model, ro.prompt_ids, ro.prompt_mask, ro.completion_ids,
                                                  ro.completion_mask, temperature=cfg.temperature)
        loss, _ = losses.grpo_loss(logprobs, logprobs.detach(), advantages, ro.completion_mask)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.max_grad_norm)
        optimizer.step()
        retriever_start = time.perf_counter()
        if learn_retriever:   # the same advantages, the retriever's own score: grad log pi_phi(d)
            phi_optimizer.zero_grad()
            (-(advantages.view(kinds.shape) * phi.log_softmax(-1)[kinds]).mean()).backward()
            phi_optimizer.step()
        end = time.perf_counter()
        for k, value in zip(kinds.flatten().tolist(), r.tolist()):
            reward_by_document[k][0] += value
            reward_by_document[k][1] += 1
        curves["reward"].append(float(r.mean()))
        curves["p_documents"].append(phi.detach().softmax(-1).tolist())
        curves["seconds"].append(end - start)
        curves["retriever_seconds"].append(end - retriever_start)
    curves["reward_by_document"] = [total / n if n else None for total, n in reward_by_document]
    curves["cross_document_ess"] = _cross_document_ess(model, tokenizer, cfg, batch, ro, phi.detach())
    return curves


@torch.no_grad()
def _cross_document_ess(model, tokenizer, cfg, batch, ro, phi) -> list[float]:
    """Could the last batch's answers update the retriever for every document, without new
    generation? Score each answer under each document (one forward pass per document) and
    return, per document, the effective sample size of the weights pi(y | d') / m(y), m the
    mixture over documents the answers were drawn from, as a fraction of the batch."""
    from . import rollout

    G = cfg.group_size
    scores = []
    for kind in range(len(DOCUMENTS)):
        texts = [with_document(tokenizer, p, kind) for p in batch for _ in range(G)]
        prompt_ids, prompt_mask = rollout.tokenize_prompts(tokenizer, texts, ro.completion_ids.device)
        logprobs, _ = rollout.completion_logprobs(model, prompt_ids, prompt_mask, ro.completion_ids,
                                                  ro.completion_mask, temperature=cfg.temperature)
        scores.append((logprobs * ro.completion_mask).sum(-1))
    log_p = torch.stack(scores, -1)                                        # [N, K]
    log_mixture = torch.logsumexp(log_p + phi.log_softmax(-1), -1, keepdim=True)
    w = (log_p - log_mixture).exp()
    return (w.sum(0) ** 2 / (len(w) * (w ** 2).sum(0))).tolist()


def retrieval(seeds: list[int], out: Path) -> dict:
    """The exact analysis, then the real run: joint retriever + generator against the generator
    alone with a uniform retriever, over seeds."""
    exact = exact_retrieval(batches=2_000 if smoke_mode() else 20_000)
    steps = 2 if smoke_mode() else 8
    arms = {JOINT: True, ALONE: False}
    runs = {}
    for arm, learn in arms.items():
        runs[arm] = []
        for seed in seeds:
            cache = RUNS / ("smoke" if smoke_mode() else "full") / "retrieval" / ("joint" if learn else "generator") / f"seed{seed}.json"
            if not cache.exists():
                cache.parent.mkdir(parents=True, exist_ok=True)
                cache.write_text(json.dumps(retrieval_run(seed, learn, steps)))
            runs[arm].append(json.loads(cache.read_text()))
    cfg = retrieval_config(seeds[0])
    last = min(3, steps)
    final = {arm: [statistics.mean(r["reward"][-last:]) for r in rs] for arm, rs in runs.items()}
    helpful = {arm: [r["p_documents"][-1][0] for r in rs] for arm, rs in runs.items()}
    seconds = {arm: [statistics.mean(r["seconds"]) for r in rs] for arm, rs in runs.items()}
    joint, alone = arms
    ess = [statistics.mean(r["cross_document_ess"]) for rs in runs.values() for r in rs]
    retriever_ms = 1000 * statistics.mean(s for r in runs[joint] for s in r["retriever_seconds"])
    by_document = [statistics.mean(r["reward_by_document"][k] for rs in runs.values() for r in rs
                                   if r["reward_by_document"][k] is not None) for k in range(len(DOCUMENTS))]
    _plot_retrieval(runs, out / "curves.png")
    rows = "\n".join(f"| {arm} | {mean_std(final[arm])} | {mean_std(helpful[arm])} | {mean_std(seconds[arm])} |"
                      for arm in arms)
    docs = "\n".join(f"| {name} | {value:.3f} |" for name, value in zip(DOCUMENTS, by_document))
    report = (retrieval_report(exact) +
              f"\n**Real runs** ({cfg.model}, {steps} GRPO steps of {cfg.prompts_per_step} prompts x "
              f"{cfg.group_size} rollouts, each rollout "
              f"with the document its retriever drew; {len(seeds)} seeds):\n\n"
              f"| arm | training reward, last {last} steps | P(retriever picks the passing example) at the end | seconds per step |\n"
              f"|---|---|---|---|\n{rows}\n\n"
              + verdict_lines("retrieval", dict(final_reward=final, p_helpful=helpful)) +
              f"\n\n{RETRIEVER_COST} {retriever_ms:.1f} ms a step\n\n"
              f"Reusing answers across documents on the real model: scored under every document, the "
              f"last batch's answers give cross-document weights whose effective sample size is "
              f"{mean_std(ess)} of the batch (mean over documents, per run)\n\n"
              f"Mean reward of the rollouts by the document they retrieved (all runs pooled):\n\n"
              f"| document | mean reward |\n|---|---|\n{docs}\n")
    result = dict(exact=exact, steps=steps, final_reward=final, p_helpful=helpful,
                  seconds_per_step=seconds, reward_by_document=dict(zip(DOCUMENTS, by_document)),
                  cross_document_ess=ess,
                  retriever_ms=retriever_ms,
                  documents=list(DOCUMENTS))
    write(out, report, result)
    return result


def _plot_retrieval(runs: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path.parent.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.0))
    for arm, rs in runs.items():
        steps = range(1, len(rs[0]["reward"]) + 1)
        reward = torch.tensor([r["reward"] for r in rs])
        helpful = torch.tensor([[p[0] for p in r["p_documents"]] for r in rs])
        for ax, values in zip(axes, (reward, helpful)):
            ax.plot(steps, values.mean(0), label=arm)
            ax.fill_between(steps, values.min(0).values, values.max(0).values, alpha=0.15)
    axes[0].set_title("training reward"); axes[1].set_title("P(passing example)")
    for ax in axes:
        ax.set_xlabel("step")
    axes[0].legend(fontsize=7); plt.tight_layout(); fig.savefig(path, dpi=110); plt.close(fig)


TRACKS = {"base_model": base_model, "serving": serving, "entropy": entropy, "kl": kl_schedule,
          "grouping": grouping, "retrieval": retrieval}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Run the learner tracks' experiments.")
    parser.add_argument("track", choices=[*TRACKS, "all"])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--out", default="notebooks/results/tracks")
    parser.add_argument("--rerender", action="store_true",
                        help="train nothing: rewrite the comparison lines of the stored reports "
                             "from their result.json (the tracks that compare arms)")
    args = parser.parse_args(argv)
    for name in (TRACKS if args.track == "all" else [args.track]):
        out = Path(args.out) / name
        if args.rerender:
            if name in VERDICTS:
                rerender_verdicts(name, out)
            continue
        out.mkdir(parents=True, exist_ok=True)
        TRACKS[name](args.seeds, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
