"""Every figure in a lesson's prose comes from somewhere: a stored result file or the library's
arithmetic, filled in by ``notebooks/build.py`` from ``{{fig:NAME}}`` (``notebooks/figures.py``),
or a cell's printed output. A number typed into the prose, in digits or as a count spelled out
("three seeds"), is a figure that can go stale, so this test fails on one, unless it is a constant
of the setup listed below with its reason; a wall time typed into a lesson or the README too."""
import json
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "notebooks"))
import figures  # noqa: E402

LESSONS = sorted((ROOT / "notebooks" / "src").glob("[0-9][0-9]_*.py"))

# A figure: a number, with its unit if it has one. Lone digits 0-9 are counts of things ("3
# seeds", "2 prompts") and are not figures.
FIGURE = re.compile(r"(?<![\w.\-/])(\d{1,3}(?:,\d{3})+|\d+(?:\.\d+)?)(%| ?x\b| GiB| MiB| MB| ms)?(?![\w/])")
NOT_PROSE = [
    r"\$\$.*?\$\$|\$[^$]*\$",                       # math
    r"`[^`]*`",                                      # code
    r"\{\{[^}]*\}\}",                                # placeholders, filled by build.py
    r"https?://\S+|arXiv \d{4}\.\d{5}",              # links and paper ids
    r"\b(?:[Ss]ections?|[Ee]xercises?|[Ll]essons?|[Tt]racks?|[Qq]uestions?) \d+(?:\.\d+)?"
    r"(?:(?:, | and | or |-)\d+(?:\.\d+)?)*",        # cross-references
    r"^\s*#+\s*\d+(?:\.\d+)*",                       # numbered headings
    r"\b(?:19|20)\d\d\b",                            # years
]

# Constants of the setup, by lesson: what the lesson *chose*, not what a run measured.
SETUP = {
    "01_policy_gradient_theorem": {"1.1", "1.2", "1.3"},                 # exercise numbers
    "02_reinforce": {"2.1", "2.2", "2.3",                                 # exercise numbers
                     "0.6"},                                              # an illustrative reward level
    "03_baselines": {"3.1", "3.2", "3.3", "16", "128"},                  # exercises; 16 prompts x 8 = 128
    "04_trust_regions": {"4.1", "4.2", "4.3", "4.4", "4.5",              # exercise numbers
                         "0.1",                                           # "a step of 0.1" (illustrative)
                         "1.16"},                                         # the TRL version described
    "05_grpo": {"5.1", "5.2", "5.3", "5.4",                               # exercise numbers
                "0.01",                                                   # "rewards differ by 0.01 or by 1"
                "16", "128"},                                             # 16 prompts x 8; 128-token prompts
    "06_grpo_by_hand": {"6.1", "6.2", "6.3", "6.4", "6.5",               # exercise numbers
                        "0.7", "1.0", "32"},                              # a question's premise
    "07_t4_recipe": {"64", "16", "128", "0.01", "1.0", "15%", "25%",      # t4 preset; plan test tolerances
                     "32", "12", "24", "15", "0.2", "0.7", "0.95", "0%", "50", "6.3",
                     "6.1", "6.2", "6.4"},
    "08_learner_tracks": {"32", "10", "4x", "256", "0.05", "0.2", "0.02", "0.04", "40",
                          "16", "0.8", "24"},   # the retrieval track's 16 documents, 0.8 vs 0.2 success, 24 new tokens
}
# Why the 07_t4_recipe and 08_learner_tracks entries are constants: 32 characters / 32-token snippets, digit sums up
# to 12, a 24-token cap, a 15-minute budget, the clip 0.2, temperature 0.7, "mean reward 0.95
# and pass rate 0%" (a question's premise), the first 50 steps (a T4 checklist item), section
# numbers; 10 (the fixed digit sum of the base-model track), 4x and 256 levels (8 bits), the entropy
# arms' 0.05 and cap 0.2 and the 0.02 they were sized for, the KL base 0.04, 40 facts sentences.


def prose_lines(path: Path):
    """(line number, text) of every markdown line of a jupytext source, fenced code excepted."""
    in_markdown = in_fence = False
    for number, line in enumerate(path.read_text().splitlines(), 1):
        if line.startswith("# %%"):
            in_markdown, in_fence = line.startswith("# %% [markdown]"), False
            continue
        if in_markdown and line.startswith("# ```"):
            in_fence = not in_fence
            continue
        if in_markdown and not in_fence and line.startswith("#"):
            yield number, line[1:]


def typed_figures(path: Path) -> list[tuple[int, str]]:
    found = []
    for number, line in prose_lines(path):
        for pattern in NOT_PROSE:
            line = re.sub(pattern, " ", line)
        for match in FIGURE.finditer(line):
            if re.fullmatch(r"\d", match.group(1)) and not match.group(2):
                continue
            found.append((number, match.group(0).strip()))
    return found


# A count spelled as a word is a figure too: "the third seed", "first ten steps", "two runs". A
# number word counts only when one of the course's countable nouns follows it, directly or
# after at most two words ("two held-out prompts"); a hyphenated compound ("two-digit target")
# is an adjective, not a count. A phrase may run on to the next line of the source.
CARDINALS = ("two|three|four|five|six|seven|eight|nine|ten|eleven|twelve|thirteen|fourteen|fifteen|"
             "sixteen|seventeen|eighteen|nineteen|twenty|thirty|forty|fifty|sixty|seventy|eighty|"
             "ninety|hundred")
ORDINALS = "second|third|fourth|fifth|sixth|seventh|eighth|ninth|tenth"
NOUNS = ("steps?|seeds?|runs?|prompts?|completions?|groups?|tokens?|characters?|digits?|targets?|"
         "epochs?|updates?|samples?|rounds?|arms?|snippets?|minutes?|hours?|seconds?|times?|"
         "pass(?:es)?|documents?|sentences?|batch(?:es)?|probes?|results?")
