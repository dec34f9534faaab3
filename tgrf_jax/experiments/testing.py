"""The held-out tests of an experiment's rows: each run's final policy, and the experiment's `compare` policies,
played under the row's `test` settings by `tgrf-eval` child processes (one per policy, each writing its own JSON,
so an interrupted test stage resumes where it stopped).

Per row directory:

    runs/<run>/test_eval.json     the run's final policy on the test episodes (tgrf-eval --out)
    compare/<policy>.json         a compared policy on the same episodes
    test_provenance.json          per evaluation: command, commit, machine, exit code, start and end; and
                                  where the row's test settings changed, which results were moved aside
    superseded_tests/<time>/      results of earlier test settings, under the same relative paths

The test episodes are the row's final evaluation's (`run.eval_episodes`, `run.eval_seed`), augmentation off as in
every evaluation, so the runs and the compared policies meet the same people.
"""

from __future__ import annotations

import datetime
import json
import os
import pathlib
import shlex
import subprocess
import sys
from collections.abc import Callable

from tgrf_jax.experiments import report
from tgrf_jax.experiments.report import COMPARE_DIR, TEST_FILE
from tgrf_jax.experiments.spec import BASELINES, Experiment, Row, tested_config
from tgrf_jax.storage.files import write_atomic

TEST_PROVENANCE = "test_provenance.json"
SUPERSEDED_DIR = "superseded_tests"


def _sets(row: Row) -> list[str]:
    return [arg for item in row.test for arg in ("--set", item)]


def jobs(exp: Experiment, row: Row, row_dir: pathlib.Path) -> list[tuple[pathlib.Path, list[str]]]:
    """(output file, tgrf-eval arguments) of every evaluation of a finished row's test stage."""
    run = tested_config(exp, row).run
    common = ["--episodes", str(run.eval_episodes), "--seed", str(run.eval_seed), "--all-metrics"]
    out = []
    runs = report.read_evals(row_dir)
    for r in runs:
        run_dir = row_dir / "runs" / r["run"]
        dest = run_dir / TEST_FILE
        out.append((dest, [str(run_dir), *_sets(row), *common, "--out", str(dest)]))
    for name in exp.compare:
        dest = row_dir / COMPARE_DIR / f"{name}.json"
        if name in BASELINES:
            # the baseline robot on the env of the row's first run, as tested
            source = ["--policy", name, str(row_dir / "runs" / runs[0]["run"] / "config.yaml")] if runs else []
        else:
            source = ["--pretrained", name]
        if source:
            out.append((dest, [*source, *_sets(row), *common, "--out", str(dest)]))
    return out


def tested(exp: Experiment, row: Row, row_dir: pathlib.Path) -> bool:
    """Every evaluation of the row's test stage has its results (a row without a test: True)."""
    if not row.test:
        return True
    todo = jobs(exp, row, row_dir)
    return bool(todo) and all(dest.is_file() for dest, _ in todo)


def run_tests(
    exp: Experiment, row: Row, row_dir: pathlib.Path, say: Callable[[str], None], commit: str, machine: str
) -> int:
    """Play the evaluations of the row's test stage that have no results yet, one tgrf-eval child process each,
    recording each (with the `commit` and `machine` it runs on) in test_provenance.json; returns the first
    non-zero exit code (the rest wait for a rerun), else 0."""
    todo = [(dest, args) for dest, args in jobs(exp, row, row_dir) if not dest.is_file()]
    prov_path = row_dir / TEST_PROVENANCE
    prov = _read(prov_path)
    for i, (dest, args) in enumerate(todo):
        what = dest.parent.name if dest.name == TEST_FILE else dest.stem
        say(f"  {row.name} | test {i + 1}/{len(todo)}: {what}")
        dest.parent.mkdir(parents=True, exist_ok=True)
        entry = {
            "command": shlex.join(["tgrf-eval", *args]),
            "commit": commit,
            "machine": machine,
            "started": _now(),
            "exit_code": None,
        }
        prov.append(entry)
        write_atomic(prov_path, json.dumps(prov, indent=2))
        proc = subprocess.run(
            [sys.executable, "-m", "tgrf_jax.cli.eval", *args],
            capture_output=True,
            text=True,
            env=dict(os.environ, PYTHONUNBUFFERED="1"),
        )
        entry.update(exit_code=proc.returncode, finished=_now())
        write_atomic(prov_path, json.dumps(prov, indent=2))
        if proc.returncode != 0:
            for line in (proc.stdout + proc.stderr).splitlines()[-5:]:
                say(f"  {row.name} | {line}")
            return proc.returncode
    return 0


def supersede(row_dir: pathlib.Path, test_before, test_now) -> tuple[pathlib.Path, int] | None:
    """Move the row's test results, made under `test_before`, aside to superseded_tests/<time>/ (nothing is
    deleted) and record the move in test_provenance.json, so that its test stage plays again under `test_now`;
    returns (the folder, how many files) or None where there were none."""
    files = sorted(row_dir.glob(f"runs/*/{TEST_FILE}")) + sorted((row_dir / COMPARE_DIR).glob("*.json"))
    if not files:
        return None
    folder = row_dir / SUPERSEDED_DIR / datetime.datetime.now().astimezone().strftime("%Y%m%dT%H%M%S")
    for path in files:
        dest = folder / path.relative_to(row_dir)
        dest.parent.mkdir(parents=True, exist_ok=True)
        os.replace(path, dest)
    prov_path = row_dir / TEST_PROVENANCE
    prov = _read(prov_path)
    prov.append(
        {
            "superseded": str(folder.relative_to(row_dir)),
            "files": len(files),
            "test_before": test_before,
            "test_now": test_now,
            "at": _now(),
        }
    )
    write_atomic(prov_path, json.dumps(prov, indent=2))
    return folder, len(files)


def _read(path: pathlib.Path) -> list:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        return data if isinstance(data, list) else []
    except (OSError, ValueError):
        return []


def _now() -> str:
    return datetime.datetime.now().astimezone().isoformat(timespec="seconds")
