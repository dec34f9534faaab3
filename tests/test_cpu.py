"""XLA:CPU process settings (tgrf_jax.configure_cpu): chosen by the command-line tools and by one explicit call,
never by importing the package. Each case runs in a fresh process: XLA reads its flags when JAX starts."""

import json
import os
import subprocess
import sys

import jax

from tgrf_jax.runtime import cpu

AVX512_CPUINFO = "processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f avx512dq\n"
AVX2_CPUINFO = "processor\t: 0\nflags\t\t: fpu sse2 avx2 fma\n"


def _probe(code: str, xla_flags: str | None) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env["JAX_PLATFORMS"] = "cpu"
    if xla_flags is not None:
        env["XLA_FLAGS"] = xla_flags
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_avx512_is_read_from_the_cpu_flags():
    assert cpu.has_avx512(AVX512_CPUINFO)
    assert not cpu.has_avx512(AVX2_CPUINFO)
    assert not cpu.has_avx512("model name\t: avx512f-like name but no flags line\n")


def test_the_recorded_cpu_names_its_vector_instruction_set():
    # two EPYCs of one model name round differently when one has AVX-512: results must tell them apart
    name = "model name\t: AMD EPYC\n"
    assert cpu.cpu_model(name + AVX512_CPUINFO) == "AMD EPYC (AVX-512)"
    assert cpu.cpu_model(name + AVX2_CPUINFO) == "AMD EPYC (AVX2)"
    assert cpu.vector_isa("flags\t\t: fpu sse2 avx\n") == "AVX"
    assert cpu.vector_isa("Features\t: fp asimd\n") is None
    assert cpu.cpu_model(name) == "AMD EPYC"


def test_importing_the_package_changes_no_process_state():
    code = (
        "import json, os; import tgrf_jax, tgrf_jax.cli, tgrf_jax.sweep, tgrf_jax.render, tgrf_jax.train; "
        "print(json.dumps({'flags': os.environ.get('XLA_FLAGS')}))"
    )
    assert _probe(code, None)["flags"] is None
    assert _probe(code, "--xla_cpu_prefer_vector_width=256")["flags"] == "--xla_cpu_prefer_vector_width=256"


def test_configure_cpu_adds_devices_and_wide_vectors_before_jax_starts():
    code = (
        "import json, os, tgrf_jax; a = tgrf_jax.configure_cpu(2); b = tgrf_jax.configure_cpu(2); import jax; "
        "print(json.dumps({'a': a, 'b': b, 'devices': len(jax.devices()), 'flags': os.environ['XLA_FLAGS']}))"
    )
    r = _probe(code, "")
    wide = {cpu.WIDTH_FLAG: "512"} if cpu.has_avx512() else {}
    assert r["a"] == dict(wide, **{cpu.DEVICE_COUNT_FLAG: "2"}) and r["b"] == {} and r["devices"] == 2
    # flags the user chose win
    r = _probe(code, f"{cpu.DEVICE_COUNT_FLAG}=3 {cpu.WIDTH_FLAG}=256")
    assert r["a"] == {} and r["devices"] == 3 and r["flags"] == f"{cpu.DEVICE_COUNT_FLAG}=3 {cpu.WIDTH_FLAG}=256"


def test_nothing_is_changed_once_jax_has_started(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "")
    jax.devices()
    assert cpu.configure_cpu(4) == {}
    assert os.environ["XLA_FLAGS"] == ""