NUMBER_WORD = re.compile(
    rf"\b(?:(?:first|last)\s+(?:{CARDINALS}|\d+)"     # "first ten", "last 5"
    rf"|(?:{CARDINALS})(?:[- ](?:{CARDINALS}))?"        # "two", "twenty-four"
    rf"|{ORDINALS})"                                    # "third"
    rf"(?:\s+[\w'-]+){{0,2}}?\s+(?:{NOUNS})\b",          # ... then the counted noun
    re.I)

# Counts spelled out that are constants of the exposition, by lesson (the phrase as the scanner
# reports it, in lower case): a worked example's size, a position, a fact of a tokenizer.
WORDS_SETUP = {
    "02_reinforce": {"hundred tokens"},                     # "a few hundred tokens": a scale
    "04_trust_regions": {"three tokens",                    # the enumerable sequence policy's length
                         "two worst arms",                  # the bandit's reward vector, arms 3 and 4
                         "two natural steps",               # the steps in theta and in phi
                         "two step"},                       # "two step sizes": the cell's linear/cubic demo
    "05_grpo": {"four tokens",                              # the worked KL example's p and q
                "two completions"},                         # the length-bias example's short and long one
    "06_grpo_by_hand": {"two end tokens",                   # Qwen2.5-Instruct's tokenizer
                        "two runs"},                        # your step's run and the library's
    "07_t4_recipe": {"second digit",                        # a digit position
                     "two digits"},                         # "the number has two digits": a two-digit number
    "08_learner_tracks": {"four prompts"},                  # the exact grouping problem's 4 prompts
}


def typed_number_words(path: Path) -> list[tuple[int, str]]:
    """(line, phrase) of every count spelled as a word in a lesson's prose."""
    lines = {}
    for number, line in prose_lines(path):
        for pattern in NOT_PROSE:
            line = re.sub(pattern, " ", line)
        lines[number] = line
    found = []
    for number, line in lines.items():
        joined = line + " " + lines.get(number + 1, "")      # a phrase may cross a line break
        found += [(number, " ".join(m.group(0).split())) for m in NUMBER_WORD.finditer(joined)
                  if m.start() < len(line)]
    return found


@pytest.mark.parametrize("lesson", LESSONS, ids=lambda p: p.stem)
def test_no_figure_is_typed_into_a_lessons_prose(lesson):
    allowed = SETUP.get(lesson.stem, set())
    typed = [(n, f) for n, f in typed_figures(lesson) if f not in allowed]
    assert not typed, (f"{lesson.name}: figures typed into prose (line, figure): {typed}. Render "
                       f"each from a stored result with {{{{fig:NAME}}}} (notebooks/figures.py), "
                       f"let a cell print it, or, for a constant of the setup, list it in SETUP")


@pytest.mark.parametrize("lesson", LESSONS, ids=lambda p: p.stem)
def test_no_count_is_spelled_into_a_lessons_prose(lesson):
    allowed = WORDS_SETUP.get(lesson.stem, set())
    typed = [(n, w) for n, w in typed_number_words(lesson) if w.lower() not in allowed]
    assert not typed, (f"{lesson.name}: counts spelled into prose (line, phrase): {typed}. Render "
                       f"each from a stored result or the config with {{{{fig:NAME}}}}, say it "
                       f"without the count, or, for a constant of the exposition, list it in WORDS_SETUP")


def test_every_allowed_count_still_appears():
    """An allowlist entry whose phrase has left the lesson would let a later one through unread."""
    stale = {stem: phrases - {w.lower() for _, w in typed_number_words(ROOT / "notebooks" / "src" / f"{stem}.py")}
             for stem, phrases in WORDS_SETUP.items()}
    assert not any(stale.values()), f"WORDS_SETUP phrases no longer in their lesson: {stale}"


def test_the_scanner_finds_typed_figures_and_skips_code_math_and_placeholders(tmp_path):
    lesson = tmp_path / "99_x.py"
    lesson.write_text("# %% [markdown]\n# It fell to 0.64 by step 30, 59 higher and 14.7%; "
                      "`lr=3e-5`, $p=0.5$, {{fig:a.b}}, section 6.1, arXiv 2503.14476 in 2025.\n"
                      "# %%\nx = 0.123\n")
    assert [f for _, f in typed_figures(lesson)] == ["0.64", "30", "59", "14.7%"]


def test_the_scanner_finds_counts_spelled_as_words_and_skips_adjectives_and_code(tmp_path):
    lesson = tmp_path / "99_x.py"
    lesson.write_text("# %% [markdown]\n# Over the first ten steps two held-out prompts and the third\n"
                      "# seed passed; ninety-nine times, the last 5 steps. A two-digit target, "
                      "`three seeds`, {{fig:a.b}} seeds, two of them.\n"
                      "# %%\nx = 'three seeds'\n")
    assert typed_number_words(lesson) == [(2, "first ten steps"), (2, "two held-out prompts"),
                                          (2, "third seed"), (3, "ninety-nine times"),
                                          (3, "last 5 steps")]


def test_every_figure_renders_and_every_placeholder_names_one():
    known = figures.figures()
    assert all(isinstance(v, str) and v for v in known.values())
    for lesson in LESSONS:
        figures.fill(lesson.read_text(), lesson.name)       # raises on an unknown name


def test_the_t4_plan_figures_match_a_hand_computation():
    known = figures.figures()
    # 494,032,768 parameters x (4 + 4 + 8 + 2) bytes = 8.28 GiB, the corrected figure
    assert known["plan.persistent_gib"] == f"{494_032_768 * 18 / 2 ** 30:.1f}" == "8.3"
    assert known["plan.logits_mb_per_token"] == f"{151_936 * 4 / 1e6:.1f}"


