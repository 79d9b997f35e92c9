"""The notebooks: generated files in sync, one repository URL, exercises that bite, re-runnable."""
import copy
import re
import sys
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient
from nbclient.exceptions import CellExecutionError

from course_utils import GITHUB_REPO

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = ROOT / "notebooks"
sys.path.insert(0, str(NOTEBOOKS))
import build  # noqa: E402

LESSONS = sorted(p.stem for p in (NOTEBOOKS / "src").glob("[0-9][0-9]_*.py"))
EXERCISE_LESSONS = [n for n in LESSONS if "exercises.check_" in (NOTEBOOKS / "src" / f"{n}.py").read_text()]
ALL_IPYNB = [NOTEBOOKS / f"{n}.ipynb" for n in LESSONS] + [NOTEBOOKS / "solutions" / f"{n}.ipynb" for n in LESSONS]


def test_there_are_four_exercise_lessons_and_every_lesson_has_both_flavours():
    assert len(EXERCISE_LESSONS) >= 4
    assert all(p.exists() for p in ALL_IPYNB)


def test_generated_notebooks_are_up_to_date():
    assert build.stale() == [], "run `python notebooks/build.py` and commit the result"


def test_committed_notebooks_carry_no_outputs():
    for path in ALL_IPYNB:
        nb = nbformat.read(path, as_version=4)
        for cell in nb.cells:
            if cell.cell_type == "code":
                assert cell.outputs == [] and cell.execution_count is None, path.name


REPO_PATTERN = r"github(?:usercontent)?(?:\.com)?/([\w.-]+/[\w.-]+?)(?:\.git|/blob|/main|[\"')\s\\])"


def test_readme_badges_use_the_one_repository():
    text = (ROOT / "README.md").read_text()
    assert set(re.findall(REPO_PATTERN, text)) == {GITHUB_REPO}
    for name in LESSONS:
        assert f"colab.research.google.com/github/{GITHUB_REPO}/blob/main/notebooks/{name}.ipynb" in text


def test_every_link_and_install_uses_the_one_repository():
    for path in ALL_IPYNB:
        text = path.read_text()
        repos = set(re.findall(REPO_PATTERN, text))
        assert repos == {GITHUB_REPO}, (path.name, repos)
        assert f"colab.research.google.com/github/{GITHUB_REPO}/blob/main/notebooks/" in text
        assert f"git+https://github.com/{GITHUB_REPO}.git" in text  # the Colab set-up cell


def test_setup_cell_installs_only_in_colab_and_never_touches_torch():
    code = build.setup_code()
    assert 'if "google.colab" in sys.modules:' in code
    install = code[code.index("subprocess.run"):]
    assert "torch" not in install and "--upgrade" not in install and "-U" not in install
    assert "requirements.txt" not in install  # its pinned CPU torch must never reach Colab


def test_learner_flavour_has_no_solutions():
    for name in EXERCISE_LESSONS:
        learner = (NOTEBOOKS / f"{name}.py").read_text()
        solution = (NOTEBOOKS / "solutions" / f"{name}.py").read_text()
        assert "BEGIN SOLUTION" not in learner + solution
        n_exercises = len(re.findall(r"exercises\.check_\w+\(", learner))
        assert n_exercises >= 3, name
        assert learner.count("raise NotImplementedError") >= n_exercises
        assert "raise NotImplementedError  # your code here" not in solution


def _execute(nb):
    NotebookClient(nb, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(NOTEBOOKS)}}).execute()


@pytest.mark.parametrize("name", EXERCISE_LESSONS)
def test_learner_notebook_stops_at_its_first_exercise_checker(name):
    nb = nbformat.read(NOTEBOOKS / f"{name}.ipynb", as_version=4)
    first_check = next(i for i, c in enumerate(nb.cells)
                       if c.cell_type == "code" and "exercises.check_" in c.source)
    with pytest.raises(CellExecutionError) as err:
        _execute(nb)
    assert err.value.ename == "ExerciseError" and "not implemented yet" in err.value.evalue
    ran = [i for i, c in enumerate(nb.cells) if c.cell_type == "code" and c.get("execution_count")]
    assert max(ran) == first_check, "the notebook must fail at the first checker, not before or after"
    failing = nb.cells[first_check]
    assert any(o.get("ename") == "ExerciseError" for o in failing.outputs)


@pytest.mark.parametrize("name", LESSONS)
def test_solution_notebook_survives_running_every_cell_twice(name):
    nb = nbformat.read(NOTEBOOKS / "solutions" / f"{name}.ipynb", as_version=4)
    doubled = copy.deepcopy(nb)
    doubled.cells = [c for cell in nb.cells for c in ([cell, copy.deepcopy(cell)] if cell.cell_type == "code" else [cell])]
    _execute(doubled)
