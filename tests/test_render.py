"""Episode recording, frame drawing, GIF/PNG/MP4 output and the tgrf-render command."""

import json
import pathlib

import jax
import numpy as np
import pytest
from helpers import CompileCounter
from matplotlib.colors import to_rgba
from PIL import Image

from tgrf_jax import CrowdNavEnv, render
from tgrf_jax.cli.render import main as render_main
from tgrf_jax.env import OUTCOME_NAMES
from tgrf_jax.evaluate import evaluate
from tgrf_jax.policies import StraightPolicy

ROOT = pathlib.Path(__file__).resolve().parents[1]

# A small scene with a short sensor range, so frames mix visible and unseen humans.
ENV_CONFIG = {"num_humans": 5, "human_policy": "social_force", "predictor": "const_vel", "sensor_range": 2.0,
              "time_limit": 8.0}
CLI_SETS = [f"env.{k}={v}" for k, v in ENV_CONFIG.items()]  # the same env, so the CLI test reuses the compiled scan
N_EPISODES = 2


@pytest.fixture(scope="module")
def env():
    return CrowdNavEnv(ENV_CONFIG, "tgrf")


@pytest.fixture(scope="module")
def episodes(env):
    return render.record_episodes(env, StraightPolicy(), render.eval_key(0), N_EPISODES, label="straight")


def test_record_shapes_and_terms(episodes, env):
    assert len(episodes) == N_EPISODES
    k = env.config.pred_horizon
    for ep in episodes:
        t, n = ep.steps, env.num_humans
        assert 1 <= t <= ep.max_steps == 32
        assert ep.robot_pos.shape == (t + 1, 2) and ep.human_pos.shape == (t + 1, n, 2)
        assert ep.visible.shape == ep.obs_mask.shape == (t + 1, n) and ep.visible.dtype == bool
        assert ep.pred_pos.shape == (t + 1, n, k, 2)
        assert ep.reward.shape == ep.outcomes.shape == (t,)
        # The episode ends exactly on its first non-running step.
        assert np.all(ep.outcomes[:-1] == 0) and ep.outcome in OUTCOME_NAMES[1:]
        # The reward terms add up to the env's reward.
        total = sum(ep.terms[name] for name in ("goal", "collision", "disc", "pot", "pred", "kinematic"))
        np.testing.assert_allclose(total, ep.reward, atol=1e-5)
        assert np.all(np.isfinite(ep.robot_pos)) and np.all(np.isfinite(ep.human_pos))


def test_record_replays_the_evaluation(episodes, env):
    """record_episodes(eval_key(s)) replays evaluate(key(s)): the same outcomes, times, paths and returns."""
    result = evaluate(env, StraightPolicy(), jax.random.key(0), N_EPISODES)
    outcome = np.array([ep.outcome for ep in episodes])
    success = outcome == "success"
    assert result.success_rate == pytest.approx(success.mean())
    assert result.collision_rate == pytest.approx(np.mean(outcome == "collision"))
    assert result.mean_return == pytest.approx(np.mean([ep.ret for ep in episodes]), rel=1e-5, abs=1e-4)
    if success.any():
        assert result.nav_time == pytest.approx(np.mean([ep.duration for ep in episodes if ep.outcome == "success"]))
        paths = [ep.summary()["path_length"] for ep in episodes if ep.outcome == "success"]
        assert result.path_length == pytest.approx(np.mean(paths), rel=1e-4)
    itr_disc = np.mean([np.mean(ep.dmin()[1:] < ep.d_disc) for ep in episodes])
    assert result.itr_disc == pytest.approx(100 * itr_disc, abs=1e-3)


def test_visibility_matches_the_env(episodes, env):
    """The visible/unseen split is the env's: the edge-to-edge range rule, and exactly the observed humans."""
    p = env.default_params
    seen_both = False
    for ep in episodes:
        edge = (np.linalg.norm(ep.human_pos - ep.robot_pos[:, None], axis=-1) - float(p.robot_radius)
                - ep.human_radius)
        np.testing.assert_array_equal(ep.visible, edge <= float(p.sensor_range))
        for t in range(ep.steps + 1):
            vis = ep.visible[t]
            seen_both |= bool(vis.any() and (~vis).any())
            assert ep.obs_mask[t].sum() == vis.sum()
            # The observation's rows are the visible humans (visible first, sorted by distance).
            observed = ep.obs_human_pos[t][ep.obs_mask[t]]
            expected = ep.human_pos[t][vis]
            order = lambda a: a[np.lexsort(a.T)]  # noqa: E731
            np.testing.assert_allclose(order(observed), order(expected), atol=1e-4)
            assert np.all(ep.obs_mask[t][: vis.sum()])
    assert seen_both, "the test scene should show visible and unseen humans in the same frame"