def test_no_control_character_hides_in_a_lesson_or_the_readme():
    """A backslash lost in an edit turns LaTeX's \\tfrac or \\top into a TAB and 'frac'/'op'; the
    rendered math breaks silently. Only newlines may appear among the control characters."""
    paths = LESSONS + [ROOT / "README.md"]
    bad = [(p.name, n) for p in paths for n, line in enumerate(p.read_text().splitlines(), 1)
           if re.search(r"[\x00-\x08\x0b-\x1f\x7f]", line)]
    assert not bad, f"control characters at (file, line): {bad}"


# A wall time: a number and a unit of time, "62 s", "3 min", "about 75 minutes", "1.3 h", a
# range ("2 to 4 minutes") or a compound ("13 min 8 s"). "s" alone needs its space ("62 s").
_NUMBER = r"\d+(?:\.\d+)?"
_UNIT = r"(?: ?(?:h|hours?|min|minutes?)| (?:s|seconds?))\b"
_TIME = rf"(?<![\w.]){_NUMBER}(?: ?(?:to|-|–) ?{_NUMBER})?{_UNIT}(?: {_NUMBER}{_UNIT})?"
WALL_TIME = re.compile(_TIME)
NOT_A_WALL_TIME = [
    r"<!-- results: [\w-]+ -->.*?<!-- end results -->",     # rendered from stored results
    r"<!-- run time: \d+ -->.*?<!-- end run time -->",      # the lessons table, rendered
    r"```.*?```", r"`[^`]*`",                                # code
    rf"(?:\b(?:under|within|at most)|≤|<=) (?:about )?{_TIME}",   # a budget or a limit
    rf"\bwhat {_TIME}\b[^.]{{0,40}}?\bbuys?\b",              # "what 15 minutes on a CPU buy"
]


def untyped_wall_times(text: str) -> list[str]:
    """Wall times such as '13 min 8 s' or '3 min' typed into prose: outside rendered results
    sections (``<!-- results: NAME -->`` ... ``<!-- end results -->``) and run-time cells
    (``<!-- run time: N -->`` ... ``<!-- end run time -->``), code, and budgets or limits
    ("under 15 minutes", "at most 2 h", "what 15 minutes buy")."""
    for pattern in NOT_A_WALL_TIME:
        text = re.sub(pattern, " ", text, flags=re.S)
    return WALL_TIME.findall(text)


def test_no_wall_time_is_typed_into_the_readme():
    """A measured time in the README comes from notebooks/results/readme-timings.jsonl (written
    by benchmarks/readme_timings.py) or, for the lessons table, lesson-timings.json (written by
    benchmarks/lesson_timings.py), rendered by notebooks/build.py, never typed."""
    typed = untyped_wall_times((ROOT / "README.md").read_text())
    assert not typed, (f"README.md: wall times typed into prose: {typed}; measure them with "
                       f"benchmarks/readme_timings.py and let notebooks/build.py render them")


@pytest.mark.parametrize("lesson", LESSONS, ids=lambda p: p.stem)
def test_no_wall_time_is_typed_into_a_lessons_prose(lesson):
    typed = [(n, t) for n, line in prose_lines(lesson)
             for t in untyped_wall_times(re.sub(r"\{\{[^}]*\}\}", " ", line))]
    assert not typed, (f"{lesson.name}: wall times typed into prose (line, time): {typed}; render a "
                       f"stored time with {{{{fig:NAME}}}} (notebooks/figures.py) or let a cell print it")


def test_the_wall_time_scanner_finds_typed_times_and_skips_rendered_ones():
    text = ("took 13 min 8 s and 1 h 15 min, `2 min 3 s` in code\n<!-- results: timings -->\n"
            "| main | 12 min 40 s |\n<!-- end results -->\nunder 15 minutes")
    assert untyped_wall_times(text) == ["13 min 8 s", "1 h 15 min"]


def test_the_wall_time_scanner_finds_single_units_and_skips_budgets_and_rendered_cells():
    text = ("took 3 min, then 62 s, about 75 minutes, 2 to 4 minutes and 1.3 h; 5 seeds, 35 ms, "
            "lesson 5's run\n| 4 | <!-- run time: 4 -->3 min 5 s<!-- end run time --> |\n"
            "under 15 minutes, within 2 hours, at most 10 min, ≤ 30 s, what 15 minutes on a CPU "
            "buy, `python x.py  # 20 minutes`\n```bash\nsleep 60  # 1 min\n```")
    assert untyped_wall_times(text) == ["3 min", "62 s", "75 minutes", "2 to 4 minutes", "1.3 h"]


# --- the README's prose ------------------------------------------------------------------------
# Rendered parts (stored results, measured run times, <!-- fig: NAME --> figures), code and link
# targets are not prose; what is left is scanned like a lesson's markdown.
README_NOT_PROSE = [
    r"<!-- results: [\w-]+ -->.*?<!-- end results -->",
    r"<!-- run time: \d+ -->.*?<!-- end run time -->",
    r"<!-- fig: [\w.]+ -->.*?<!-- end fig -->",
    r"```.*?```",
    r"\]\([^)]*\)",                                   # a link's target
]
# Constants of the README: versions and platforms, budgets, the presets table's settings (checked
# against config.py by test_the_readmes_presets_table_matches_the_config), and what a test or a
# tool is set to.
README_SETUP = {
    "3.11", "3.13", "3.14", "5.23", "7.4", "2.13", "2.11", "1.16",   # Python and package versions
    "14",                                                            # macOS 14, torch's oldest wheel
    "15", "25",                                                      # the budgets "under 15/25 minutes"
    "32", "128", "10,240",                                           # the presets table's settings
    "15%",                                                           # plan.py's memory check tolerance
}
README_WORDS_SETUP = {
    "second run",           # "a second run in the same out_dir is refused": not a count
    "two steps",            # the CI test of the TRL rewards trains two steps: a test's setting
}


