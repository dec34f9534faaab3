"""The XLA:CPU vector-width flag that importing tgrf_jax adds on AVX-512 machines (tgrf_jax.cpu_codegen)."""

import os
import subprocess
import sys

import jax

from tgrf_jax import cpu_codegen

AVX512_CPUINFO = "processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f avx512dq\n"
AVX2_CPUINFO = "processor\t: 0\nflags\t\t: fpu sse2 avx2 fma\n"
PROBE = "import os, tgrf_jax; print(os.environ.get('XLA_FLAGS', ''))"


def test_avx512_is_read_from_the_cpu_flags():
    assert cpu_codegen.has_avx512(AVX512_CPUINFO)
    assert not cpu_codegen.has_avx512(AVX2_CPUINFO)
    assert not cpu_codegen.has_avx512("model name\t: avx512f-like name but no flags line\n")


def _flags_after_import(xla_flags: str) -> str:
    env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS=xla_flags)
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip().splitlines()[-1] if out.stdout.strip() else ""


def test_import_prefers_512_bit_vectors_only_on_avx512_cpus():
    flags = _flags_after_import("--xla_force_host_platform_device_count=2")
    assert "--xla_force_host_platform_device_count=2" in flags.split()
    assert ("--xla_cpu_prefer_vector_width=512" in flags.split()) == cpu_codegen.has_avx512()


def test_a_width_chosen_by_the_user_is_kept():
    assert _flags_after_import("--xla_cpu_prefer_vector_width=256") == "--xla_cpu_prefer_vector_width=256"


def test_nothing_is_added_once_the_backend_exists(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "")
    jax.devices()
    assert cpu_codegen.prefer_wide_vectors() is False
    assert os.environ["XLA_FLAGS"] == ""
