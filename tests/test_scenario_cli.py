"""Every scenario runs through tgrf-train, tgrf-eval and tgrf-render (a tiny config, a few updates and steps)."""

import json
import pathlib

import pytest
from helpers import CompileCounter, write_catalogue_recordings

from tgrf_jax.cli import eval_main, render_main, train_main
from tgrf_jax.config import SCENARIOS, ConfigError, TrainConfig
from tgrf_jax.pedestrians import FOLDS

ROOT = pathlib.Path(__file__).resolve().parents[1]
TINY = str(ROOT / "configs" / "tiny.yaml")
# 4 humans out of 6 slots on average, 5-second episodes: short renders, and the variable crowd in every program.
SHORT = [
    "--set",
    "env.num_humans=6",
    "--set",
    "env.active_humans_min=2",
    "--set",
    "env.active_humans_max=6",
    "--set",
    "env.time_limit=5",
]


def _train_eval_render(name, tmp_path, capsys=None):
    run = tmp_path / name
    overrides = ["--set", f"env.scenario={name}", *SHORT]
    assert (
        train_main(
            [TINY, "--out-dir", str(run), "--set", "ppo.total_steps=256", "--set", "run.eval_episodes=4", *overrides]
        )
        == 0
    )
    assert f"scenario: {name}" in (run / "config.yaml").read_text()
    out = tmp_path / "eval.json"
    assert eval_main([str(run), "--episodes", "4", "--policy", "orca", "--out", str(out), "--all-metrics"]) == 0
    if capsys is not None:
        printed = capsys.readouterr().out
        assert "| SPL |" in printed and "min TTC (s)" in printed
    results = json.loads(out.read_text())["results"]
    assert set(results) == {"learned", "orca"} and results["orca"]["n_episodes"] == 4
    assert render_main([str(run), "--out", str(tmp_path / "render"), "--no-frames", "--no-mp4", "--dpi", "30"]) == 0
    summary = json.loads((tmp_path / "render" / "summary.json").read_text())
    assert summary["episodes"][0]["steps"] <= 20


def test_mix_runs_in_every_tool(tmp_path, capsys):
    """mix compiles every scenario's samplers into the trainer, the evaluation and the recorder."""
    _train_eval_render("mix", tmp_path, capsys)


@pytest.mark.slow
@pytest.mark.parametrize("name", SCENARIOS)
def test_every_scenario_runs_in_every_tool(name, tmp_path):
    _train_eval_render(name, tmp_path)


def test_suite_writes_its_table_and_thumbnails(tmp_path, capsys):
    out = tmp_path / "suite"
    argv = [TINY, "--suite", str(out), "--episodes", "2", "--policy", "straight", "--set", "env.time_limit=3"]
    assert eval_main(argv) == 0
    rows = (out / "suite.csv").read_text().splitlines()
    assert len(rows) == 1 + len(SCENARIOS) * 4 and rows[0].startswith("scenario,humans,policy,n_episodes")
    assert "spl" in rows[0] and "min_ttc" in rows[0]
    table = (out / "suite.md").read_text()
    assert "| robot_crowding | 30 | straight |" in table
    assert sorted(p.stem for p in (out / "thumbnails").glob("*.png")) == sorted(SCENARIOS)
    printed = capsys.readouterr().out
    assert f"[{len(SCENARIOS) * 4}/{len(SCENARIOS) * 4}]" in printed
    assert "suite: the real scenes (eth, hotel, univ, zara1, zara2) are left out" in printed
    assert "tgrf-data fetch eth-ucy" in printed
    assert printed.index("suite: compiling the evaluation program") < printed.index(f"[1/{len(SCENARIOS) * 4}]")
    # the suite is not overwritten without a word: the second run is refused before anything is played
    table = (out / "suite.md").read_text()
    with CompileCounter() as counter:
        assert eval_main(argv) == 2
    assert counter.compiles == 0 and (out / "suite.md").read_text() == table
    err = capsys.readouterr().err
    assert f"tgrf-eval: error: --suite {str(out)!r} holds an earlier suite (suite.md, suite.csv)" in err
    assert "--overwrite to replace it" in err


def test_suite_plays_the_real_scenes_when_the_recordings_are_there(tmp_path, monkeypatch, capsys):
    from tgrf_jax.cli.suite import RECORDED, run_suite
    from tgrf_jax.policies import baseline

    config = TrainConfig.from_yaml(TINY, ["env.time_limit=15"])
    with pytest.raises(ConfigError, match="the suite's real scenes need the ETH/UCY recordings; 6 are missing"):
        run_suite(config, {"straight": baseline("straight")}, tmp_path / "none", episodes=2, seed=0, real=True)
    write_catalogue_recordings(tmp_path / "data" / "pedestrians")
    monkeypatch.setenv("TGRF_JAX_DATA", str(tmp_path / "data"))
    out = tmp_path / "suite"
    policies = {"orca": baseline("orca")}
    rows = run_suite(config, policies, out, episodes=3, seed=0, sizes=(5,), scenarios=("circle_crossing",))
    real = [r for r in rows if r["humans"] == RECORDED]
    assert [(r["scenario"], r["policy"]) for r in real] == [(f, p) for f in FOLDS for p in policies]
    assert all(r["n_episodes"] == 3 for r in real)
    table = (out / "suite.md").read_text()
    assert "| zara2 | recorded | orca |" in table
    assert sorted(p.stem for p in (out / "thumbnails").glob("*.png")) == sorted(("circle_crossing", *FOLDS))
    # the same seed plays the same episodes: a second suite's real rows are equal
    again = run_suite(
        config,
        policies,
        tmp_path / "again",
        episodes=3,
        seed=0,
        sizes=(5,),
        scenarios=("circle_crossing",),
        thumbnails=False,
    )
    assert [r for r in again if r["humans"] == RECORDED] == real
    # a fold plays its own file only: its episodes differ from the next fold's
    assert len({r["min_dist_human"] for r in real}) > 1
    assert any(r["success_rate"] > 0 for r in real)


@pytest.mark.parametrize(
    "overrides",
    [
        ["env.scenario=replay", "env.human_policy=replay"],
        ["env.scenario=mix", "env.mix_scenarios=[replay,circle_crossing]", "env.human_policy=orca"],
    ],
    ids=["replay", "mix_with_replay"],
)
def test_suite_plays_policies_trained_among_recordings_on_the_synthetic_rows(overrides, tmp_path, capsys):
    from tgrf_jax.cli.suite import SYNTHETIC_HUMANS, run_suite, suite_env_config
    from tgrf_jax.policies import baseline

    config = TrainConfig.from_yaml(TINY, ["env.time_limit=3", "env.replay_files=[eth,hotel]", *overrides])
    env_config = suite_env_config(config.env, 5, ("circle_crossing",))
    assert env_config.replay_files is None and env_config.replay_weights is None
    expected = SYNTHETIC_HUMANS if config.env.human_policy == "replay" else config.env.human_policy
    assert env_config.human_policy == expected
    rows = run_suite(
        config,
        {"straight": baseline("straight")},
        tmp_path / "suite",
        episodes=2,
        seed=0,
        sizes=(5,),
        scenarios=("circle_crossing",),
        real=False,
        thumbnails=False,
    )
    assert [(r["scenario"], r["humans"]) for r in rows] == [("circle_crossing", 5)]
    printed = capsys.readouterr().out
    assert ("the synthetic rows' humans move as env.human_policy = 'orca'" in printed) == (
        config.env.human_policy == "replay"
    )