def readme_prose() -> list[tuple[int, str]]:
    """(line number, text) of the README's prose, rendered parts, code and link targets blanked
    (newlines kept, so line numbers stay true)."""
    text = (ROOT / "README.md").read_text()
    for pattern in README_NOT_PROSE:
        text = re.sub(pattern, lambda m: re.sub(r"[^\n]", " ", m.group(0)), text, flags=re.S)
    lines = []
    for number, line in enumerate(text.splitlines(), 1):
        for pattern in NOT_PROSE:
            line = re.sub(pattern, " ", line)
        lines.append((number, line))
    return lines


def test_no_figure_or_count_is_typed_into_the_readmes_prose():
    lines = readme_prose()
    digits = [(n, m.group(0).strip()) for n, line in lines for m in FIGURE.finditer(line)
              if not (re.fullmatch(r"\d", m.group(1)) and not m.group(2))]
    words = []
    for i, (n, line) in enumerate(lines):
        joined = line + " " + (lines[i + 1][1] if i + 1 < len(lines) else "")
        words += [(n, " ".join(m.group(0).split())) for m in NUMBER_WORD.finditer(joined) if m.start() < len(line)]
    typed = ([(n, f) for n, f in digits if f not in README_SETUP]
             + [(n, w) for n, w in words if w.lower() not in README_WORDS_SETUP])
    assert not typed, (f"README.md: figures or counts typed into prose (line, figure): {typed}. Write "
                       f"<!-- fig: NAME --><!-- end fig --> (a figure of notebooks/figures.py) and run "
                       f"`python notebooks/build.py`, or, for a constant, list it in README_SETUP")


def test_every_readme_constant_still_appears():
    lines = readme_prose()
    text = " ".join(line for _, line in lines)
    found = {m.group(0).strip() for m in FIGURE.finditer(text)}
    words = {" ".join(m.group(0).split()).lower() for m in NUMBER_WORD.finditer(text)}
    assert not README_SETUP - found and not README_WORDS_SETUP - words, (
        f"README_SETUP entries no longer in the README: {(README_SETUP - found) | (README_WORDS_SETUP - words)}")


def test_the_readme_scanner_skips_rendered_figures():
    assert re.sub(README_NOT_PROSE[2], " ", "over <!-- fig: ablation.seeds -->three<!-- end fig --> seeds") \
        == "over   seeds"


def test_the_readmes_presets_table_matches_the_config():
    """The presets table's settings are typed (README_SETUP); this is their source check."""
    from course_utils.config import PRESETS, Config

    rows = {m.group(1): m.group(0) for m in re.finditer(r"^\| `([\w-]+)` \|.*$", (ROOT / "README.md").read_text(), re.M)}
    for name in ("cpu", "t4", "gpt2-rtx4070"):
        cfg = Config.from_dict(PRESETS[name])
        assert f"{cfg.prompt_tokens} tokens" in rows[name], (name, cfg.prompt_tokens)
    t4, gpt2 = Config.from_dict(PRESETS["t4"]), Config.from_dict(PRESETS["gpt2-rtx4070"])
    per_micro = t4.prompts_per_step // t4.grad_accum
    assert f"micro-batches of {per_micro} prompt{'s' * (per_micro > 1)} x {t4.group_size}" in rows["t4"]
    assert f"{t4.total_steps * t4.prompts_per_step:,} prompts" in rows["t4"]
    assert f"{gpt2.target_chars}-character target, batch {gpt2.prompts_per_step}" in rows["gpt2-rtx4070"]


def test_the_order_chance_is_the_exact_permutation_p_and_refuses_an_ordering_that_does_not_hold():
    # 3 tuning seeds all above 5 fresh ones: 1 of the C(8, 3) = 56 labellings puts them on top
    assert figures._order_chance([0.9, 0.7, 0.8], [0.0, 0.1, 0.2, 0.3, 0.6]) == "1 in 56"
    assert figures._order_chance([0.5, 0.6], [0.1, 0.2]) == "1 in 6"
    with pytest.raises(ValueError, match="every tuning seed passes more"):
        figures._order_chance([0.9, 0.2], [0.3, 0.1])
    with pytest.raises(ValueError, match="every tuning seed passes more"):  # a tie is not "more"
        figures._order_chance([0.5, 0.9], [0.5, 0.1])


def test_the_order_chance_matches_a_brute_force_permutation_test():
    # a second implementation: enumerate every way to label k of the n values "tuning" and count
    # the labellings whose tuning values are all above all the others
    import itertools
    import math
    tuning, fresh = [0.891, 0.719, 0.734], [0.0, 0.062, 0.031, 0.047, 0.625]
    values = tuning + fresh
    splits = list(itertools.combinations(range(len(values)), len(tuning)))
    on_top = sum(min(values[i] for i in s) > max(values[j] for j in range(len(values)) if j not in s)
                 for s in splits)
    assert on_top == 1 and figures._order_chance(tuning, fresh) == f"1 in {len(splits)}"
    assert len(splits) == math.comb(8, 3)


def test_the_fresh_seed_runs_share_one_config_but_their_seed_and_out_dir():
    """figures.frozen_recipe reads one fresh-seed run's config as the recipe's: that is only the
    recipe if every fresh-seed run has the same settings but its seed and out_dir."""
    configs = [figures._json(f"fresh-seeds/{run.name}/config.json") for run in figures.fresh_runs()]
    settings = [{k: v for k, v in c.items() if k not in ("seed", "out_dir")} for c in configs]
    assert len(configs) >= 2 and all(s == settings[0] for s in settings)
    assert len({c["seed"] for c in configs}) == len(configs)


def _cap_json_with(monkeypatch, run: str, **changes):
    real = figures._json
    monkeypatch.setattr(figures, "_json", lambda rel: {**real(rel), **changes}
                        if rel == f"cap-probes/{run}/config.json" else real(rel))


