"""XLA:CPU process settings: 512-bit vectors on AVX-512 CPUs and the number of CPU devices.

XLA reads both from ``XLA_FLAGS`` once, when JAX first touches its backend, so they are process-wide choices
made before any computation: by the command-line tools, and by notebook or library users through
:func:`configure_cpu` (``import tgrf_jax`` changes nothing). Flags the user already set win.

* Vector width: LLVM, and with it XLA:CPU, emits 256-bit vectors by default even where the CPU has AVX-512 (wide
  vectors once cost clock speed on early AVX-512 chips). The ORCA solver's linear programs, one problem per
  vector lane, run markedly faster with 512-bit vectors on AVX-512 machines, with identical results
  (docs/benchmarks.md).
* Device count: XLA:CPU spreads one program's small ops over the cores poorly, while programs pinned to one
  device each run side by side; so tgrf-train gives each env shard (``ppo.num_shards``) a CPU device and
  tgrf-sweep gives each core one (docs/design.md).
"""

from __future__ import annotations

import os
import pathlib
import platform

WIDTH_FLAG = "--xla_cpu_prefer_vector_width"
DEVICE_COUNT_FLAG = "--xla_force_host_platform_device_count"


def _read_cpuinfo() -> str:
    try:
        return pathlib.Path("/proc/cpuinfo").read_text()
    except OSError:
        return ""


def _cpu_flags(cpuinfo: str) -> set[str]:
    for line in cpuinfo.splitlines():
        if line.startswith("flags"):
            return set(line.split(":", 1)[1].split()) if ":" in line else set()
    return set()


def has_avx512(cpuinfo: str | None = None) -> bool:
    """Whether the CPU has AVX-512 Foundation (Linux ``/proc/cpuinfo``; False where that cannot be read)."""
    return "avx512f" in _cpu_flags(_read_cpuinfo() if cpuinfo is None else cpuinfo)


def vector_isa(cpuinfo: str | None = None) -> str | None:
    """The widest x86 vector instruction set of the CPU ('AVX-512', 'AVX2', 'AVX'), None where unknown.

    XLA:CPU compiles for the host's instruction set, so two CPUs sold under one model name but of different
    generations (an AVX2 and an AVX-512 EPYC) round differently and train different runs from the same seed:
    results record it beside the model name."""
    flags = _cpu_flags(_read_cpuinfo() if cpuinfo is None else cpuinfo)
    for flag, name in (("avx512f", "AVX-512"), ("avx2", "AVX2"), ("avx", "AVX")):
        if flag in flags:
            return name
    return None


def backend_started() -> bool:
    """Whether JAX's backends exist already (then XLA_FLAGS no longer matter)."""
    import sys

    if "jax" not in sys.modules:
        return False
    # JAX has no public query for this; the private one is confined to this function.
    from jax._src import xla_bridge

    return xla_bridge.backends_are_initialized()


def configure_cpu(devices: int | None = None, *, wide_vectors: bool = True) -> dict[str, str]:
    """Choose XLA:CPU's vector width and device count for this process; call it before any JAX computation.

    `devices`: CPU devices to create (e.g. one per env shard or per core; None or 1: leave XLA's single device);
    `wide_vectors`: 512-bit vectors where the CPU has AVX-512. A flag already in ``XLA_FLAGS`` is left alone, and
    nothing is changed once JAX's backend exists. Returns the flags added, {flag: value}.
    """
    if backend_started():
        return {}
    flags = os.environ.get("XLA_FLAGS", "")
    added = {}
    if wide_vectors and WIDTH_FLAG not in flags and has_avx512():
        added[WIDTH_FLAG] = "512"
    if devices is not None and devices > 1 and DEVICE_COUNT_FLAG not in flags:
        added[DEVICE_COUNT_FLAG] = str(int(devices))
    if added:
        os.environ["XLA_FLAGS"] = " ".join([flags] + [f"{k}={v}" for k, v in added.items()]).strip()
    return added


def cpu_model(cpuinfo: str | None = None) -> str:
    """The processor's model name and vector instruction set, e.g. 'AMD EPYC (AVX2)' (Linux /proc/cpuinfo; else
    what `platform` knows), for recording results."""
    cpuinfo = _read_cpuinfo() if cpuinfo is None else cpuinfo
    name = next((line.split(":", 1)[1].strip() for line in cpuinfo.splitlines() if line.startswith("model name")), None)
    name = name or platform.processor() or platform.machine()
    isa = vector_isa(cpuinfo)
    return f"{name} ({isa})" if isa else name
