"""Run an experiment row by row as tgrf-sweep (or, for tune rows, tgrf-tune) processes, resumably, and keep its
report up to date.

Each row lives in `<out>/<row>/`, a plain tgrf-sweep or tgrf-tune directory. A row is finished when its results
exist (a sweep's `evals.csv`, a tune's `tune.md`); a row with a checkpoint resumes from it; a row stopped before
its first checkpoint starts again (nothing of it was kept). So the command can be stopped and restarted any number
of times. Each row runs in a child process: a crash or an out-of-memory in one row leaves the others and the
report intact. A search experiment's grid row is read from the finished sweep it names, never trained.
"""

from __future__ import annotations

import contextlib
import ctypes
import datetime
import json
import os
import pathlib
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable

import yaml

from tgrf_jax.config import ConfigError
from tgrf_jax.experiments import report, search, testing
from tgrf_jax.experiments.spec import Experiment, Row, portable, row_command
from tgrf_jax.storage.files import write_atomic

EXPERIMENT_FILE = "experiment.yaml"
PROVENANCE_FILE = "provenance.json"
LOG_FILE = "reproduce.log"
PR_SET_PDEATHSIG = 1  # from <sys/prctl.h>


# What a training run imports or reads. Results written into the checkout (docs/, exported policies under
# tgrf_jax/pretrained/) are not code: they must not mark every row trained from a working tree as '+dirty'.
CODE_PATHS = ("tgrf_jax", "configs", "pyproject.toml", ":(exclude)tgrf_jax/pretrained")


def source_commit(root: pathlib.Path | None = None) -> str:
    """The git commit of the code that runs, with '+dirty' when the package, the configs or pyproject.toml have
    uncommitted changes (new files included), or 'unknown' outside a git checkout."""
    root = pathlib.Path(__file__).resolve().parents[2] if root is None else root
    try:
        head = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "--short=12", "HEAD"],
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(root), "status", "--porcelain", "--untracked-files=all", "--", *CODE_PATHS],
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return head + ("+dirty" if dirty else "")


NVIDIA_DRIVER_GPUS = pathlib.Path("/proc/driver/nvidia/gpus")


def gpu_models() -> list[str]:
    """The models of the NVIDIA GPUs that the driver lists and JAX may use (Linux; else none).

    Read from the driver's files rather than from JAX, because a parent process that starts JAX on a GPU takes
    its memory from the sweep it launches.
    """
    if os.environ.get("CUDA_VISIBLE_DEVICES", None) in ("", "-1"):
        return []
    platforms = os.environ.get("JAX_PLATFORMS", "")
    if platforms and not any(p in platforms for p in ("cuda", "gpu")):
        return []
    try:
        gpu_dirs = sorted(NVIDIA_DRIVER_GPUS.iterdir())
    except OSError:
        return []
    models = []
    for gpu_dir in gpu_dirs:
        try:
            lines = (gpu_dir / "information").read_text().splitlines()
        except OSError:
            continue
        models += [line.split(":", 1)[1].strip() for line in lines if line.startswith("Model:")]
    return models


def machine() -> str:
    """The CPU and its usable cores, and any GPUs, as recorded beside results."""
    from tgrf_jax.runtime.cpu import cpu_model

    desc = f"{cpu_model()}, {len(os.sched_getaffinity(0))} cores"
    models = gpu_models()
    for model in dict.fromkeys(models):
        desc += f", {models.count(model)} x {model}"
    return desc


# per kind of row: the file its tool writes first (the row has started) and the one it writes last (finished)
_MARKERS = {
    "sweep": ("sweep.yaml", "evals.csv"),
    "random": ("sweep.yaml", "evals.csv"),
    "tune": ("tune.yaml", "tune.md"),
}
TOOLS = {"tgrf-sweep": "tgrf_jax.cli.sweep", "tgrf-tune": "tgrf_jax.cli.tune"}


def row_state(row_dir: pathlib.Path, kind: str = "sweep") -> str:
    """'done', 'damaged' (finished, but its results are not whole, or its last invocation is unrecorded: a rerun
    of its finished sweep or tune repairs it), 'resumable', 'stale' (started, no checkpoint yet) or 'new'; a grid
    row of a search experiment is 'read' (its results come from elsewhere)."""
    if kind == "grid":
        return "read"
    started, finished = _MARKERS[kind]
    if (row_dir / finished).is_file():
        return "done" if _results_problem(row_dir, kind) is None and _recorded(row_dir) else "damaged"
    if not (row_dir / started).is_file():
        return "new"
    return "resumable" if _has_step(row_dir) else "stale"


def _results_problem(row_dir: pathlib.Path, kind: str) -> str | None:
    return search.tune_problem(row_dir) if kind == "tune" else report.evals_problem(row_dir)


