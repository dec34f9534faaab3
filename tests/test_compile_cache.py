"""The persistent compilation cache of the command-line tools (tgrf_jax.runtime.compile_cache), each case in a fresh
process: the cache is process-global JAX state."""

import json
import os
import subprocess
import sys

PROBE = r"""
import json
import jax, jax.numpy as jnp
from jax import monitoring

hits = []
monitoring.register_event_listener(
    lambda event, **_: hits.append(event) if event == "/jax/compilation_cache/cache_hits" else None)
from tgrf_jax.runtime import compile_cache

path = compile_cache.enable()
x = jax.jit(lambda a: jnp.tanh(a) @ a.T + jnp.cos(a).sum())(jnp.arange(12.0).reshape(3, 4) / 7)
print(json.dumps({"path": None if path is None else str(path), "hits": len(hits),
                  "value": [float(v) for v in x.ravel()]}))
"""


def probe(**env_overrides):
    env = {k: v for k, v in os.environ.items() if k not in ("TGRF_JAX_COMPILE_CACHE", "JAX_COMPILATION_CACHE_DIR")}
    env.update(JAX_PLATFORMS="cpu", JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0", **env_overrides)
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1]), out.stderr


def test_second_process_loads_the_compiled_program_and_gets_the_same_numbers(tmp_path):
    cache = tmp_path / "cache"
    first, _ = probe(TGRF_JAX_COMPILE_CACHE=str(cache))
    assert first["path"] == str(cache) and first["hits"] == 0
    assert any(p.name.endswith("-cache") for p in cache.iterdir())
    second, _ = probe(TGRF_JAX_COMPILE_CACHE=str(cache))
    assert second["hits"] >= 1
    assert second["value"] == first["value"]


def test_off_means_no_cache_and_no_directory(tmp_path):
    for setting in ("off", "0", ""):
        result, _ = probe(TGRF_JAX_COMPILE_CACHE=setting, XDG_CACHE_HOME=str(tmp_path / "xdg"))
        assert result["path"] is None and result["hits"] == 0
    assert not (tmp_path / "xdg").exists()


def test_default_location_is_under_xdg_cache_home(tmp_path):
    env = {"XDG_CACHE_HOME": str(tmp_path / "xdg")}
    result, _ = probe(**env)
    assert result["path"] == str(tmp_path / "xdg" / "tgrf_jax" / "xla")


def test_jax_own_cache_setting_wins(tmp_path):
    result, _ = probe(JAX_COMPILATION_CACHE_DIR=str(tmp_path / "jax"), TGRF_JAX_COMPILE_CACHE=str(tmp_path / "ours"))
    assert result["path"] == str(tmp_path / "jax")
    assert not (tmp_path / "ours").exists()


def test_unwritable_location_warns_and_compiles_anyway(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a directory")
    result, stderr = probe(TGRF_JAX_COMPILE_CACHE=str(blocker / "cache"))
    assert result["path"] is None and len(result["value"]) == 9
    assert "compilation cache off" in stderr and "TGRF_JAX_COMPILE_CACHE" in stderr
