"""kill -9 at every stage of a run and of a sweep, then --resume: before the first checkpoint, while a checkpoint is
being committed, during the final evaluation and after completion. Each chain ends with the files and the state of
an uninterrupted run (bit-identical parameters, the same eval.json, no duplicated CSV rows).

The kills are real SIGKILLs of tgrf-train / tgrf-sweep processes, sent by the process itself at the chosen point
(see KILLER), so each lands exactly there. The processes share one persistent compilation cache (a fresh directory
per module), so only the first compiles the training and evaluation programs; still, each chain is six processes
(1.5-2 minutes on 2 busy cores), so they are `slow`. The states these kills leave are also resumed in-process in the
default suite: tests/test_train_cli.py and tests/test_sweep.py (finished, evaluation missing, damaged checkpoint),
tests/test_lock.py (stopped before the first checkpoint).
"""

import csv
import json
import os
import pathlib
import signal
import subprocess
import sys

import pytest
from helpers import CompileCounter

from tgrf_jax.cli import sweep_main, train_main
from tgrf_jax.storage.checkpoint import tree_digest
from tgrf_jax.train.run_dir import restore_run

ROOT = pathlib.Path(__file__).resolve().parents[1]
TINY = str(ROOT / "configs" / "tiny.yaml")
# configs/tiny.yaml (12 updates, checkpoints every 4) on one env shard with one epoch of one minibatch: the
# smallest programs to compile
SETS = ["--set", "ppo.num_shards=1", "--set", "ppo.update_epochs=1", "--set", "ppo.num_minibatches=1",
        "--set", "run.eval_episodes=4"]
GRID = ["--grid", "reward.h_disc=1.0,2.5"]