def row_problem(row_dir: pathlib.Path, kind: str = "sweep") -> str:
    """Why a 'damaged' row is not done."""
    return _results_problem(row_dir, kind) or f"{PROVENANCE_FILE} does not record the invocation that finished it"


def _has_step(row_dir: pathlib.Path) -> bool:
    ckpts = row_dir / "checkpoints"
    return ckpts.is_dir() and any(p.name.isdigit() for p in ckpts.iterdir())


def _recorded(row_dir: pathlib.Path) -> bool:
    """The row's last invocation ended with exit code 0 in provenance.json. The entry is written before the sweep
    starts and completed after it, so a kill in between leaves a row that is not done."""
    prov = report.read_provenance(row_dir)
    return bool(prov and prov["invocations"] and prov["invocations"][-1].get("exit_code") == 0)


def _load_recorded(recorded: pathlib.Path) -> dict:
    try:
        old = yaml.safe_load(recorded.read_text(encoding="utf-8"))
        if (
            not isinstance(old, dict)
            or not isinstance(old.get("rows", []), list)
            or not all(isinstance(r, dict) and "name" in r for r in old.get("rows", []))
        ):
            raise ValueError("not a mapping with a list of rows")
    except (OSError, UnicodeDecodeError, ValueError, yaml.YAMLError) as e:
        raise ConfigError(
            f"{str(recorded)!r} is damaged ({type(e).__name__}: {str(e).splitlines()[0][:80]}): the "
            "settings of the rows in its directory are unknown; restore it, or use another --out"
        ) from None
    return old


def _training_settings(row: dict) -> dict:
    """A recorded row without its test settings: what its runs were trained with."""
    return {k: v for k, v in row.items() if k != "test"}


def retested_rows(exp: Experiment, out: pathlib.Path) -> list[tuple[str, list, list]]:
    """(name, recorded test, test now) of the rows recorded in `out` whose test settings differ from `exp`'s."""
    recorded = out / EXPERIMENT_FILE
    if not recorded.is_file():
        return []
    old_rows = {r["name"]: r for r in _load_recorded(recorded).get("rows", [])}
    return [
        (r["name"], old_rows[r["name"]].get("test", []), r.get("test", []))
        for r in exp.to_dict()["rows"]
        if r["name"] in old_rows and old_rows[r["name"]].get("test", []) != r.get("test", [])
    ]


def check_out_dir(exp: Experiment, out: pathlib.Path) -> None:
    """The output directory holds this experiment (same rows, seeds and budget) or nothing yet. A row whose test
    settings changed is this experiment's still: its tests play again (`retested_rows`)."""
    recorded = out / EXPERIMENT_FILE
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {str(out)!r} is a file, not a directory")
    if recorded.is_file():
        old = _load_recorded(recorded)
        new = exp.to_dict()
        old_rows = {r["name"]: r for r in old.get("rows", [])}
        clash = [k for k in ("config", "seeds", "space", "objective") if old.get(k) != new.get(k)]
        clash += [
            f"row {r['name']}"
            for r in new["rows"]
            if r["name"] in old_rows and _training_settings(old_rows[r["name"]]) != _training_settings(r)
        ]
        if clash:
            raise ConfigError(
                f"{str(out)!r} holds results of this experiment with other settings ({', '.join(clash)} differ); "
                "use another --out, or the same --steps/--seeds as before"
            )
    elif out.is_dir():
        started = sorted(p.name for p in out.iterdir() if any((p / m).is_file() for m in ("sweep.yaml", "tune.yaml")))
        if started:  # their budget and seeds are recorded nowhere else: results could mix settings
            raise ConfigError(
                f"{str(out)!r} holds rows ({', '.join(started[:5])}) but no {EXPERIMENT_FILE}, so "
                "their settings are unknown; restore it, or use another --out"
            )


def _record(exp: Experiment, out: pathlib.Path) -> None:
    """experiment.yaml: the settings of every row run so far (rows of earlier --rows selections are kept)."""
    recorded = out / EXPERIMENT_FILE
    data = exp.to_dict()
    if recorded.is_file():
        old = _load_recorded(recorded)
        names = {r["name"] for r in data["rows"]}
        data["rows"] = [r for r in old.get("rows", []) if r["name"] not in names] + data["rows"]
    write_atomic(recorded, yaml.safe_dump(data, sort_keys=False))


