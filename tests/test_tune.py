"""The tuner's pieces: the search space, the objective and the exploit-and-explore step."""

from __future__ import annotations

import json
import math
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

from tgrf_jax.config import ConfigError, TrainConfig
from tgrf_jax.train.ppo import hparams_from_config
from tgrf_jax.tune import exploit_explore, num_replaced, parse_objective, parse_space
from tgrf_jax.tune.pbt import get_values, select_donors
from tgrf_jax.tune.run import run_tune
from tgrf_jax.tune.spec import TuneSpec, load_tune

# --------------------------------------------------------------------------------------------- space


def test_space_parses_linear_and_log_dims():
    dims = parse_space(["reward.h_disc=0.5:5:log", "ppo.ent_coef=0:0.05"])
    assert [(d.name, d.low, d.high, d.log) for d in dims] == [
        ("reward.h_disc", 0.5, 5.0, True),
        ("ppo.ent_coef", 0.0, 0.05, False),
    ]


@pytest.mark.parametrize(
    "item, message",
    [
        ("reward.h_dsic=0.5:5", "did you mean 'reward.h_disc'"),
        ("env.num_humans=5:10", "cannot be searched"),
        ("reward.scheme=0:1", "cannot be searched"),
        ("env.active_humans_max=5:20", "whole-number count"),
        ("env.detection_latency=0:3", "whole-number count"),
        ("env.scenario_weights=0:1", "one weight per entry"),
        ("reward.h_disc=5:0.5", "lower bound must be below"),
        ("reward.h_disc=1:1", "lower bound must be below"),
        ("reward.h_disc=0:5:log", "positive lower bound"),
        ("reward.h_disc=0.5:5:ln", "LO:HI:log"),
        ("reward.h_disc=a:5", "not a number"),
        ("reward.h_disc=0.5:inf", "finite"),
        ("reward.sigma_disc=-1:1", "reward.sigma_disc"),  # the config's own range check
        ("reward.h_disc", "FIELD=LO:HI"),
    ],
)
def test_space_refuses_bad_items(item, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(")):
        parse_space([item])


def test_space_refuses_a_field_twice():
    with pytest.raises(ConfigError, match="given twice"):
        parse_space(["reward.h_disc=0.5:5", "reward.h_disc=1:2"])


# --------------------------------------------------------------------------------------------- objective


def test_objective_reads_short_names_with_their_scale():
    objective = parse_objective("0.4 * success + 0.3 * spl + 0.3 * psc")
    result = {"success_rate": 0.9, "spl": 0.8, "personal_space_compliance": 95.0}
    assert objective.metrics == ("success", "spl", "psc")
    assert objective.score(result) == pytest.approx(0.4 * 0.9 + 0.3 * 0.8 + 0.3 * 0.95)


def test_objective_functions_and_full_field_names():
    objective = parse_objective("min(success_rate, 0.5) - abs(-collision) / 2")
    assert objective.score({"success_rate": 0.9, "collision_rate": 0.2}) == pytest.approx(0.5 - 0.1)


def test_objective_undefined_metric_ranks_last():
    objective = parse_objective("success - 0.01 * nav_time")
    assert objective.score({"success_rate": 0.0, "nav_time": None}) == -math.inf
    assert objective.score({"success_rate": 0.0, "nav_time": float("nan")}) == -math.inf


@pytest.mark.parametrize(
    "text, message",
    [
        ("success - 0.5 * colision", "unknown metric 'colision'.*did you mean 'collision'"),
        ("success -", "syntax error at its end"),
        ("succ ess", "syntax error at column 6"),
        ("__import__('os').system('true')", "not allowed"),
        ("success ** 2", "not allowed"),
        ("success if spl else 0", "not allowed"),
        ("3.5", "reads no metric"),
        ("", "empty"),
    ],
)
def test_objective_refuses_bad_expressions(text, message):
    with pytest.raises(ConfigError, match=message):
        parse_objective(text)


# --------------------------------------------------------------------------------------------- exploit / explore


@struct.dataclass
class _State:  # the fields of TrainState that the step reads or must leave alone
    params: dict
    opt_state: jnp.ndarray
    return_stats: jnp.ndarray
    hparams: object
    env_state: jnp.ndarray
    key: jnp.ndarray


def _population(n: int):
    hp = hparams_from_config(TrainConfig())
    hparams = jax.tree.map(lambda x: jnp.stack([x] * n), hp)
    ids = jnp.arange(n, dtype=jnp.float32)
    return _State(
        params={"w": ids[:, None] * jnp.ones((n, 3))},
        opt_state=ids * 10,
        return_stats=ids * 100,
        hparams=hparams.replace(lr=(ids + 1) * 1e-4),
        env_state=ids * 1000,
        key=jnp.stack([jax.random.PRNGKey(i) for i in range(n)]),
    )


def test_num_replaced():
    assert [num_replaced(p, 0.25) for p in (2, 4, 8, 16, 3)] == [1, 1, 2, 4, 1]


def test_select_donors_replaces_the_worst_with_the_best():
    scores = jnp.array([0.5, 0.1, 0.9, 0.3, 0.8, 0.2, 0.7, 0.4])
    for seed in range(20):
        donor = np.asarray(select_donors(scores, jax.random.PRNGKey(seed), 2))
        worst = {1, 5}
        for i in range(8):
            if i in worst:
                assert donor[i] in {2, 4}
            else:
                assert donor[i] == i


def test_exploit_explore_copies_learning_state_and_keeps_the_episodes():
    dims = parse_space(["ppo.lr=1e-5:1e-3:log", "reward.h_disc=0.5:5"])
    state = _population(8)
    scores = jnp.array([0.5, 0.1, 0.9, 0.3, 0.8, 0.2, 0.7, 0.4])
    step = jax.jit(lambda s, sc, k: exploit_explore(s, sc, k, dims, 0.25, 0.25))
    new, record = step(state, scores, jax.random.PRNGKey(3))
    donor = np.asarray(record.donor)
    for i in range(8):
        d = donor[i]
        np.testing.assert_array_equal(new.params["w"][i], state.params["w"][d])
        assert float(new.opt_state[i]) == float(state.opt_state[d])
        assert float(new.return_stats[i]) == float(state.return_stats[d])
        assert float(new.env_state[i]) == float(state.env_state[i])  # its own episodes
        np.testing.assert_array_equal(new.key[i], state.key[i])
    values = np.asarray(record.values)
    np.testing.assert_array_equal(values, np.asarray(get_values(new.hparams, dims)))
    old = np.asarray(get_values(state.hparams, dims))
    kept = donor == np.arange(8)
    np.testing.assert_array_equal(values[kept], old[kept])
    for i in np.flatnonzero(~kept):
        for j, d in enumerate(dims):
            assert d.low <= values[i, j] <= d.high
            donor_value = old[donor[i], j]
            perturbed = [np.clip(donor_value * f, d.low, d.high) for f in (0.8, 1.25)]
            # perturbed by a factor, or resampled within the bounds
            assert any(np.isclose(values[i, j], p, rtol=1e-6) for p in perturbed) or d.low <= values[i, j] <= d.high
    # deterministic: the same key gives the same step
    again, record2 = step(state, scores, jax.random.PRNGKey(3))
    np.testing.assert_array_equal(np.asarray(record2.donor), donor)
    np.testing.assert_array_equal(np.asarray(record2.values), values)


def test_explore_perturbs_by_the_stated_factors_without_resampling():
    dims = parse_space(["ppo.lr=1e-6:1:log"])
    state = _population(4)
    new, record = exploit_explore(state, jnp.array([3.0, 2.0, 1.0, 0.0]), jax.random.PRNGKey(0), dims, 0.25, 0.0)
    donor, values = np.asarray(record.donor), np.asarray(record.values)[:, 0]
    assert donor[3] == 0 and list(donor[:3]) == [0, 1, 2]
    ratio = values[3] / float(state.hparams.lr[0])
    assert np.isclose(ratio, 0.8, rtol=1e-6) or np.isclose(ratio, 1.25, rtol=1e-6)


# --------------------------------------------------------------------------------------------- the tune


TINY = str(pathlib.Path(__file__).resolve().parents[1] / "configs" / "tiny.yaml")
SPACE = ["reward.h_disc=0.5:5:log", "ppo.lr=1e-4:3e-3:log"]


def _spec(**kw):
    kw = {"population": 4, "interval": 4, "objective_episodes": 8, "final_episodes": 8, **kw}
    return TuneSpec.create(TINY, SPACE, **kw)


@pytest.mark.parametrize(
    "kw, message",
    [
        ({"population": 1}, "--population 1"),
        ({"population": 3, "fraction": 0.25}, "replaces no member"),
        ({"interval": 12}, "--interval 12: allowed 1 .. 11"),
        ({"interval": 0}, "--interval 0"),
        ({"fraction": 0.75}, "--fraction"),
        ({"resample_prob": 1.5}, "--resample"),
        ({"objective": "succes"}, "unknown metric"),
        ({"objective_episodes": 0}, "--objective-episodes"),
    ],
)
def test_tune_spec_refuses_bad_settings(kw, message):
    with pytest.raises(ConfigError, match=message):
        _spec(**kw)


def test_tune_spec_round_trips_and_draws_members_within_bounds():
    spec = _spec()
    assert TuneSpec.from_dict(spec.to_dict()) == spec
    members = spec.members()
    assert [m.seed for m in members] == [0, 1, 2, 3]
    for m in members:
        assert 0.5 <= m.values["reward.h_disc"] <= 5 and 1e-4 <= m.values["ppo.lr"] <= 3e-3
        assert m.config.reward.h_disc == pytest.approx(m.values["reward.h_disc"])


def _tune(tmp_path, name, layout="batched", **kw):
    return run_tune(_spec(layout=layout), tmp_path / name, log=lambda line: None, **kw)


def test_tune_spec_records_its_layout():
    spec = _spec(layout="sequential")
    assert TuneSpec.from_dict(spec.to_dict()).layout == "sequential" and "sequential layout" in spec.describe()
    recorded = spec.to_dict()
    del recorded["layout"]  # a tune.yaml written before the layout was recorded ran batched
    assert TuneSpec.from_dict(recorded).layout == "batched"
    with pytest.raises(ConfigError, match="--layout 'vmapped': allowed batched, sequential"):
        _spec(layout="vmapped")


@pytest.mark.parametrize("layout", ["batched", "sequential"])
def test_tune_writes_its_outputs_and_resumes_bit_identically(tmp_path, layout):
    full = _tune(tmp_path, "full", layout)
    assert full.best is not None and np.isfinite(full.best_objective)
    root = tmp_path / "full"
    for name in ("tune.md", "lineage.csv", "schedule.csv", "lineage.png", "schedule.png", "tune.yaml"):
        assert (root / name).is_file(), name
    lineage = (root / "lineage.csv").read_text().splitlines()
    assert len(lineage) == 1 + 2 * 4  # header, 2 steps x 4 members (updates 4 and 8 of 12)
    best = root / "runs" / f"m{full.best:03d}"
    assert (best / "eval.json").is_file() and (best / "checkpoints").is_dir()

    # interrupted after update 6, then resumed: the same lineage and the same final states
    _tune(tmp_path, "cut", layout, stop_after_updates=6)
    assert len((tmp_path / "cut" / "lineage.csv").read_text().splitlines()) == 1 + 4
    resumed = run_tune(None, tmp_path / "cut", resume=True, log=lambda line: None)
    assert resumed.best == full.best and resumed.best_objective == full.best_objective
    assert (tmp_path / "cut" / "lineage.csv").read_text() == (root / "lineage.csv").read_text()

    def final_results(directory):
        return [json.loads((d / "eval.json").read_text())["results"] for d in sorted((directory / "runs").iterdir())]

    assert final_results(tmp_path / "cut") == final_results(root)
    assert (tmp_path / "cut" / "schedule.csv").read_text() == (root / "schedule.csv").read_text()


def test_a_resumed_tune_switches_its_layout_and_records_it(tmp_path):
    lines = []
    run_tune(_spec(), tmp_path / "t", log=lambda line: None, stop_after_updates=6)
    result = run_tune(None, tmp_path / "t", resume=True, layout="sequential", log=lines.append)
    assert result.best is not None and np.isfinite(result.best_objective)
    assert "tune continues in the sequential layout (was batched)" in lines
    assert load_tune(tmp_path / "t").layout == "sequential"
    lineage = (tmp_path / "t" / "lineage.csv").read_text().splitlines()
    assert len(lineage) == 1 + 2 * 4 and {row.split(",")[0] for row in lineage[1:]} == {"4", "8"}
    with pytest.raises(ConfigError, match="switches the layout of a resumed tune"):
        run_tune(_spec(), tmp_path / "new", layout="sequential", log=lambda line: None)


def test_tune_refuses_an_existing_tune_directory(tmp_path):
    (tmp_path / "t").mkdir()
    (tmp_path / "t" / "tune.yaml").write_text("x: 1\n")
    with pytest.raises(ConfigError, match="already holds a tune"):
        run_tune(_spec(), tmp_path / "t", log=lambda line: None)
