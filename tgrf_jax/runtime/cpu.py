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


def has_avx512(cpuinfo: str | None = None) -> bool:
    """Whether the CPU has AVX-512 Foundation (Linux ``/proc/cpuinfo``; False where that cannot be read)."""
    if cpuinfo is None:
        try:
            cpuinfo = pathlib.Path("/proc/cpuinfo").read_text()
        except OSError:
            return False
    return any(line.startswith("flags") and "avx512f" in line.split() for line in cpuinfo.splitlines())


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


def cpu_model() -> str:
    """The processor's model name (Linux /proc/cpuinfo; else what `platform` knows), for recording results."""
    try:
        for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()
