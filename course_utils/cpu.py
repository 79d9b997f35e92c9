"""What this CPU does fast, and one allocator setting that stops it wasting time.

Two facts measured on the machines this course is built on (benchmarks/RESULTS.md):

* **bf16 matrix units.** Intel's AMX (and, slower, AVX512-BF16) multiply bf16 matrices 5-7x
  faster than fp32; a CPU without them (many laptops, Colab's CPU runtimes) emulates bf16 and
  is *slower* in it than in fp32. ``native_bf16()`` tells which kind this is, and
  ``precision='auto'`` picks bf16 only where it is native.
* **Fresh pages cost more than arithmetic.** A GRPO step allocates several vocabulary-sized
  tensors ([rows, tokens, 49,152] floats, 100+ MB each). glibc hands every allocation above
  32 MB to ``mmap``, so each one arrives as fresh pages that the kernel must fault in and zero,
  and an element-wise pass into a new tensor costs several times one into an existing tensor.
  ``keep_freed_memory()`` makes glibc serve large blocks from its heap and keep them, so
  the second step reuses the first step's pages. It changes no number, only time: in
  benchmarks/step_speed.py the ``reference fp32`` arm differs from ``old fp32`` by this and by
  skipping divisions by a temperature of 1 (which change nothing either).
"""

from __future__ import annotations

import ctypes
import functools
import ctypes.util
import platform
import sys
from pathlib import Path

import torch


def _cpu_flags() -> set[str]:
    """The CPU's feature flags as Linux reports them (empty elsewhere)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("flags"):
                return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


@functools.cache   # the machine does not change; torch's probe is not free
def bf16_units() -> str:
    """Which hardware multiplies bf16 matrices here: 'AMX', 'AVX512-BF16' or 'none' (emulated).

    torch's own probe initializes AMX where the CPU and the kernel allow it; the flags cover
    AVX512-BF16 without AMX. Apple Silicon and other ARM CPUs answer 'none' (their bf16 support in
    torch's CPU kernels is not what these measurements cover)."""
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return "none"
    amx = getattr(torch._C._cpu, "_init_amx", None)
    if amx is not None and amx():
        return "AMX"
    return "AVX512-BF16" if "avx512_bf16" in _cpu_flags() else "none"


def native_bf16() -> bool:
    """True when bf16 matrix products run on hardware units (AMX or AVX512-BF16), not emulated."""
    return bf16_units() != "none"


def machine() -> dict[str, str]:
    """The CPU a run ran on, for its summary: the model name Linux reports and its bf16 units.
    torch's ``get_cpu_capability()`` says 'AVX512' both on an AMX Xeon and on an AMD EPYC
    without AMX, and a bf16 run's arithmetic differs between the two (lesson 7, 6.8)."""
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"model": model, "bf16_units": bf16_units()}


def keep_freed_memory() -> bool:
    """Ask glibc (Linux) to serve every allocation from its heap and never hand freed memory back
    to the system, so large tensors reuse pages already faulted in. Returns whether it applied.

    M_MMAP_MAX = 0 turns off mmap for large blocks; M_TRIM_THRESHOLD = 2 GiB (the most a C int holds) keeps freed heap
    memory (the resident set stays at the step's peak instead of shrinking between steps)."""
    if not sys.platform.startswith("linux"):
        return False
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):   # musl and other libcs have no mallopt
        return False
    M_TRIM_THRESHOLD, M_MMAP_MAX = -1, -4
    return bool(mallopt(M_MMAP_MAX, 0)) and bool(mallopt(M_TRIM_THRESHOLD, 2**31 - 1))  # an int