def _fmt_duration(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 3600}:{seconds % 3600 // 60:02d}:{seconds % 60:02d}"


def _stop_child(proc: subprocess.Popen, relay: Callable[[], None]) -> None:
    """Stop the sweep after this process was interrupted, and relay its last lines. SIGTERM asks it to stop after
    its running chunk with a checkpoint (`tgrf_jax.train.stop`; a sweep that Ctrl-C in a terminal reached already
    is stopping so, and takes it as the same request); another interrupt of this process kills it at once."""
    proc.send_signal(signal.SIGTERM)
    try:
        relay()
    except KeyboardInterrupt:
        proc.kill()
        raise


def _stop_with_parent() -> None:
    """In the sweep child, before it starts (Linux): SIGTERM when tgrf-reproduce dies, even by SIGKILL, so the
    sweep stops after its running chunk with a checkpoint rather than training on unattended and unrecorded."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except (OSError, AttributeError):
        pass


def run_row(
    exp: Experiment, row: Row, row_dir: pathlib.Path, say: Callable[[str], None], layout: str | None = None
) -> int:
    """Train (or resume) one row as a tgrf-sweep (tune rows: tgrf-tune) child process; returns its exit code.
    `layout`: a new row's layout (default auto: sequential on CPUs), or the layout a started one switches to
    (default: the one it has)."""
    state = row_state(row_dir, row.kind)
    prov_path = row_dir / PROVENANCE_FILE
    if state == "stale":
        say(f"  {row.name}: stopped before its first checkpoint; starting it again")
        if prov_path.is_file():  # the invocations that got it this far are kept
            kept = prov_path.read_text()
            shutil.rmtree(row_dir)
            row_dir.mkdir(parents=True)
            write_atomic(prov_path, kept)
        else:
            shutil.rmtree(row_dir)
    tool, *args = row_command(exp, row, layout or "auto")
    if state == "damaged":
        say(f"  {row.name}: {row_problem(row_dir, row.kind)}; its finished {tool[5:]} writes its results again")
    cmd = [sys.executable, "-m", TOOLS[tool]]
    if state in ("resumable", "damaged"):
        cmd += ["--resume", str(row_dir)] + (["--layout", layout] if layout else [])
    else:
        cmd += args + ["--out", str(row_dir)]
    prov = report.read_provenance(row_dir) or {"wall_s": 0.0, "invocations": []}
    started, commit = time.perf_counter(), source_commit()  # the code the sweep imports now, not at its end
    invocation = {
        "commit": commit,
        "machine": machine(),
        "exit_code": None,
        "started": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
        "command": shlex.join([tool] + [portable(a) if a == exp.config else a for a in cmd[3:]]),
    }
    wall_before = float(prov.get("wall_s", 0.0))
    prov["invocations"].append(invocation)
    row_dir.mkdir(parents=True, exist_ok=True)
    # recorded before the sweep starts: a kill of this process while the sweep writes its results leaves an
    # invocation without an exit code, and the row is not counted as done until a rerun completes it
    write_atomic(prov_path, json.dumps(prov, indent=2))
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(
        cmd,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
        preexec_fn=_stop_with_parent if sys.platform.startswith("linux") else None,
    )

    def relay_output():
        for line in proc.stdout:
            say(f"  {row.name} | {line.rstrip()}")

    try:
        with proc:
            try:
                relay_output()
            except KeyboardInterrupt:
                _stop_child(proc, relay_output)  # read to the end: it must not die on a closed pipe
                raise
    finally:
        # Also when interrupted: a row trained over several invocations keeps the wall time and commit of each.
        code = proc.wait()
        if row_dir.is_dir():
            prov["wall_s"] = wall_before + time.perf_counter() - started
            invocation.update(
                exit_code=code, finished=datetime.datetime.now().astimezone().isoformat(timespec="seconds")
            )
            write_atomic(prov_path, json.dumps(prov, indent=2))
    return code


def write_report(exp: Experiment, out: pathlib.Path, say: Callable[[str], None] = print) -> list[pathlib.Path]:
    """The experiment's report in `out`: the paper's layout, or for a search experiment its comparison."""
    return search.write(exp, out, say) if exp.search else report.write(exp, out)


def export_best(exp: Experiment, out: pathlib.Path, row: Row, dest_root) -> list[pathlib.Path]:
    """For each compared value of a finished row, export the best seed's final policy to
    `dest_root/<experiment>-<row>-<value>` (see `tgrf_jax.pretrained`)."""
    from tgrf_jax import pretrained

    runs = report.tested_runs(out / row.name) if row.test else report.read_evals(out / row.name)
    axis, written = exp.column_axis, []
    for value in row.grid[0][1]:
        members = [r for r in runs if r.get(axis) == str(value)]
        if not members:
            continue
        best = report.cell(members)["best_seed"]
        run = next(r for r in members if int(r["seed"]) == best)
        meta = {
            "experiment": exp.name,
            "row": row.name,
            "label": row.label,
            axis: str(value),
            "seed": best,
            "test": {
                k: report._float(run[k])
                for k in (
                    "success_rate",
                    "collision_rate",
                    "timeout_rate",
                    "nav_time",
                    "path_length",
                    "itr_future",
                    "itr_disc",
                )
                if k in run
            },
            "commit": _provenance_commit(out / row.name),
        }
        dest = pathlib.Path(dest_root) / f"{exp.name}-{row.name}-{value}"
        written.append(pretrained.export(out / row.name / "runs" / run["run"], dest, meta))
    return written


def _provenance_commit(row_dir: pathlib.Path) -> str | None:
    prov = report.read_provenance(row_dir)
    if prov is None:
        return None
    invocations = prov["invocations"] or [{}]
    return invocations[-1].get("commit")


def export_finished(exp: Experiment, out: pathlib.Path, dest_root) -> list[pathlib.Path]:
    """`export_best` for every finished row of `exp`; returns the exported directories."""
    return [
        path
        for row in exp.rows
        if row.kind == "sweep" and row_state(out / row.name) == "done" and testing.tested(exp, row, out / row.name)
        for path in export_best(exp, out, row, dest_root)
    ]


def reproduce(
    exp: Experiment,
    out,
    *,
    log: Callable[[str], None] = print,
    export_to=None,
    report_exp: Experiment | None = None,
    layout: str | None = None,
) -> int:
    """Run every unfinished row of `exp` into `out`, rewriting the report after each row; returns an exit code.
    With `export_to`, each finished row's best policies are exported there (`export_best`). The report covers
    `report_exp` (default `exp`): the whole experiment when `exp` is a selection of its rows, so rows finished
    by earlier selections stay in the table. `layout`: see `run_row`."""
    from tgrf_jax.storage.lock import exclusive

    out = pathlib.Path(out)
    check_out_dir(exp, out)
    with exclusive(out), _sigterm_as_interrupt():
        return _reproduce(exp, out, log, export_to, report_exp or exp, layout)


@contextlib.contextmanager
def _sigterm_as_interrupt():
    """SIGTERM (`kill`, `timeout`, a scheduler) stops like Ctrl-C: the running row's sweep is asked to stop with a
    checkpoint, its last lines are logged and the invocation is recorded. By default SIGTERM would end this
    process at once, before any of that."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)


def _reproduce(exp: Experiment, out: pathlib.Path, log, export_to, report_exp: Experiment, layout) -> int:
    log_file = open(out / LOG_FILE, "a", buffering=1)

    def say(message: str) -> None:
        log(message)
        log_file.write(message + "\n")

    try:
        # before the new settings are recorded: a run stopped in between finds the change again
        for name, test_before, test_now in retested_rows(exp, out):
            moved = testing.supersede(out / name, test_before, test_now)
            if moved:
                say(
                    f"[{exp.name}] row {name}: its test settings changed; its {moved[1]} earlier test results are "
                    f"in {moved[0]}, and its tests play again"
                )
        _record(exp, out)
        states = {r.name: row_state(out / r.name, r.kind) for r in exp.rows}
        for r in exp.rows:
            if states[r.name] == "done" and not testing.tested(exp, r, out / r.name):
                states[r.name] = "trained, not yet tested"
        todo = [r for r in exp.rows if states[r.name] not in ("done", "read")]
        say(f"[{exp.name}] {exp.title}: {exp.size()}; {len(exp.rows) - len(todo)} rows already done; results in {out}")
        for row in report_exp.rows:  # what a grid row reads must be usable before hours go into the others
            if row.kind == "grid":
                note = search.check_grid(exp, row)
                if note:
                    say(f"[{exp.name}] note: {note}")
        write_report(report_exp, out, say)
        t0 = time.perf_counter()
        for i, row in enumerate(todo):
            done = len(exp.rows) - len(todo) + i
            eta = ""
            if i:
                per_row = (time.perf_counter() - t0) / i
                eta = f"; about {_fmt_duration(per_row * (len(todo) - i))} left"
            say(
                f"[{exp.name}] row {done + 1}/{len(exp.rows)}: {row.label} ({row.name}), "
                f"{states[row.name]}; {_fmt_duration(time.perf_counter() - t0)} elapsed{eta}"
            )
            try:
                code = 0
                if row_state(out / row.name, row.kind) != "done":
                    code = run_row(exp, row, out / row.name, say, layout)
                if code == 0 and row.test:
                    code = testing.run_tests(exp, row, out / row.name, say, source_commit(), machine())
            except KeyboardInterrupt:
                say(f"[{exp.name}] row {row.name} interrupted; rerun the same command to resume")
                raise
            if code != 0:
                say(f"[{exp.name}] row {row.name} stopped (exit code {code}); rerun the same command to resume")
                return 130 if code in (130, -2) else code
            paths = write_report(report_exp, out, say)
            say(f"[{exp.name}] row {row.name} done; report: {', '.join(str(p) for p in paths)}")
        if export_to is not None:
            for path in export_finished(exp, out, export_to):
                say(f"[{exp.name}] exported {path}")
        say(f"[{exp.name}] all {len(exp.rows)} rows done")
        return 0
    finally:
        log_file.close()
