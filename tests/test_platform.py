"""Where the course runs: the device a preset pins, the precision a GPU can really do, and an
install that chooses torch's CPU build."""
import re
from pathlib import Path

import pytest

from course_utils import config as config_module
from course_utils.config import ConfigError, load_config

ROOT = Path(__file__).resolve().parents[1]


def test_the_cpu_preset_pins_the_cpu_even_where_a_gpu_would_be_picked():
    from accelerate.state import PartialState

    from course_utils import train
    assert load_config("cpu").device == "cpu" and load_config("t4", precision="fp32").device == "auto"
    policy = train.setup(load_config("smoke", device="cpu"))
    assert PartialState._shared_state["_cpu"] is True
    assert next(policy.model.parameters()).device.type == "cpu"
    train.setup(load_config("smoke"))  # switching back in the same process needs no restart
    assert PartialState._shared_state["_cpu"] is False


@pytest.mark.parametrize("capability, ok", [((7, 5), False), ((6, 1), False), ((8, 0), True), ((9, 0), True)])
def test_bf16_is_refused_on_a_gpu_older_than_ampere(monkeypatch, capability, ok):
    monkeypatch.setattr(config_module, "_cuda_capability", lambda: capability)
    if ok:
        assert load_config("gpt2-rtx4070").precision == "bf16"
    else:
        with pytest.raises(ConfigError, match=r"precision.*bf16.*compute capability 8\.0.*"
                                              rf"{capability[0]}\.{capability[1]}.*fp16"):
            load_config("gpt2-rtx4070")


def test_bf16_on_the_cpu_asks_no_gpu(monkeypatch):
    monkeypatch.setattr(config_module, "_cuda_capability", lambda: (7, 5))
    assert load_config("gpt2-rtx4070", device="cpu").precision == "bf16"


def test_fp16_is_refused_on_the_cpu_device_even_beside_a_gpu(monkeypatch):
    monkeypatch.setattr(config_module, "_cuda_available", lambda: True)
    assert load_config("t4").precision == "fp16"
    with pytest.raises(ConfigError, match="precision.*fp16 needs a CUDA GPU; use fp32 on a CPU"):
        load_config("t4", device="cpu")


def test_the_installed_torch_is_the_cpu_build():
    """What the README's install chose here: no CUDA build, no nvidia-* package."""
    import importlib.metadata

    import torch
    assert torch.version.cuda is None, torch.__version__
    nvidia = [d.metadata["Name"] for d in importlib.metadata.distributions()
              if d.metadata["Name"].lower().startswith("nvidia")]
    assert not nvidia


def test_requirements_take_torch_from_the_cpu_index_on_linux_only():
    reqs = (ROOT / "requirements.txt").read_text()
    assert re.search(r"^--extra-index-url https://download\.pytorch\.org/whl/cpu$", reqs, flags=re.M)
    linux = re.search(r'^torch==(\S+)\+cpu ; sys_platform == "linux"$', reqs, flags=re.M)
    other = re.search(r'^torch==(\S+) ; sys_platform != "linux"$', reqs, flags=re.M)
    assert linux and other and linux.group(1) == other.group(1)


def test_requires_python_is_the_python_the_readme_states():
    import sys
    pyproject = (ROOT / "pyproject.toml").read_text()
    low = re.search(r'requires-python = ">=3\.(\d+)"', pyproject)
    assert low and sys.version_info >= (3, int(low.group(1)))
    assert f"Python 3.{low.group(1)} or newer" in (ROOT / "README.md").read_text()


@pytest.mark.parametrize("amx, flags, units", [
    (True, {"avx512_bf16", "amx_bf16"}, "AMX"),
    (False, {"avx512_bf16", "avx512f"}, "AVX512-BF16"),   # an AMD EPYC (Zen 4): no AMX
    (False, {"avx2", "fma"}, "none"),                       # a laptop, or Colab's CPU runtime
])
def test_the_summary_names_the_bf16_units_the_capability_cannot_tell_apart(monkeypatch, amx, flags, units):
    """torch's get_cpu_capability() says 'AVX512' on an AMX Xeon and on an AMD EPYC alike; a bf16
    run's arithmetic differs between them, so summary.json records cpu.machine() as well."""
    import platform

    import torch

    from course_utils import cpu
    monkeypatch.setattr(platform, "machine", lambda: "x86_64")
    monkeypatch.setattr(torch._C._cpu, "_init_amx", lambda: amx, raising=False)
    monkeypatch.setattr(cpu, "_cpu_flags", lambda: flags)
    cpu.bf16_units.cache_clear()
    try:
        assert cpu.bf16_units() == units and cpu.native_bf16() == (units != "none")
        assert cpu.machine()["bf16_units"] == units and cpu.machine()["model"]
    finally:
        cpu.bf16_units.cache_clear()
    monkeypatch.setattr(platform, "machine", lambda: "arm64")
    assert cpu.bf16_units() == "none"
    cpu.bf16_units.cache_clear()