def test_frame_artists_follow_the_state(episodes):
    """Humans are coloured by the env's mask, predictions drawn for visible humans only, circles on the robot."""
    ep = episodes[0]
    fig, ax = render.new_figure()
    painter = render.FramePainter(ax, ep)
    k = ep.pred_pos.shape[2]
    for t in range(ep.steps + 1):
        painter.update(t)
        faces = painter.humans.get_facecolor()
        expected = np.array([to_rgba(render.VISIBLE_COLOR if v else render.UNSEEN_COLOR) for v in ep.visible[t]])
        np.testing.assert_allclose(faces, expected)
        np.testing.assert_allclose(painter.humans.get_offsets(), ep.human_pos[t])
        assert len(painter.pred_dots.get_offsets()) == ep.visible[t].sum() * k
        np.testing.assert_allclose(painter.robot.center, ep.robot_pos[t])
        np.testing.assert_allclose(painter.sensor_edge.center, ep.robot_pos[t])
        assert painter.sensor_edge.radius == pytest.approx(ep.robot_radius + ep.sensor_range)
        assert painter.danger_edge.radius == pytest.approx(ep.robot_radius + ep.d_disc)
        in_danger = ep.dmin()[t] < ep.d_disc
        assert painter.danger_fill.get_alpha() == (0.3 if in_danger else 0.07)
        assert painter.banner.get_visible() == (t == ep.steps)
    rgb = painter.render_rgb()
    assert rgb.shape == (720, 648, 3) and rgb.dtype == np.uint8
    # The blitted frame equals a full redraw.
    fig.canvas.draw()
    full = np.asarray(fig.canvas.buffer_rgba())[..., :3]
    assert np.mean(np.abs(full.astype(int) - rgb.astype(int)) > 8) < 0.002


def test_save_episode_writes_frames_and_gif(episodes, tmp_path):
    ep = episodes[0]
    paths = render.save_episode(ep, tmp_path, fps=10, dpi=60)
    frames = sorted((tmp_path / "ep000").glob("frame_*.png"))
    assert [p.name for p in frames] == [f"frame_{t:04d}.png" for t in range(ep.steps + 1)]
    assert frames == sorted(paths["frames"])
    sizes = {Image.open(p).size for p in frames}
    assert sizes == {(432, 480)}  # 7.2 x 8 in at 60 dpi
    assert all(p.stat().st_size > 5_000 for p in frames)
    first, last = (np.asarray(Image.open(frames[i]).convert("RGB")) for i in (0, -1))
    assert np.mean(first != last) > 0.005  # the scene moved
    gif = Image.open(paths["gif"])
    assert gif.n_frames == ep.steps + 1 and gif.size == (432, 480)
    assert paths["gif"].stat().st_size > 20_000
    assert gif.info["duration"] == 100
    if render.ffmpeg_path():
        assert paths["mp4"].is_file() and paths["mp4"].stat().st_size > 5_000
    else:
        assert paths["mp4"] is None and not (tmp_path / "ep000.mp4").exists()
        with pytest.raises(RuntimeError, match="ffmpeg"):
            render.save_episode(ep, tmp_path / "x", mp4=True)


def test_stride_keeps_the_outcome_frame(episodes, tmp_path):
    ep = episodes[1]
    paths = render.save_episode(ep, tmp_path, name="s", stride=7, gif=False, mp4=False, dpi=30)
    got = [int(p.stem.split("_")[1]) for p in paths["frames"]]
    assert got[0] == 0 and got[-1] == ep.steps and all(b - a <= 7 for a, b in zip(got, got[1:]))
    assert paths["gif"] is None
    with pytest.raises(ValueError, match="stride"):
        render.save_episode(ep, tmp_path, stride=0)


def test_inline_animation_and_reward_plot(episodes):
    ep = episodes[0]
    html = render.to_jshtml(ep, stride=4, dpi=30)
    assert "<script" in html and html.count("data:image/png;base64") == len(range(0, ep.steps + 1, 4)) + (
        ep.steps % 4 != 0)
    fig = render.plot_reward_terms(ep)
    assert len(fig.axes) == 2
    assert render.plot_frame(ep).axes[0].get_title() == "straight: episode 0"


# ------------------------------------------------------------------------------------------------ tgrf-render


def test_cli_renders_baseline(tmp_path, capsys, episodes):
    out = tmp_path / "out"
    args = ["--policy", "straight", "--episodes", str(N_EPISODES), "--out", str(out), "--dpi", "40", "--stride", "2"]
    assert render_main(args + sum((["--set", s] for s in CLI_SETS), [])) == 0
    text = capsys.readouterr().out
    assert "straight: recording 2 episode(s)" in text and "wrote " in text and str(out) in text
    summary = json.loads((out / "summary.json").read_text())
    assert [e["episode"] for e in summary["episodes"]] == [0, 1]
    for row, ep in zip(summary["episodes"], episodes):
        assert row["outcome"] == ep.outcome and row["steps"] == ep.steps  # same seed: the same episodes
        assert pathlib.Path(row["gif"]).is_file()
        assert len(list(pathlib.Path(row["frame_dir"]).glob("frame_*.png"))) == row["frames"] == ep.steps // 2 + 1 + (
            ep.steps % 2)