@pytest.mark.parametrize("run, changes, mistake", [
    (figures.CAP_PUNISHED, {"lr": 1.0}, "changes only the overlong punishment"),
    (figures.CAP_PUNISHED, {"overlong_buffer": 0, "overlong_penalty": 0.0}, "changes only the overlong"),
    (figures.CAP_CONTROL, {"seed": 14}, "control must be the frozen recipe on the probe's seed"),
    (figures.CAP_CONTROL, {"overlong_penalty": 1.0}, "control must be the frozen recipe"),
    (figures.CAP_CONTROL, {"kl_coef": 0.0}, "control must be the frozen recipe"),
])
def test_the_cap_probe_figures_refuse_a_probe_or_control_that_is_not_what_6_6_says(monkeypatch, run,
                                                                                   changes, mistake):
    figures.cap_figures()  # the stored files pass
    _cap_json_with(monkeypatch, run, **changes)
    with pytest.raises(ValueError, match=mistake):
        figures.cap_figures()


@pytest.mark.parametrize("changes", [{"precision": "bf16"}, {"cpu_capability": "AVX512"}])
def test_the_cap_probe_figures_refuse_a_control_in_another_precision_or_cpu(monkeypatch, changes):
    real = figures._json
    monkeypatch.setattr(figures, "_json", lambda rel: {**real(rel), **changes}
                        if rel == f"cap-probes/{figures.CAP_CONTROL}/summary.json" else real(rel))
    with pytest.raises(ValueError, match="different precisions or CPUs"):
        figures.cap_figures()


def test_every_cap_probe_pair_is_checked(monkeypatch):
    """The fresh seed's pair too, not only the probe's."""
    control, punished = figures.CAP_PAIRS[figures.CAP_FRESH_SEED]
    _cap_json_with(monkeypatch, punished, lr=1.0)
    with pytest.raises(ValueError, match=f"{punished} changes"):
        figures.cap_figures()


def _precision_json_with(monkeypatch, rel_path: str, **changes):
    real = figures._json
    monkeypatch.setattr(figures, "_json", lambda rel: {**real(rel), **changes}
                        if rel == rel_path else real(rel))


@pytest.mark.parametrize("file, changes, mistake", [
    ("punished-fp32-seed16/config.json", {"lr": 1e-4}, "6.6's punished recipe"),
    ("punished-bf16-seed16/config.json", {"overlong_penalty": 0.0}, "6.6's punished recipe"),
    ("punished-bf16-seed16/config.json", {"seed": 99}, "6.6's punished recipe"),
    ("punished-bf16-seed16/summary.json", {"precision": "fp32"}, "fp32 and bf16 on one CPU"),
    ("punished-bf16-seed16/summary.json", {"cpu_capability": "AVX2"}, "fp32 and bf16 on one CPU"),
])
def test_the_precision_figures_refuse_a_pair_that_is_not_what_6_7_says(monkeypatch, file, changes, mistake):
    figures.precision_figures()  # the stored files pass
    _precision_json_with(monkeypatch, f"precision-pairs/{file}", **changes)
    with pytest.raises(ValueError, match=mistake):
        figures.precision_figures()


def test_the_precision_figures_refuse_prose_the_stored_runs_stop_supporting(monkeypatch):
    fp32, bf16 = figures.precision_pair_runs()
    real = figures._json
    # every fp32 run ahead of its bf16 twin: the difference no longer changes sign
    ahead = {f"precision-pairs/{run.name}/summary.json" for run in fp32}

    def lifted(rel):
        value = real(rel)
        if rel in ahead:
            value["after"]["greedy"]["pass_both"] = 1.0
        return value
    monkeypatch.setattr(figures, "_json", lifted)
    with pytest.raises(ValueError, match="changes from seed to seed"):
        figures.precision_figures()


@pytest.mark.parametrize("files, changes, mistake", [
    (["gated/tuning/gated-seed16/config.json"], {"lr": 1e-4}, "reward='gated' and nothing else"),
    (["gated/tuning/gated-seed16/config.json"], {"reward": "counted"}, "reward='gated' and nothing else"),
    (["gated/tuning/gated-seed16/config.json"], {"seed": 17}, "reward='gated' and nothing else"),
    (["precision-pairs/punished-bf16-seed16/config.json"], {"kl_coef": 0.0}, "6.6's punished recipe on seed 16"),
    # both runs of a pair on another seed than their folders say
    (["gated/fresh/gated-seed21/config.json", "gated/fresh/punished-seed21/config.json"], {"seed": 22},
     "6.6's punished recipe on seed 21"),
    # the control and its gated twin off the recipe the same way
    (["gated/fresh/gated-seed21/config.json", "gated/fresh/punished-seed21/config.json"],
     {"overlong_penalty": 0.0}, "6.6's punished recipe on seed 21"),
    (["gated/fresh/gated-seed21/config.json"], {"is_correction": "token_mask"}, "reward='gated' and nothing"),
    (["gated/fresh/gated-seed21/summary.json"], {"precision": "fp32"}, "both ran in bf16 on one CPU"),
    (["gated/fresh/punished-seed21/summary.json"], {"cpu_capability": "AVX2"}, "both ran in bf16 on one CPU"),
])
def test_the_gated_figures_refuse_a_pair_that_is_not_what_6_8_says(monkeypatch, files, changes, mistake):
    _refused_after_changes(monkeypatch, figures.gated_figures, files, changes, mistake)


def _refused_after_changes(monkeypatch, build, files, changes, mistake):
    """``build`` passes on the stored files, and refuses them with ``mistake`` once each of
    ``files`` (JSON, relative to results/) has ``changes`` merged into it."""
    build()
    real = figures._json
    monkeypatch.setattr(figures, "_json", lambda rel: {**real(rel), **changes} if rel in files else real(rel))
    with pytest.raises(ValueError, match=mistake):
        build()