# Runs a tool's main with a SIGKILL of its own process at one point: "first-save" (the initial checkpoint, before
# anything is on disk), "commit:N" (orbax has written checkpoint N into its temporary directory and is about to
# rename it into place) or "final-evaluation".
KILLER = r"""
import os, signal, sys
tool, when, argv = sys.argv[1], sys.argv[2], sys.argv[3:]

def die(*args, **kwargs):
    os.kill(os.getpid(), signal.SIGKILL)

if when == "first-save":
    from tgrf_jax.storage.checkpoint import Checkpointer
    Checkpointer.save = die
elif when.startswith("commit:"):
    step, rename = when.split(":")[1], os.rename
    def commit(src, dst, *args, **kwargs):
        dst = os.fspath(dst)
        if os.path.basename(dst) == step and os.path.basename(os.path.dirname(dst)) == "checkpoints":
            die()
        return rename(src, dst, *args, **kwargs)
    os.rename = commit
elif when == "final-evaluation":
    from tgrf_jax.sweep.program import SweepBatch
    from tgrf_jax.train.run_dir import SoloProgram
    SoloProgram.evaluate = SweepBatch.evaluate = die
from tgrf_jax.cli import sweep_main, train_main
sys.exit({"train": train_main, "sweep": sweep_main}[tool](argv))
"""


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    cache = tmp_path_factory.mktemp("xla_cache")
    return dict(os.environ, JAX_PLATFORMS="cpu", TGRF_JAX_COMPILE_CACHE=str(cache),
                JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
                PYTHONPATH=f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")


def tool(env, name: str, argv: list[str], kill_at: str | None = None) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-c", KILLER, name, kill_at or "never", *argv]
    out = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    if kill_at is None:
        assert out.returncode == 0, out.stderr[-3000:]
    else:
        assert out.returncode == -signal.SIGKILL, (kill_at, out.returncode, out.stderr[-3000:])
    return out


def steps(directory: pathlib.Path) -> list[int]:
    return sorted(int(p.name) for p in directory.iterdir() if p.name.isdigit()) if directory.is_dir() else []


def leftovers(directory: pathlib.Path) -> list[str]:
    return [p.name for p in directory.iterdir() if "tmp" in p.name] if directory.is_dir() else []


def updates(csv_path: pathlib.Path) -> list[int]:
    with open(csv_path, newline="") as f:
        return [int(row["update"]) for row in csv.DictReader(f)]


def evaluation(path: pathlib.Path) -> dict:
    payload = json.loads(path.read_text())
    payload.pop("run_dir")
    return payload


def state_digest(run_dir) -> str:
    return tree_digest(restore_run(run_dir)[1])


@pytest.mark.slow
def test_run_killed_at_every_stage_ends_as_an_uninterrupted_run(env, tmp_path):
    reference, run = tmp_path / "reference", tmp_path / "run"
    tool(env, "train", [TINY, *SETS, "--out-dir", str(reference)])
    ckpts = run / "checkpoints"

    tool(env, "train", [TINY, *SETS, "--out-dir", str(run)], kill_at="first-save")
    assert (run / "config.yaml").is_file() and steps(ckpts) == []

    tool(env, "train", ["--resume", str(run)], kill_at="commit:8")  # starts over, dies committing update 8
    assert steps(ckpts) == [0, 4] and leftovers(ckpts)  # the half-committed step is not a step
    assert updates(run / "metrics.csv") == [2, 4, 6, 8]

    tool(env, "train", ["--resume", str(run)], kill_at="final-evaluation")  # from 4: trains 5-12 again
    assert steps(ckpts) == [4, 8, 12] and not leftovers(ckpts)  # the writer removed orbax's leftover
    assert not (run / "eval.json").exists()

    out = tool(env, "train", ["--resume", str(run)])  # evaluates, trains nothing
    assert "trained to the end already" in out.stdout and "compiled a" not in out.stdout
    assert evaluation(run / "eval.json") == evaluation(reference / "eval.json")
    assert updates(run / "metrics.csv") == updates(reference / "metrics.csv") == [2, 4, 6, 8, 10, 12]
    assert state_digest(run) == state_digest(reference)

    # after completion: nothing to train or evaluate (nothing compiles); a missing plot is drawn again
    (run / "learning_curve.png").unlink()
    before = {p: p.stat().st_mtime_ns for p in [run / "eval.json", *ckpts.rglob("*")]}
    with CompileCounter() as counter:
        assert train_main(["--resume", str(run)]) == 0
    assert counter.compiles == 0
    assert (run / "learning_curve.png").stat().st_size > 0
    assert {p: p.stat().st_mtime_ns for p in before} == before


@pytest.mark.slow
def test_sweep_killed_at_every_stage_ends_as_an_uninterrupted_sweep(env, tmp_path):
    reference, sweep = tmp_path / "reference", tmp_path / "sweep"
    tool(env, "sweep", [TINY, *GRID, *SETS, "--out", str(reference)])
    ckpts = sweep / "checkpoints"
    names = sorted(p.name for p in (reference / "runs").iterdir())
    assert len(names) == 2

    tool(env, "sweep", [TINY, *GRID, *SETS, "--out", str(sweep)], kill_at="first-save")
    assert (sweep / "sweep.yaml").is_file() and steps(ckpts) == []

    tool(env, "sweep", ["--resume", str(sweep)], kill_at="commit:8")
    assert steps(ckpts) == [0, 4] and leftovers(ckpts)

    tool(env, "sweep", ["--resume", str(sweep)], kill_at="final-evaluation")
    assert steps(ckpts) == [4, 8, 12] and not leftovers(ckpts)
    assert not (sweep / "evals.csv").exists()

    out = tool(env, "sweep", ["--resume", str(sweep)])
    assert "trained to the end already" in out.stdout and "compiled a" not in out.stdout
    for name in names:
        assert evaluation(sweep / "runs" / name / "eval.json") == evaluation(reference / "runs" / name / "eval.json")
        assert updates(sweep / "runs" / name / "metrics.csv") == [2, 4, 6, 8, 10, 12]
        assert state_digest(sweep / "runs" / name) == state_digest(reference / "runs" / name)
    assert (sweep / "evals.csv").read_text() == (reference / "evals.csv").read_text()
    assert (sweep / "summary.md").read_text() == (reference / "summary.md").read_text()
    assert updates(sweep / "metrics.csv") == updates(reference / "metrics.csv")  # 2 runs x 6 chunks, once each

    # after completion: evals.csv, summaries, plots and the runs' final checkpoints come back; nothing compiles
    for name in ("evals.csv", "summary.csv", "summary.md", "learning_curves.png"):
        (sweep / name).unlink()
    export = sweep / "runs" / names[0] / "checkpoints"
    for step in steps(export):
        subprocess.run(["rm", "-r", str(export / str(step))], check=True)
    kept = {p: p.stat().st_mtime_ns for p in (sweep / "runs" / names[1] / "checkpoints").rglob("*")}
    with CompileCounter() as counter:
        assert sweep_main(["--resume", str(sweep)]) == 0
    assert counter.compiles == 0
    assert (sweep / "evals.csv").read_text() == (reference / "evals.csv").read_text()
    assert (sweep / "summary.md").read_text() == (reference / "summary.md").read_text()
    assert (sweep / "learning_curves.png").stat().st_size > 0
    assert steps(export) == [12] and state_digest(sweep / "runs" / names[0]) == state_digest(
        reference / "runs" / names[0])
    assert {p: p.stat().st_mtime_ns for p in kept} == kept  # an intact export is left alone
