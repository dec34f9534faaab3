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
SETS = [
    "--set",
    "ppo.num_shards=1",
    "--set",
    "ppo.update_epochs=1",
    "--set",
    "ppo.num_minibatches=1",
    "--set",
    "run.eval_episodes=4",
]
GRID = ["--grid", "reward.h_disc=1.0,2.5"]

# Runs a tool's main with a SIGKILL of its own process at one point: "first-save" (the initial checkpoint, before
# anything is on disk), "commit:N" (orbax has written checkpoint N into its temporary directory and is about to
# rename it into place), "final-evaluation", "before-provenance" (tgrf-reproduce: a row's sweep has written its
# evals.csv and exited, and the parent is about to record that in provenance.json) or "update:N" (tgrf-predictor:
# the chunk of updates that reaches update N has trained, before it is logged or checkpointed).
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
    from tgrf_jax.sweep.program import BatchedProgram
    from tgrf_jax.train.run_dir import SoloProgram
    SoloProgram.evaluate = BatchedProgram.evaluate = die
elif when == "before-provenance":
    from tgrf_jax.experiments import runner
    write = runner.write_atomic
    def record(path, text, *args, **kwargs):
        path = os.fspath(path)
        if os.path.basename(path) == "provenance.json" and os.path.isfile(os.path.join(os.path.dirname(path),
                                                                                        "evals.csv")):
            die()
        return write(path, text, *args, **kwargs)
    runner.write_atomic = record
elif when.startswith("update:"):
    from tgrf_jax.predictor import train as predictor_train
    chunk, stop = predictor_train.train_chunk, int(when.split(":")[1])
    def train_chunk(*args, **kwargs):
        state, loss = chunk(*args, **kwargs)
        if int(state.step) >= stop:
            die()
        return state, loss
    predictor_train.train_chunk = train_chunk
from tgrf_jax.cli import predictor_main, reproduce_main, sweep_main, train_main
sys.exit({"train": train_main, "sweep": sweep_main, "reproduce": reproduce_main,
          "predictor": predictor_main}[tool](argv))
"""


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    cache = tmp_path_factory.mktemp("xla_cache")
    return dict(
        os.environ,
        JAX_PLATFORMS="cpu",
        TGRF_JAX_COMPILE_CACHE=str(cache),
        JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
        PYTHONPATH=f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
    )


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
        reference / "runs" / names[0]
    )
    assert {p: p.stat().st_mtime_ns for p in kept} == kept  # an intact export is left alone


@pytest.mark.slow
def test_reproduce_killed_between_a_row_s_results_and_its_provenance_reruns_the_row(env, tmp_path):
    # The sweep child has finished (evals.csv whole) when its parent dies before recording the invocation's exit
    # code: the row must not count as done without its provenance, and a rerun at once completes it.
    import yaml

    from tgrf_jax.experiments import runner

    exp = tmp_path / "exp.yaml"
    exp.write_text(
        yaml.safe_dump(
            {
                "title": "kill",
                "layout": "table",
                "config": TINY,
                "seeds": 1,
                "grid": {"reward.scheme": ["tgrf"]},
                "set": {
                    "ppo.total_steps": 256,
                    "ppo.num_shards": 1,
                    "ppo.update_epochs": 1,
                    "ppo.num_minibatches": 1,
                    "run.eval_episodes": 4,
                },
                "rows": [{"name": "mlp", "label": "MLP"}],
            }
        )
    )
    out, row = tmp_path / "out", tmp_path / "out" / "mlp"
    argv = [str(exp), "--out", str(out)]

    tool(env, "reproduce", argv, kill_at="before-provenance")
    results = (row / "evals.csv").read_text()
    prov = json.loads((row / "provenance.json").read_text())
    assert [i["exit_code"] for i in prov["invocations"]] == [None]  # recorded as started, never as finished
    assert runner.row_state(row) == "damaged"
    assert "Rows finished: 0/1" in (out / "report.md").read_text()  # the report written before the row

    rerun = tool(env, "reproduce", argv)
    assert "provenance.json does not record the invocation that finished it" in rerun.stdout
    assert "trained to the end already" in rerun.stdout and "compiled a" not in rerun.stdout  # nothing retrained
    assert (row / "evals.csv").read_text() == results
    prov = json.loads((row / "provenance.json").read_text())
    assert [i["exit_code"] for i in prov["invocations"]] == [None, 0]
    assert runner.row_state(row) == "done" and "Rows finished: 1/1" in (out / "report.md").read_text()
    with open(out / "report.csv", newline="") as f:
        assert [r["seeds"] for r in csv.DictReader(f)] == ["1"]


def _predictor_dataset(path: pathlib.Path) -> pathlib.Path:
    """Straight-line walkers, all seen all the time: the smallest dataset tgrf-predictor trains on."""
    import numpy as np

    from tgrf_jax.predictor import data as data_lib

    rng = np.random.default_rng(0)
    b, t, n = 5, 40, 3
    times = np.arange(t, dtype=np.float32)[None, :, None, None] * 0.25
    human = rng.uniform(-3, 3, (b, 1, n, 2)) + rng.uniform(-1, 1, (b, 1, n, 2)) * times
    arrays = {
        "robot_pos": np.zeros((b, t, 2), np.float32),
        "human_pos": human.astype(np.float32),
        "visible": np.ones((b, t, n), bool),
        "seg": np.zeros((b, t, n), np.int16),
    }
    return data_lib.save_dataset(path, {"arrays": arrays, "config": {"crowd": "orca", "seed": 0}})


@pytest.mark.slow
def test_predictor_training_killed_mid_save_and_mid_training_ends_as_an_uninterrupted_one(env, tmp_path):
    import numpy as np

    dataset = _predictor_dataset(tmp_path / "d.npz")
    # dropout: its keys are part of the state that must resume; checkpoints every 4 updates, logs every 2
    opts = [
        "--dataset",
        str(dataset),
        "--updates",
        "8",
        "--batch-size",
        "4",
        "--log-every",
        "2",
        "--checkpoint-every",
        "4",
        "--decay-every",
        "2",
        "--eval-windows",
        "8",
        "--dropout",
        "0.1",
    ]
    reference, run = tmp_path / "reference", tmp_path / "run"
    tool(env, "predictor", ["train", *opts, "--run-dir", str(reference)])
    ckpts = run / "checkpoints"

    tool(env, "predictor", ["train", *opts, "--run-dir", str(run)], kill_at="commit:4")
    assert steps(ckpts) == [] and leftovers(ckpts)  # the half-committed step is not a step
    tool(env, "predictor", ["train", *opts, "--run-dir", str(run)], kill_at="update:6")  # from scratch, dies at 6
    assert steps(ckpts) == [4] and not leftovers(ckpts)
    out = tool(env, "predictor", ["train", *opts, "--run-dir", str(run)])
    assert f"resumed from {ckpts} at update 4" in out.stdout
    assert steps(ckpts) == [4, 8]

    with np.load(reference / "gst.npz") as a, np.load(run / "gst.npz") as b:
        names = [k for k in a.files if k != "meta"]
        assert names and sorted(names) == sorted(k for k in b.files if k != "meta")
        for k in names:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)  # bit-identical weights
    for step in (4, 8):
        from tgrf_jax.predictor import train as predictor_train
        from tgrf_jax.storage.checkpoint import Checkpointer

        template = predictor_train.init_state(predictor_train.TrainConfig(dropout=0.1))
        digests = [
            tree_digest(Checkpointer(d / "checkpoints", create=False).restore(template, step)) for d in (reference, run)
        ]
        assert digests[0] == digests[1], step