def test_dead_end_names_how_a_run_without_a_template_ended():
    def after(one, length, digits):
        return dict(pass_both_one_digit=one, pass_length=length, pass_digits=digits)
    assert figures.dead_end(after(1.0, 0.7, 0.7)) is None
    assert figures.dead_end(after(0.98, 0.8, 0.8)) is None
    assert figures.dead_end(after(0.85, 0.9, 0.8)) == "length"
    assert figures.dead_end(after(0.0, 1.0, 0.0)) == "length"
    assert figures.dead_end(after(0.15, 0.92, 0.17)) == "length"
    assert figures.dead_end(after(0.1, 0.08, 0.75)) == "digits"
    assert figures.dead_end(after(0.1, 0.5, 0.5)) == "tie"


def test_the_gated_figures_refuse_a_seed_with_a_run_missing(monkeypatch):
    for stage, seeds in (("tuning", figures.GATED_TUNING_SEEDS), ("fresh", figures.GATED_FRESH_SEEDS)):
        gated, counted = figures.gated_pair_runs(stage)
        assert [json.loads((r / "config.json").read_text())["seed"] for r in gated] == list(seeds)
    monkeypatch.setattr(figures, "GATED_FRESH_SEEDS", (*figures.GATED_FRESH_SEEDS, 99))
    with pytest.raises(ValueError, match="missing .*gated-seed99"):
        figures.gated_figures()
    with pytest.raises(ValueError, match="'tuning' or 'fresh'"):
        figures.gated_pair_runs("probe")


def test_the_gated_figures_refuse_prose_the_dead_end_stops_supporting(monkeypatch):
    """6.8 says the length-first run almost never sampled the right digit sum once it had learned
    the length (at most 1% of its sampled replies)."""
    rel = "precision-pairs/punished-bf16-seed18"
    steps = [json.loads(line) for line in (figures.RESULTS / rel / "metrics.jsonl").read_text().splitlines()]
    from course_utils import ablation
    real = ablation.records
    monkeypatch.setattr(ablation, "records", lambda run: [{**x, "pass_digits": 0.03125} for x in steps]
                        if str(run).endswith(rel) else real(run))
    with pytest.raises(ValueError, match="almost never sampled the right digit sum"):
        figures.gated_figures()


def test_no_stored_run_falls_near_the_template_line():
    """6.8's template runs are those at or above figures.TEMPLATE_ONE_DIGIT of one-digit passes;
    a run near the line would make the count depend on the threshold chosen."""
    runs = sum(figures.precision_pair_runs(), []) + [r for stage in ("tuning", "fresh")
                                                     for arm in figures.gated_pair_runs(stage) for r in arm]
    for run in runs:
        one = json.loads((run / "summary.json").read_text())["after"]["greedy"]["pass_both_one_digit"]
        assert not 0.5 <= one < figures.TEMPLATE_ONE_DIGIT, (run.name, one)


def _lifted_after(real, runs, **after):
    """figures._json with the held-out greedy results of ``runs`` (folder names) overwritten."""
    def lifted(rel):
        data = real(rel)
        if rel.endswith("summary.json") and rel.split("/")[-2] in runs:
            data = {**data, "after": {**data["after"], "greedy": {**data["after"]["greedy"], **after}}}
        return data
    return lifted


def test_the_gated_figures_refuse_a_verdict_the_fresh_seeds_stop_supporting(monkeypatch):
    """6.8's verdict: no difference detected on fresh seeds, no recipe met the bar, the template
    did not become likely with the gate, no gated run ended on replies without a digit, and the
    gated runs that ended length first wrote one sentence with a fixed number."""
    real = figures._json
    gated_fresh = {r.name for r in figures.gated_pair_runs("fresh")[0]}
    # every fresh gated run a template run that passes 90%: a difference, and the template likely
    monkeypatch.setattr(figures, "_json", _lifted_after(real, gated_fresh, pass_both=0.9, pass_both_one_digit=1.0))
    with pytest.raises(ValueError, match="detect no difference"):
        figures.gated_figures()
    # four of five template runs (seed 24's stays the run that ended on a fixed number)
    monkeypatch.setattr(figures, "_json", _lifted_after(real, gated_fresh - {"gated-seed24"}, pass_both_one_digit=1.0))
    with pytest.raises(ValueError, match="template did not become the likely path"):
        figures.gated_figures()
    # both arms at 90% on every fresh seed: no difference, and the bar met
    everyone = gated_fresh | {r.name for r in figures.gated_pair_runs("fresh")[1]}
    monkeypatch.setattr(figures, "_json", _lifted_after(real, everyone, pass_both=0.9))
    with pytest.raises(ValueError, match="neither recipe met the bar"):
        figures.gated_figures()
    # each gated run 1 point above its control: a difference the fresh seeds detect
    counted = {r.name: real(f"gated/fresh/{r.name}/summary.json")["after"]["greedy"]["pass_both"]
               for r in figures.gated_pair_runs("fresh")[1]}
    def above(rel):
        data = real(rel)
        if rel.endswith("summary.json") and rel.split("/")[-2] in gated_fresh:
            control = counted[rel.split("/")[-2].replace("gated-", "punished-")]
            seed = int(rel.split("/")[-2].removeprefix("gated-seed"))
            data = {**data, "after": {**data["after"], "greedy": {**data["after"]["greedy"],
                                                                  "pass_both": control + 0.01 * seed / 21}}}
        return data
    monkeypatch.setattr(figures, "_json", above)
    with pytest.raises(ValueError, match="detect no difference"):
        figures.gated_figures()
    # a gated run whose replies hold no digit
    first = sorted(gated_fresh)[0]
    monkeypatch.setattr(figures, "_json", _with_samples(
        real, f"gated/fresh/{first}/summary.json",
        lambda samples: [{**x, "completion": "No digits in this reply at all!!"} for x in samples]))
    with pytest.raises(ValueError, match="no gated run and no fresh run ended on replies without a digit"):
        figures.gated_figures()
    # the gated run that ended length first, with its replies all different: no fixed sentence
    monkeypatch.setattr(figures, "_json", _with_samples(
        real, "gated/fresh/gated-seed24/summary.json",
        lambda samples: [{**x, "completion": f"{x['completion']}{i}"} for i, x in enumerate(samples)]))
    with pytest.raises(ValueError, match="a fixed number for most prompts"):
        figures.gated_figures()
    # the same run with a different frame for each prompt: it settled on nothing
    monkeypatch.setattr(figures, "_json", _with_samples(
        real, "gated/fresh/gated-seed24/summary.json",
        lambda samples: [{**x, "completion": "ab" * i + x["completion"]} for i, x in enumerate(samples)]))
    with pytest.raises(ValueError, match="settled on one frame .* frame None"):
        figures.gated_figures()