def test_cli_records_long_renders_in_batches(tmp_path, capsys, monkeypatch, env, episodes):
    from tgrf_jax.render import record

    monkeypatch.setattr(record, "RECORD_STEPS", 64)  # two 32-step episodes per batch (the scan compiled already)
    out = tmp_path / "out"
    args = ["--policy", "straight", "--episodes", "4", "--out", str(out), "--no-frames", "--dpi", "20"]
    assert render_main(args + sum((["--set", s] for s in CLI_SETS), [])) == 0
    text = capsys.readouterr().out
    assert "straight: recording 2 episode(s) (0-1 of 4, batch 1/2)" in text
    assert "straight: recording 2 episode(s) (2-3 of 4, batch 2/2)" in text
    summary = json.loads((out / "summary.json").read_text())
    assert [e["episode"] for e in summary["episodes"]] == [0, 1, 2, 3]
    assert all((out / "straight" / f"ep{i:03d}.gif").is_file() for i in range(4))
    # batch b is played with evaluate's key of batch b
    second = render.record_episodes(env, StraightPolicy(), render.eval_key(0, 1), 2)
    assert [(e["steps"], e["outcome"]) for e in summary["episodes"]] == [
        (ep.steps, ep.outcome) for ep in [*episodes, *second]]


def test_cli_renders_run_dir(tmp_path, capsys):
    from tgrf_jax.config import TrainConfig
    from tgrf_jax.train.run_dir import train_run

    config = TrainConfig.from_yaml(ROOT / "configs" / "tiny.yaml", ["env.time_limit=5"])
    run_dir = tmp_path / "run"
    train_run(config, run_dir, log=lambda m: None, stop_after_updates=0)  # config + the initial checkpoint
    out = tmp_path / "out"
    assert render_main([str(run_dir), "--out", str(out), "--no-frames", "--dpi", "30"]) == 0
    text = capsys.readouterr().out
    assert "learned (update 0): recording 1 episode(s)" in text
    summary = json.loads((out / "summary.json").read_text())
    assert summary["episodes"][0]["policy"] == "learned" and summary["episodes"][0]["frames"] == 0
    assert (out / "learned" / "ep000.gif").is_file() and not (out / "learned" / "ep000").exists()


@pytest.mark.parametrize("args, message", [
    (["{tmp}/nope"], "'{tmp}/nope' does not exist (expected a tgrf-train run directory or a YAML config)"),
    (["{tmp}"], "is not a tgrf-train run directory"),
    (["{tmp}/cfg.yaml"], "is a config file: name the robot with --policy straight|orca"),
    ([], "give a RUN_DIR, --pretrained NAME or --policy straight|orca"),
    (["--policy", "orca", "--set", "env.num_human=3"], "unknown config key 'env.num_human' (did you mean 'num_humans'?)"),
    (["--policy", "orca", "--set", "env.human_policy=teleport"],
     "env.human_policy = 'teleport' is not allowed; allowed: one of 'orca', 'social_force'"),
    (["--policy", "orca", "--set", "reward.sigma_disc=0"], "reward.sigma_disc = 0.0 is out of range"),
    (["--policy", "orca", "--set", "ppo.lr=1"], "only those can be overridden, not ['ppo.lr=1']"),
    (["--policy", "orca", "--episodes", "0"], "--episodes = 0 is out of range; allowed: 1 .. 10,000,000"),
    (["--policy", "orca", "--fps", "0"], "--fps = 0.0 must be > 0"),
    (["--policy", "orca", "--step", "3"], "--step selects a checkpoint of a RUN_DIR"),
    (["--policy", "orca", "--out", "{tmp}/cfg.yaml"], "exists and is not a directory"),
])
def test_cli_errors_before_compiling(tmp_path, capsys, args, message):
    (tmp_path / "cfg.yaml").write_text("env:\n  num_humans: 3\n")
    fmt = lambda s: s.replace("{tmp}", str(tmp_path))  # noqa: E731
    args = [fmt(a) for a in args]
    if "--out" not in args:
        args += ["--out", str(tmp_path / "out")]
    with CompileCounter() as counter:
        assert render_main(args) == 2
    assert counter.traces == counter.compiles == 0  # rejected before anything was traced or compiled
    err = capsys.readouterr().err
    assert err.startswith("tgrf-render: error: ") and fmt(message) in err
    assert not (tmp_path / "out").exists()


def test_cli_bad_policy_name(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        render_main(["--policy", "random", "--out", str(tmp_path)])
    assert exc.value.code == 2
    assert "invalid choice: 'random' (choose from straight, orca)" in capsys.readouterr().err.replace("'straight'", "straight").replace("'orca'", "orca")


def test_cli_run_dir_overrides_limited(tmp_path, capsys):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "config.yaml").write_text((ROOT / "configs" / "tiny.yaml").read_text())
    assert render_main([str(run_dir), "--out", str(tmp_path / "o"), "--set", "ppo.lr=0.1"]) == 2
    assert "with a RUN_DIR only env.* and reward.* can be overridden" in capsys.readouterr().err
    # A run dir without checkpoints fails clearly (after the config checks).
    assert render_main([str(run_dir), "--out", str(tmp_path / "o")]) == 2
    assert "checkpoint" in capsys.readouterr().err
