"""Episode recording, frame drawing, GIF/PNG/MP4 output and the tgrf-render command."""

import functools
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
ENV_CONFIG = {
    "num_humans": 5,
    "human_policy": "social_force",
    "predictor": "const_vel",
    "sensor_range": 2.0,
    "time_limit": 8.0,
}
CLI_SETS = [f"env.{k}={v}" for k, v in ENV_CONFIG.items()]  # the same env, so the CLI test reuses the compiled scan
N_EPISODES = 2

# Static obstacles and a LiDAR: random boxes (a new layout per episode), plus one fixed wall outside the robot's arena
# (so never dropped for blocking its start or goal), occlusion on. Social Force humans walk around obstacles
# locally, not routed: straight at their goals they pass through the boxes' shadows, which the test needs.
WALL = [[-7.0, -3.0], [-7.0, 3.0]]
LIDAR_RAYS = 24
OBSTACLE_CONFIG = {
    "num_humans": 3,
    "human_policy": "social_force",
    "human_routing": False,
    "scenario": "random_obstacles",
    "obstacles": [WALL],
    "lidar_rays": LIDAR_RAYS,
    "occlusion": True,
    "sensor_range": 4.0,
    "time_limit": 6.0,
}
OBSTACLE_SETS = [f"env.{k}={v}".replace("True", "true") for k, v in OBSTACLE_CONFIG.items()]


@pytest.fixture(scope="module")
def env():
    return CrowdNavEnv(ENV_CONFIG, "tgrf")


@pytest.fixture(scope="module")
def episodes(env):
    return render.record_episodes(env, StraightPolicy(), render.eval_key(0), N_EPISODES, label="straight")


@pytest.fixture(scope="module")
def obstacle_env():
    return CrowdNavEnv(OBSTACLE_CONFIG, "tgrf")


@pytest.fixture(scope="module")
def obstacle_episodes(obstacle_env):
    return render.record_episodes(obstacle_env, StraightPolicy(), render.eval_key(0), N_EPISODES, label="straight")


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
        edge = np.linalg.norm(ep.human_pos - ep.robot_pos[:, None], axis=-1) - float(p.robot_radius) - ep.human_radius
        np.testing.assert_array_equal(ep.visible, edge <= float(p.sensor_range))
        for t in range(ep.steps + 1):
            vis = ep.visible[t]
            seen_both |= bool(vis.any() and (~vis).any())
            assert ep.obs_mask[t].sum() == vis.sum()
            # The observation's rows are the visible humans (visible first, sorted by distance).
            observed = ep.obs_human_pos[t][ep.obs_mask[t]]
            expected = ep.human_pos[t][vis]
            order = lambda a: a[np.lexsort(a.T)]
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
        ep.steps % 4 != 0
    )
    fig = render.plot_reward_terms(ep)
    assert len(fig.axes) == 2
    assert render.plot_frame(ep).axes[0].get_title() == "straight: episode 0"


# ------------------------------------------------------------------------------------------------ obstacles, LiDAR


def _layout(polygons):
    from tgrf_jax.env import obstacles as obstacles_lib

    return obstacles_lib.from_polygons([p.tolist() for p in polygons])