def _with_samples(real, rel_summaries, change):
    """figures._json with the held-out greedy samples of one summary (a path) or several (a set)
    passed through ``change``."""
    wanted = {rel_summaries} if isinstance(rel_summaries, str) else rel_summaries
    def changed(rel):
        data = real(rel)
        if rel in wanted:
            greedy = data["after"]["greedy"]
            data = {**data, "after": {**data["after"], "greedy": {**greedy, "samples": change(greedy["samples"])}}}
        return data
    return changed


@pytest.mark.parametrize("file, changes, mistake", [
    # a fresh seed with no machine named
    ("gated/fresh/machines.json", lambda d: {**d, "seeds": {k: v for k, v in d["seeds"].items() if k != "25"}},
     "names the machine of every fresh pair"),
    # a run that records another machine than the file names for its pair
    ("gated/fresh/gated-seed21/summary.json",
     lambda d: {**d, "cpu": {"model": "AMD EPYC", "bf16_units": "AVX512-BF16"}}, "ran on"),
    # one run of a pair twice as slow as its twin: not one machine
    ("gated/fresh/gated-seed21/summary.json", lambda d: {**d, "seconds": 2 * d["seconds"]},
     "both runs of seed 21's pair ran on one machine"),
    # every pair on one machine: 6.8 says two
    ("gated/fresh/machines.json", lambda d: {**d, "seeds": {k: d["seeds"]["21"] for k in d["seeds"]}},
     "ran on one machine; their wall times differ"),
    # two pairs on the slower machine: 6.8 names one
    ("gated/fresh/machines.json", lambda d: {**d, "seeds": {**d["seeds"], "24": d["seeds"]["25"]}},
     "ran on one machine; their wall times differ|one fresh pair ran on the slower machine"),
])
def test_the_gated_figures_refuse_machines_the_runs_contradict(monkeypatch, file, changes, mistake):
    assert figures.gated_fresh_machines()["gated.fresh_machines"].startswith("seeds 21, 22, 23 and 24 on an Intel Xeon")
    real = figures._json
    monkeypatch.setattr(figures, "_json", lambda rel: changes(real(rel)) if rel == file else real(rel))
    with pytest.raises(ValueError, match=mistake):
        figures.gated_figures()


def test_the_gated_figures_refuse_a_dead_end_that_sampled_digits_before_the_length(monkeypatch):
    """6.8 says seed 18's bf16 run almost never sampled the right digit sum before it learned the
    length either (at most 1% of its sampled replies then)."""
    rel = "precision-pairs/punished-bf16-seed18"
    steps = [json.loads(line) for line in (figures.RESULTS / rel / "metrics.jsonl").read_text().splitlines()]
    from course_utils import ablation
    real = ablation.records
    early = [{**x, "pass_digits": 0.25} if x["pass_length"] < 0.5 and x["step"] < 31 else x for x in steps]
    monkeypatch.setattr(ablation, "records", lambda run: early if str(run).endswith(rel) else real(run))
    with pytest.raises(ValueError, match="before or after it learned the length: [1-9]"):
        figures.gated_figures()


def test_the_gated_figures_refuse_endings_the_runs_stop_supporting(monkeypatch):
    """What 6.8 says of how the runs ended, each altered in the stored files until its check fires."""
    real = figures._json
    # a fresh control whose replies hold no digit: 6.8 says no fresh run of either arm did
    monkeypatch.setattr(figures, "_json", _with_samples(
        real, "gated/fresh/punished-seed23/summary.json",
        lambda samples: [{**x, "completion": "Nothing but words in this reply."} for x in samples]))
    with pytest.raises(ValueError, match="no fresh run ended on replies without a digit"):
        figures.gated_figures()
    # 6.7's fp32 seed-18 run a template run: no fixed-number sentence before the gate
    monkeypatch.setattr(figures, "_json", _lifted_after(real, {"punished-fp32-seed18"}, pass_both_one_digit=1.0))
    with pytest.raises(ValueError, match="already ended on a fixed-number sentence"):
        figures.gated_figures()
    # gated seed 22's frame 32 characters with a one-digit number: not one character short
    monkeypatch.setattr(figures, "_json", _with_samples(
        real, "gated/fresh/gated-seed22/summary.json",
        lambda samples: [{**x, "n_chars": 32} for x in samples]))
    with pytest.raises(ValueError, match="one character short"):
        figures.gated_figures()
    # gated seed 22's replies all different: every digits-first gated run unsettled
    monkeypatch.setattr(figures, "_json", _with_samples(
        real, "gated/fresh/gated-seed22/summary.json",
        lambda samples: [{**x, "completion": f"{'ab' * i}{x['completion']}"} for i, x in enumerate(samples)]))
    with pytest.raises(ValueError, match="one settled on a frame one character short"):
        figures.gated_figures()
    # every gated run's two-digit replies with the target's own digit sum: no one fixed sum
    gated = {f"{figures._relative(r)}/summary.json" for stage in ("tuning", "fresh")
             for r in figures.gated_pair_runs(stage)[0]}
    monkeypatch.setattr(figures, "_json", _with_samples(
        real, gated, lambda samples: [{**x, "digit_sum": x["target_digit_sum"]} for x in samples]))
    with pytest.raises(ValueError, match="end their two-digit targets on one digit sum"):
        figures.gated_figures()


