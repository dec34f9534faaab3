"""Persistent XLA compilation cache for the command-line tools.

Every `tgrf-train`, `tgrf-eval`, `tgrf-sweep` and `tgrf-render` process compiles the same large programs (the
default training chunk takes about 30 s, the 500-episode evaluation about 25 s on 2 CPU cores). JAX can keep the
compiled executables on disk; a later process with the same program, shapes, jax version and machine loads them
instead of compiling. A cached executable is the very program that was compiled, so results are bit-identical.

Where: ``$TGRF_JAX_COMPILE_CACHE`` if set (``off``, ``0``, ``no``, ``false`` or empty: no cache), else
``$XDG_CACHE_HOME/tgrf_jax/xla`` (``~/.cache/tgrf_jax/xla``). If the user configured JAX's own cache
(``JAX_COMPILATION_CACHE_DIR`` or ``jax.config``), that wins and this module leaves it alone.
"""

from __future__ import annotations

import os
import pathlib
import sys

ENV_VAR = "TGRF_JAX_COMPILE_CACHE"
# With a size bound JAX evicts least-recently-used entries and takes a file lock around reads and writes, so
# concurrent processes (a sweep's workers, a training run and a tgrf-eval beside it) cannot see half-written
# entries. One default-config entry is a few MB.
MAX_BYTES = 2 * 1024**3
_DISABLED = ("", "0", "off", "no", "false")


def default_dir() -> pathlib.Path:
    base = os.environ.get("XDG_CACHE_HOME") or pathlib.Path.home() / ".cache"
    return pathlib.Path(base) / "tgrf_jax" / "xla"


def enable() -> pathlib.Path | None:
    """Switch the persistent cache on for this process (call before the first compilation).

    Returns the cache directory in use, or None when it is off. Never fails the caller: a directory that
    cannot be created costs a warning and the process compiles as usual.
    """
    import jax

    configured = jax.config.jax_compilation_cache_dir
    if configured:
        return pathlib.Path(configured)
    setting = os.environ.get(ENV_VAR)
    if setting is not None and setting.strip().lower() in _DISABLED:
        return None
    path = pathlib.Path(setting).expanduser() if setting is not None else default_dir()
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        print(
            f"tgrf-jax: warning: compilation cache off, cannot create {path} ({e}); set {ENV_VAR} to a "
            f"writable directory or to 'off'",
            file=sys.stderr,
        )
        return None
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_compilation_cache_max_size", MAX_BYTES)  # needs `filelock`, a dependency
    return path