def test_record_obstacles_and_scans(obstacle_episodes, obstacle_env, episodes):
    """Each episode carries its own layout (that of its reset state) and the scan of every state, as the env saw it."""
    from tgrf_jax.env import obstacles as obstacles_lib

    params = obstacle_env.default_params
    # The reset states the recording starts from (record_episodes splits its key as evaluate does).
    k_reset = jax.random.split(render.eval_key(0))[0]
    _, starts = jax.jit(jax.vmap(obstacle_env.reset))(jax.random.split(k_reset, N_EPISODES))
    hits = hidden = 0
    for b, ep in enumerate(obstacle_episodes):
        t = ep.steps
        assert ep.lidar.shape == (t + 1, LIDAR_RAYS) and ep.lidar_rays == LIDAR_RAYS
        assert ep.robot_heading.shape == ep.obstacle_dist.shape == (t + 1,)
        assert ep.occlusion
        counts = np.asarray(starts.obstacles.num_vertices[b])
        used = [np.asarray(starts.obstacles.vertices[b, m, :c]) for m, c in enumerate(counts) if c > 0]
        assert len(ep.obstacles) == len(used) >= 2
        for got, want in zip(ep.obstacles, used):
            np.testing.assert_allclose(got, want)
        assert [len(p) for p in ep.obstacles] == [4] * (len(used) - 1) + [2]  # random boxes, then the fixed wall
        np.testing.assert_allclose(ep.obstacles[-1], WALL)
        # Every recorded scan is the LiDAR of the recorded state in this layout, up to the final one: nothing of a
        # later episode's layout enters the recording.
        layout = _layout(ep.obstacles)
        lidar = functools.partial(obstacles_lib.lidar_scan, num_rays=LIDAR_RAYS, max_range=params.sensor_range)
        scan = jax.jit(jax.vmap(lidar, in_axes=(0, 0, None, 0, 0, None)))(
            ep.robot_pos, ep.robot_heading, layout, ep.human_pos, ep.human_radius, np.ones(ep.num_humans, bool)
        )
        np.testing.assert_allclose(ep.lidar, scan, atol=1e-4)
        # With env.occlusion the visible humans are those in range and in the robot's line of sight.
        in_range = (
            np.linalg.norm(ep.human_pos - ep.robot_pos[:, None], axis=-1) - ep.robot_radius - ep.human_radius
        ) <= ep.sensor_range
        in_sight = jax.jit(jax.vmap(obstacles_lib.line_of_sight, in_axes=(0, 0, None)))(
            ep.robot_pos, ep.human_pos, layout
        )
        np.testing.assert_array_equal(ep.visible, in_range & np.asarray(in_sight))
        hidden += int(np.sum(in_range & ~np.asarray(in_sight)))
        np.testing.assert_array_equal(ep.obs_mask.sum(1), ep.visible.sum(1))
        clearance = jax.jit(obstacles_lib.clearance)(ep.robot_pos, layout)
        np.testing.assert_allclose(ep.obstacle_dist, clearance - ep.robot_radius, atol=1e-4)
        assert np.all((ep.lidar >= 0) & (ep.lidar <= ep.sensor_range + 1e-6))
        hits += int((ep.lidar < ep.sensor_range - 1e-3).sum())
    assert hits > 0, "the test scene should have rays that hit something"
    assert hidden > 0, "the test scene should hide humans in range behind obstacles"
    first, second = (e.obstacles for e in obstacle_episodes)
    assert len(first) != len(second) or not all(np.array_equal(a, b) for a, b in zip(first, second)), (
        "random_obstacles draws a layout per episode"
    )
    # Without obstacles or a LiDAR there is nothing of either.
    assert episodes[0].obstacles == [] and episodes[0].lidar is None and episodes[0].obstacle_dist is None
    with pytest.raises(ValueError, match="env.lidar_rays"):
        episodes[0].lidar_points(0)


def _in_axes(rgb, rect=(0.1, 0.15, 0.86, 0.8)):
    """The pixels of a `new_figure` frame inside its axes (its legend, below them, left out)."""
    h, w = rgb.shape[:2]
    x, y, dx, dy = rect
    return rgb[int((1 - y - dy) * h) + 1 : int((1 - y) * h) - 1, int(x * w) + 1 : int((x + dx) * w) - 1]


def _teal_pixels(rgb):
    """Pixels of the LiDAR's colour (the rays and hits) inside the axes."""
    r, g, b = (_in_axes(rgb)[..., i].astype(int) for i in range(3))
    return int(np.sum((g - r > 40) & (b - r > 40) & (np.abs(g - b) < 25)))


def _obstacle_pixels(rgb):
    grey = np.array(to_rgba(render.OBSTACLE_COLOR)[:3]) * 255
    return int(np.sum(np.all(np.abs(rgb.astype(int) - grey) <= 3, axis=-1)))