def test_the_gated_figures_refuse_a_credit_that_pays_right_digits_differently(monkeypatch):
    """6.8 says a near miss with the right digits earns the same under both credits (D = 1)."""
    from course_utils import rewards
    real = rewards.gated_score
    monkeypatch.setattr(rewards, "gated_score", lambda *a: 0.99 * real(*a))
    with pytest.raises(ValueError, match="pay a reply with the right digits alike"):
        figures.gated_figures()


@pytest.mark.parametrize("files, changes, mistake", [
    (["forks/forks-seed16/config.json"], {"lr": 1e-4}, "nothing else changed"),
    (["forks/forks-seed16/config.json"], {"top_entropy_quantile": 0.5}, "nothing else changed"),
    (["forks/forks-seed16/config.json"], {"seed": 17}, "nothing else changed"),
    (["forks/forks-seed16/summary.json"], {"precision": "fp32"}, "bf16 on a CPU with AMX"),
    (["forks/forks-seed16/summary.json"], {"cpu": {"model": "AMD EPYC", "bf16_units": "AVX512-BF16"}},
     "bf16 on a CPU with AMX"),
    ([figures.FORKS_RERUN + "/config.json"], {"kl_coef": 0.0}, "reruns gated-seed16"),
    ([figures.FORKS_RERUN + "/summary.json"], {"cpu": {"model": "AMD EPYC", "bf16_units": "none"}},
     "ran on a CPU with AMX"),
])
def test_the_forks_figures_refuse_a_run_that_is_not_what_6_9_says(monkeypatch, files, changes, mistake):
    _refused_after_changes(monkeypatch, figures.forks_figures, files, changes, mistake)


@pytest.mark.parametrize("step, key, value", [(0, "loss", 0.123), (4, "reward_mean", 0.0), (2, "entropy", 1.0)])
def test_the_forks_figures_refuse_a_rerun_that_does_not_match_its_control(monkeypatch, step, key, value):
    """6.9 takes 6.8's stored gated runs as controls because one of them, rerun for its first
    steps on the forks runs' machine, matched bitwise: a rerun that differs in any logged number
    (timings aside) is refused, and so is one with a step missing."""
    from course_utils import ablation
    real = ablation.records

    def altered(run):
        steps = real(run)
        if run.name == Path(figures.FORKS_RERUN).name:
            steps[step] = {**steps[step], key: value}
        return steps
    monkeypatch.setattr(ablation, "records", altered)
    with pytest.raises(ValueError, match="bitwise"):
        figures.forks_figures()
    monkeypatch.setattr(ablation, "records", lambda run: real(run)[:-1] if run.name == Path(figures.FORKS_RERUN).name
                        else real(run))
    with pytest.raises(ValueError, match="bitwise"):
        figures.forks_figures()


def test_the_forks_figures_refuse_a_seed_with_a_run_missing(monkeypatch, tmp_path):
    monkeypatch.setattr(figures, "FORKS_SEEDS", (*figures.FORKS_SEEDS, 99))
    with pytest.raises(ValueError, match="tuning seeds"):   # seed 99 has no control
        figures.forks_pair_runs()
    monkeypatch.undo()
    monkeypatch.setattr(figures, "RESULTS", tmp_path)          # no run stored at all
    with pytest.raises(ValueError, match=f"missing .*forks-seed{figures.FORKS_SEEDS[0]}"):
        figures.forks_pair_runs()


def test_the_forks_figures_refuse_prose_the_runs_stop_supporting(monkeypatch):
    """6.9 says every forks run ended with a higher entropy and more replies cut off than its
    control, and fewer held-out replies of the right length; and drops the lever because it did
    worse on average. A run that breaks one of those is refused, with the claim named."""
    from course_utils import ablation
    real_json, real_records = figures._json, ablation.records
    first = f"forks-seed{figures.FORKS_SEEDS[0]}"
    monkeypatch.setattr(figures, "_json", _lifted_after(real_json, [first], pass_length=1.0))
    with pytest.raises(ValueError, match="fewer held-out replies of the right length"):
        figures.forks_figures()
    every = [f"forks-seed{s}" for s in figures.FORKS_SEEDS]
    monkeypatch.setattr(figures, "_json", _lifted_after(real_json, every, pass_both=1.0))
    with pytest.raises(ValueError, match="did worse"):
        figures.forks_figures()
    monkeypatch.setattr(figures, "_json", _lifted_after(real_json, [first], pass_both=1 / 64))
    with pytest.raises(ValueError, match="no forks run passed a held-out prompt"):
        figures.forks_figures()
    monkeypatch.setattr(figures, "_json", real_json)
    for key, value, claim in (("entropy", 0.0, "higher entropy"), ("truncated_frac", 0.0, "more replies cut off")):
        monkeypatch.setattr(ablation, "records", lambda run: [{**x, key: value} for x in real_records(run)]
                            if run.name == first else real_records(run))
        with pytest.raises(ValueError, match=claim):
            figures.forks_figures()


def test_the_forks_run_script_changes_the_gated_recipe_in_one_setting():
    """benchmarks/forks_runs.py builds what 6.9 says it ran: the stored gated config on the seed,
    top_entropy_quantile added for the forks arm and nothing else, the control unchanged."""
    import importlib.util
    spec = importlib.util.spec_from_file_location("forks_runs", ROOT / "benchmarks" / "forks_runs.py")
    forks_runs = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(forks_runs)
    stored = figures._config_with_defaults("gated/tuning/gated-seed17")
    for control, changed in ((False, {"top_entropy_quantile"}), (True, set())):
        cfg = forks_runs.config_for(17, control, None).to_dict()
        assert {k for k in stored if k != "out_dir" and cfg[k] != stored[k]} == changed
    assert forks_runs.config_for(17, False, None).top_entropy_quantile == figures.FORKS_QUANTILE
    assert forks_runs.config_for(16, True, 5).max_steps == 5
    assert forks_runs.config_for(16, True, 5).out_dir.endswith("gated-seed16-steps5")
