"""Every figure in a lesson's prose comes from somewhere: a stored result file or the library's
arithmetic, filled in by ``notebooks/build.py`` from ``{{fig:NAME}}`` (``notebooks/figures.py``),
or a cell's printed output. A number typed into the prose is a figure that can go stale, so this
test fails on one, unless it is a constant of the setup listed below with its reason."""
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
    "04_trust_regions": {"4.1", "4.2", "4.3", "4.4",                     # exercise numbers
                         "0.1"},                                          # "a step of 0.1" (illustrative)
    "05_grpo": {"5.1", "5.2", "5.3", "5.4",                               # exercise numbers
                "0.01",                                                   # "rewards differ by 0.01 or by 1"
                "16", "128"},                                             # 16 prompts x 8; 128-token prompts
    "06_grpo_by_hand": {"6.1", "6.2", "6.3",                             # exercise numbers
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


@pytest.mark.parametrize("lesson", LESSONS, ids=lambda p: p.stem)
def test_no_figure_is_typed_into_a_lessons_prose(lesson):
    allowed = SETUP.get(lesson.stem, set())
    typed = [(n, f) for n, f in typed_figures(lesson) if f not in allowed]
    assert not typed, (f"{lesson.name}: figures typed into prose (line, figure): {typed}. Render "
                       f"each from a stored result with {{{{fig:NAME}}}} (notebooks/figures.py), "
                       f"let a cell print it, or, for a constant of the setup, list it in SETUP")


def test_the_scanner_finds_typed_figures_and_skips_code_math_and_placeholders(tmp_path):
    lesson = tmp_path / "99_x.py"
    lesson.write_text("# %% [markdown]\n# It fell to 0.64 by step 30, 59 higher and 14.7%; "
                      "`lr=3e-5`, $p=0.5$, {{fig:a.b}}, section 6.1, arXiv 2503.14476 in 2025.\n"
                      "# %%\nx = 0.123\n")
    assert [f for _, f in typed_figures(lesson)] == ["0.64", "30", "59", "14.7%"]


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


WALL_TIME = re.compile(r"\b\d+ ?(?:h|hours?|min|minutes?) \d+ ?(?:s|seconds?|min|minutes?)\b")


def untyped_wall_times(text: str) -> list[str]:
    """Wall times such as '13 min 8 s' typed into prose: outside rendered results sections
    (``<!-- results: NAME -->`` ... ``<!-- end results -->``), code fences and inline code."""
    text = re.sub(r"<!-- results: \w+ -->.*?<!-- end results -->", " ", text, flags=re.S)
    text = re.sub(r"```.*?```", " ", text, flags=re.S)
    text = re.sub(r"`[^`]*`", " ", text)
    return WALL_TIME.findall(text)


def test_no_wall_time_is_typed_into_the_readme():
    """A measured time in the README comes from notebooks/results/readme-timings.jsonl (written
    by benchmarks/readme_timings.py), rendered into a results section, never typed."""
    # still typed: the lessons table's estimate of lesson 8's full run (its many shared runs
    # were never timed as one; issue 25 asks for each lesson's full run to write its time)
    estimates = ["1 hour 15 minutes"]
    typed = [t for t in untyped_wall_times((ROOT / "README.md").read_text()) if t not in estimates]
    assert not typed, (f"README.md: wall times typed into prose: {typed}; measure them with "
                       f"benchmarks/readme_timings.py and let notebooks/build.py render them")


def test_the_wall_time_scanner_finds_typed_times_and_skips_rendered_ones():
    text = ("took 13 min 8 s and 1 h 15 min, `2 min 3 s` in code\n<!-- results: timings -->\n"
            "| main | 12 min 40 s |\n<!-- end results -->\nunder 15 minutes")
    assert untyped_wall_times(text) == ["13 min 8 s", "1 h 15 min"]