def test_frame_draws_obstacles_and_rays(obstacle_episodes, episodes):
    ep = obstacle_episodes[0]
    boxes = [p for p in ep.obstacles if len(p) >= 3]
    fig, ax = render.new_figure()
    plain = render.FramePainter(ax, ep)  # rays are off by default
    assert plain.rays is None and plain.ray_hits is None
    assert plain.obstacles.get_gid() == "obstacles" and plain.walls.get_gid() == "walls"
    assert plain.obstacles in ax.collections and plain.walls in ax.collections
    assert [len(p.vertices) for p in plain.obstacles.get_paths()] == [len(p) + 1 for p in boxes]  # closed outlines
    np.testing.assert_allclose(plain.walls.get_segments(), [WALL])
    plain.update(0)
    rgb_plain = plain.render_rgb()
    assert _obstacle_pixels(rgb_plain) > 30 and _teal_pixels(rgb_plain) == 0

    fig, ax = render.new_figure()
    painter = render.FramePainter(ax, ep, show_rays=True)
    assert painter.rays.get_gid() == "lidar_rays" and painter.ray_hits.get_gid() == "lidar_hits"
    for t in range(ep.steps + 1):
        painter.update(t)
        segs = painter.rays.get_segments()
        assert len(segs) == LIDAR_RAYS
        np.testing.assert_allclose([s[0] for s in segs], np.tile(ep.robot_pos[t], (LIDAR_RAYS, 1)), atol=1e-6)
        np.testing.assert_allclose(np.linalg.norm([s[1] - s[0] for s in segs], axis=-1), ep.lidar[t], atol=1e-5)
        hit = ep.lidar[t] < ep.sensor_range * (1 - 1e-5)  # a miss returns the range
        np.testing.assert_allclose(painter.ray_hits.get_offsets(), ep.lidar_points(t)[hit].reshape(-1, 2))
    # Ray k points at heading + 2 pi k / R: ray 0 along the heading.
    painter.update(0)
    end = painter.rays.get_segments()[0][1] - ep.robot_pos[0]
    assert np.arctan2(end[1], end[0]) == pytest.approx(ep.robot_heading[0], abs=1e-5)
    rgb = painter.render_rgb()
    assert _teal_pixels(rgb) > 200 and _obstacle_pixels(rgb) > 30
    # The blitted frame equals a full redraw, obstacles and rays included.
    fig.canvas.draw()
    full = np.asarray(fig.canvas.buffer_rgba())[..., :3]
    assert np.mean(np.abs(full.astype(int) - rgb.astype(int)) > 8) < 0.002
    # The legend names the obstacles and the LiDAR, and says that hidden humans are unseen.
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert {"obstacle", "wall", f"LiDAR, {LIDAR_RAYS} rays", "human, out of sight"} <= set(labels)
    # An episode without a LiDAR has no rays to draw.
    with pytest.raises(ValueError, match="env.lidar_rays"):
        render.FramePainter(ax, episodes[0], show_rays=True)


def test_view_limits_clip_long_obstacles(episodes):
    """A long wall widens the view only near the action; an obstacle just beside it is shown whole."""
    import dataclasses

    ep = episodes[0]
    base = render.view_limits(ep)
    far = dataclasses.replace(
        ep, obstacles=[np.array([[-100.0, 0.0], [100.0, 0.0]]), np.array([[60.0, 60.0], [61.0, 60.0], [61.0, 61.0]])]
    )
    x0, x1, _, _ = render.view_limits(far)
    assert x1 - x0 < (base[1] - base[0]) + 2 * 1.5 + 1e-6 and max(abs(x0), abs(x1)) < 30
    assert render.view_limits(dataclasses.replace(ep, obstacles=[np.array([[60.0, 60.0], [61.0, 60.0]])])) == base
    pts = np.concatenate([ep.robot_pos, ep.goal[None], ep.human_pos.reshape(-1, 2)])
    corner = pts.max(0) + 1.0  # within the 1.5 m reach, outside the current box
    box = np.array([corner, corner + [0.5, 0.0], corner + [0.5, 0.5], corner + [0.0, 0.5]])
    _, x1, _, y1 = render.view_limits(dataclasses.replace(ep, obstacles=[box]))
    assert x1 >= box[:, 0].max() and y1 >= box[:, 1].max()


def test_obstacle_collision_is_an_outcome(episodes):
    import dataclasses

    from tgrf_jax.env import OBSTACLE_COLLISION

    ep = episodes[0]
    outcomes = ep.outcomes.copy()
    outcomes[-1] = OBSTACLE_COLLISION
    hit = dataclasses.replace(ep, outcomes=outcomes)
    assert hit.outcome == "obstacle_collision"
    painter = render.draw_frame(render.new_figure()[1], hit, hit.steps)
    assert painter.banner.get_visible() and painter.banner.get_text().startswith("OBSTACLE COLLISION at ")
    assert to_rgba(painter.banner.get_color()) == to_rgba(render.OUTCOME_COLORS["obstacle_collision"])
    assert render.OUTCOME_COLORS["obstacle_collision"] not in (
        render.OUTCOME_COLORS["collision"],
        render.OUTCOME_COLORS["timeout"],
    )
    assert "obstacle collision after" in render.plot_reward_terms(hit)._suptitle.get_text()


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
        assert (
            len(list(pathlib.Path(row["frame_dir"]).glob("frame_*.png")))
            == row["frames"]
            == ep.steps // 2 + 1 + (ep.steps % 2)
        )


