"""Shared benchmark plumbing: machine description, timing and JSON output."""

from __future__ import annotations

import json
import os
import pathlib
import platform
import statistics
import time

import jax


def machine_info() -> dict:
    """The machine, the software, the code's commit and the date of a measurement."""
    import datetime

    from tgrf_jax.experiments.runner import source_commit
    from tgrf_jax.runtime.cpu import cpu_model

    return {
        "commit": source_commit(),
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "cpu": cpu_model(),
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "devices": [str(d) for d in jax.devices()],
    }


def time_call(fn, *args, repeats: int = 3):
    """(compile_seconds, median_run_seconds) of a jitted fn; results are blocked on."""
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - start
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        runs.append(time.perf_counter() - start)
    run = statistics.median(runs)
    return max(first - run, 0.0), run


def write_json(path, payload: dict) -> None:
    if not path:
        return
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(payload, indent=2))
    print(f"wrote {path}")
