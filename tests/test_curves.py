"""Learning curves under test conditions (run.eval_every): rows, resume, tgrf-eval agreement, sweeps."""

import csv
import json
import pathlib

import jax
import numpy as np
import pytest

from tgrf_jax.cli import eval_main
from tgrf_jax.config import TrainConfig
from tgrf_jax.train.curves import CURVE_METRICS
from tgrf_jax.train.run_dir import train_run

ROOT = pathlib.Path(__file__).resolve().parents[1]
TINY = str(ROOT / "configs" / "tiny.yaml")
# 8 test episodes: the evaluation program of the other tiny runs (tests/test_train_cli.py, tests/test_sweep.py,
# tests/test_pretrained.py), compiled once per test session
CURVE_SETS = ["run.eval_every=4", "run.curve_episodes=8", "run.eval_episodes=0"]


def read(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def curve_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("curve") / "run"
    return train_run(TrainConfig.from_yaml(TINY, CURVE_SETS), out, log=lambda m: None)


def test_test_episodes_every_eval_every_updates(curve_run):
    rows = read(curve_run.run_dir / "eval_curve.csv")
    assert [int(r["update"]) for r in rows] == [4, 8, 12]
    assert [int(r["env_steps"]) for r in rows] == [512, 1024, 1536]
    for r in rows:
        assert int(r["episodes"]) == 8 and 0.0 <= float(r["success_rate"]) <= 1.0
        rates = sum(float(r[k]) for k in ("success_rate", "collision_rate", "timeout_rate"))
        assert rates == pytest.approx(1.0)
    assert (curve_run.run_dir / "eval_curve.png").stat().st_size > 10_000


def test_periodic_evaluation_leaves_training_unchanged(curve_run, tmp_path):
    # The evaluations cut the chunk plan at their period and draw their own episodes: the trained state must be
    # the one a run without them reaches, bit for bit.
    sets = [s for s in CURVE_SETS if not s.startswith("run.eval_every")] + ["run.eval_every=0"]
    plain = train_run(TrainConfig.from_yaml(TINY, sets), tmp_path / "plain", log=lambda m: None)
    assert not (tmp_path / "plain" / "eval_curve.csv").exists()
    got, want = jax.tree_util.tree_leaves(curve_run.state), jax.tree_util.tree_leaves(plain.state)
    assert len(got) == len(want)
    for a, b in zip(got, want):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_curve_point_equals_tgrf_eval_of_the_same_checkpoint(curve_run, tmp_path):
    out = tmp_path / "eval.json"
    assert eval_main([str(curve_run.run_dir), "--step", "8", "--episodes", "8", "--seed", "0", "--out", str(out)]) == 0
    evaluated = json.loads(out.read_text())["results"]["learned"]
    row = next(r for r in read(curve_run.run_dir / "eval_curve.csv") if r["update"] == "8")
    for k in CURVE_METRICS:
        expected = evaluated[k]
        assert (row[k] == "nan") if expected is None else float(row[k]) == pytest.approx(expected, rel=1e-12), k


def test_resumed_run_has_the_same_curve(curve_run, tmp_path):
    out = tmp_path / "run"
    config = TrainConfig.from_yaml(TINY, CURVE_SETS)
    train_run(config, out, log=lambda m: None, stop_after_updates=6)
    assert [r["update"] for r in read(out / "eval_curve.csv")] == ["4"]
    train_run(config, out, resume=True, log=lambda m: None)
    assert read(out / "eval_curve.csv") == read(curve_run.run_dir / "eval_curve.csv")


def test_sweep_writes_curves_of_every_run(tmp_path):
    from tgrf_jax.sweep import SweepSpec, run_sweep

    spec = SweepSpec.create(TINY, ["reward.scheme=tgrf,crowdnav_pp"], 1, CURVE_SETS)
    run_sweep(spec, tmp_path / "sweep", log=lambda m: None)
    rows = read(tmp_path / "sweep" / "eval_curves.csv")
    assert sorted((r["reward.scheme"], r["update"]) for r in rows) == sorted(
        (s, u) for s in ("tgrf", "crowdnav_pp") for u in ("4", "8", "12")
    )
    for run in {r["run"] for r in rows}:
        assert len(read(tmp_path / "sweep" / "runs" / run / "eval_curve.csv")) == 3
    assert (tmp_path / "sweep" / "eval_curves.png").stat().st_size > 10_000


def test_a_run_compiles_its_training_program_once(tmp_path, monkeypatch):
    # log, checkpoint and evaluation periods that all differ cut the run into chunks of 1, 2 and 3 updates; the
    # update count is traced, so the update is traced (and its program compiled) once for all of them
    from tgrf_jax.train.ppo import Trainer

    traces = []
    real_update = Trainer.update
    monkeypatch.setattr(Trainer, "update", lambda self, ts: traces.append(1) or real_update(self, ts))
    sets = [
        "run.log_every=2",
        "run.checkpoint_every=3",
        "run.eval_every=5",
        "run.curve_episodes=8",
        "run.eval_episodes=0",
    ]
    result = train_run(TrainConfig.from_yaml(TINY, sets), tmp_path / "run", log=lambda m: None)
    assert result.updates == 12
    assert len(read(tmp_path / "run" / "metrics.csv")) == 9  # chunks ending at 2, 3, 4, 5, 6, 8, 9, 10, 12
    assert result.compiled_chunks == 1
    assert len(traces) == 1