def test_cli_renders_rays(tmp_path, capsys, obstacle_episodes):
    """--rays draws the LiDAR of an obstacle scenario (the same env as obstacle_episodes: no new compilation)."""
    out = tmp_path / "out"
    args = [
        "--policy",
        "straight",
        "--episodes",
        str(N_EPISODES),
        "--out",
        str(out),
        "--dpi",
        "40",
        "--stride",
        "50",
        "--no-gif",
        "--no-mp4",
        "--rays",
    ]
    assert render_main(args + sum((["--set", s] for s in OBSTACLE_SETS), [])) == 0
    summary = json.loads((out / "summary.json").read_text())
    for row, ep in zip(summary["episodes"], obstacle_episodes):
        assert row["outcome"] == ep.outcome and row["steps"] == ep.steps
        frames = sorted(pathlib.Path(row["frame_dir"]).glob("frame_*.png"))
        rgb = np.asarray(Image.open(frames[0]).convert("RGB"))
        assert _teal_pixels(rgb) > 5 and _obstacle_pixels(rgb) > 5


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
        (ep.steps, ep.outcome) for ep in [*episodes, *second]
    ]


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


@pytest.mark.parametrize(
    "args, message",
    [
        (["{tmp}/nope"], "'{tmp}/nope' does not exist (expected a tgrf-train run directory or a YAML config)"),
        (["{tmp}"], "is not a tgrf-train run directory"),
        (["{tmp}/cfg.yaml"], "is a config file: name the robot with --policy straight|orca"),
        ([], "give a RUN_DIR, --pretrained NAME or --policy straight|orca"),
        (
            ["--policy", "orca", "--set", "env.num_human=3"],
            "unknown config key 'env.num_human' (did you mean 'num_humans'?)",
        ),
        (
            ["--policy", "orca", "--set", "env.human_policy=teleport"],
            "env.human_policy = 'teleport' is not allowed; allowed: one of 'orca', 'social_force'",
        ),
        (["--policy", "orca", "--set", "reward.sigma_disc=0"], "reward.sigma_disc = 0.0 is out of range"),
        (["--policy", "orca", "--set", "ppo.lr=1"], "only those can be overridden, not ['ppo.lr=1']"),
        (["--policy", "orca", "--episodes", "0"], "--episodes = 0 is out of range; allowed: 1 .. 10,000,000"),
        (["--policy", "orca", "--fps", "0"], "--fps = 0.0 must be > 0"),
        (["--policy", "orca", "--step", "3"], "--step selects a checkpoint of a RUN_DIR"),
        (
            ["--policy", "straight", "--rays"],
            "--rays draws the robot's LiDAR rays, but this env has no LiDAR (env.lidar_rays = 0)",
        ),
        (["--policy", "straight", "--rays", "--set", "env.scenario=doorway"], "--set env.lidar_rays=72"),
        (["--policy", "orca", "--out", "{tmp}/cfg.yaml"], "exists and is not a directory"),
    ],
)
def test_cli_errors_before_compiling(tmp_path, capsys, args, message):
    (tmp_path / "cfg.yaml").write_text("env:\n  num_humans: 3\n")
    fmt = lambda s: s.replace("{tmp}", str(tmp_path))
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
    assert "invalid choice: 'random' (choose from straight, orca)" in capsys.readouterr().err.replace(
        "'straight'", "straight"
    ).replace("'orca'", "orca")


def test_cli_run_dir_overrides_limited(tmp_path, capsys):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "config.yaml").write_text((ROOT / "configs" / "tiny.yaml").read_text())
    assert render_main([str(run_dir), "--out", str(tmp_path / "o"), "--set", "ppo.lr=0.1"]) == 2
    assert "with a RUN_DIR only env.* and reward.* can be overridden" in capsys.readouterr().err
    # A run dir without checkpoints fails clearly (after the config checks).
    assert render_main([str(run_dir), "--out", str(tmp_path / "o")]) == 2
    assert "checkpoint" in capsys.readouterr().err
