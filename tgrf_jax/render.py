"""Episode rendering: record episodes in one jitted scan, draw them with matplotlib, and the `tgrf-render` command.

Recording (`record_episodes`) is pure JAX: a `lax.scan` over the time limit plays a batch of episodes with the same
keys and step order as `tgrf_jax.evaluate` (so episode i of a render and of an evaluation with the same seed and
count are the same episode) and returns every state, the robot's visibility mask, the predictions it observed and
the reward split into its terms. Everything after that is host code on numpy arrays.

Drawing conventions (the colours of the paper's Fig. 5):

* robot: yellow disc with its velocity as a short black tick; goal: a star inside the goal-tolerance circle;
* humans inside the sensor range (the env's `visible_mask`): solid blue; humans outside it: pale red;
* predicted positions (t+1..t+K) of visible humans, as the robot observes them: orange dots, fading with k;
* sensor range: dashed grey circle of radius r_robot + sensor_range around the robot (the range is edge-to-edge,
  so a human is visible exactly when its body reaches into this circle);
* danger zone: a ring of radius r_robot + d_disc around the robot. d_disc is an edge-to-edge distance, so the
  robot is in the danger zone exactly when a human's body overlaps this ring; one ring around the robot shows the
  same condition as a ring of r_human + d_disc around every human, without twenty overlapping rings. It fills red
  on danger steps;
* trajectories so far: the robot's whole path (orange), the humans' recent trails (grey; broken where a human
  respawns);
* a caption with time, step, visible count, nearest distance, step reward, return and, at the end, the outcome.

Figures are built on `matplotlib.figure.Figure` with an Agg canvas, never through pyplot, so nothing here touches
the global backend or shows stray figures in notebooks.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import pathlib
import shutil
import subprocess
import sys
import time
from typing import Sequence

import numpy as np

# Colours (the paper's Fig. 5: yellow robot, blue humans in range, red humans out of range, orange predictions).
ROBOT_COLOR = "#ffd21f"
VISIBLE_COLOR = "#1f5fbf"
UNSEEN_COLOR = "#f2a0a0"
VISIBLE_EDGE = "#0b2f66"
UNSEEN_EDGE = "#b05050"
PRED_COLOR = "#ff8c1a"
GOAL_COLOR = "#2ca02c"
DANGER_COLOR = "#d62728"
PATH_COLOR = "#e07b00"
TERM_COLORS = {
    "goal": "#2ca02c", "collision": "#7f0000", "disc": "#d62728", "pot": "#1f77b4", "pred": "#ff8c1a",
    "kinematic": "#9467bd",
}
TERM_LABELS = {
    "goal": "r_goal", "collision": "r_col", "disc": "r_disc", "pot": "r_pot", "pred": "r_pred",
    "kinematic": "r_spin + r_back",
}
OUTCOME_COLORS = {"running": "#333333", "success": "#1a7f1a", "collision": "#b00000", "timeout": "#8a6d00"}
POLICY_CHOICES = ("straight", "orca")


# ------------------------------------------------------------------------------------------------ recording


@dataclasses.dataclass
class Episode:
    """One recorded episode as numpy arrays. T = `steps`; index 0 of the (T+1)-long arrays is the reset state.

    `visible` is in human-index order (True: within sensor range). `pred_pos` / `pred_mask` are the observation's
    predicted world positions in the observation's own row order (visible humans first), so only what the robot
    observed is drawn. Per-step arrays (`reward`, `terms`, `outcomes`) are T long: entry t-1 belongs to step t.
    """

    label: str
    index: int
    robot_pos: np.ndarray  # (T+1, 2)
    robot_vel: np.ndarray  # (T+1, 2)
    goal: np.ndarray  # (2,)
    human_pos: np.ndarray  # (T+1, N, 2)
    human_radius: np.ndarray  # (T+1, N)
    visible: np.ndarray  # (T+1, N) bool, human-index order
    obs_human_pos: np.ndarray  # (T+1, N, 2) world positions of the observed rows (sorted, visible first)
    obs_mask: np.ndarray  # (T+1, N) bool, the observation's human_mask
    pred_pos: np.ndarray | None  # (T+1, N, K, 2) observed predictions (world), None without a predictor
    reward: np.ndarray  # (T,)
    terms: dict  # name -> (T,)
    outcomes: np.ndarray  # (T,) int, the last one is the episode's outcome
    dt: float
    robot_radius: float
    sensor_range: float
    d_disc: float
    goal_tolerance: float
    max_steps: int

    @property
    def steps(self) -> int:
        return len(self.reward)

    @property
    def num_humans(self) -> int:
        return self.human_pos.shape[1]

    @property
    def outcome(self) -> str:
        from tgrf_jax.env import OUTCOME_NAMES

        return OUTCOME_NAMES[int(self.outcomes[-1])] if self.steps else "running"

    @property
    def duration(self) -> float:
        return self.steps * self.dt

    @property
    def ret(self) -> float:
        return float(self.reward.sum())

    def dmin(self) -> np.ndarray:
        """Nearest edge-to-edge robot-human distance of every recorded state (T+1,) (inf without humans)."""
        if self.num_humans == 0:
            return np.full(self.steps + 1, np.inf)
        d = np.linalg.norm(self.human_pos - self.robot_pos[:, None], axis=-1) - self.robot_radius - self.human_radius
        return d.min(axis=1)

    def summary(self) -> dict:
        return dict(label=self.label, episode=self.index, outcome=self.outcome, steps=self.steps,
                    time=round(self.duration, 3), ret=round(self.ret, 4),
                    path_length=round(float(np.linalg.norm(np.diff(self.robot_pos, axis=0), axis=-1).sum()), 4))


def _record(env, policy, key, n_episodes: int, params, n_steps: int):
    """Pure: play `n_episodes` episodes for `n_steps` steps, freezing each after it ends; returns stacked outputs."""
    import jax
    import jax.numpy as jnp

    from tgrf_jax.env import sensing

    def snapshot(obs, state):
        visible = jax.vmap(sensing.visible_mask, in_axes=(0, None))(state, params)
        return dict(
            robot_pos=state.robot.pos, robot_vel=state.robot.vel, goal=state.robot.goal,
            human_pos=state.humans.pos, human_radius=state.humans.radius, visible=visible,
            obs_humans=obs.humans, obs_mask=obs.human_mask,
        )

    def step_one(key, state, action):
        k_step, _ = jax.random.split(key)  # as env.step splits it, so trajectories match evaluate()
        return env.step_env(k_step, state, action, params)

    def body(loop, t):
        key, obs, state, carry, alive = loop
        key, k_act, k_step = jax.random.split(key, 3)
        carry, action = policy.act(carry, obs, jnp.equal(t, 0) & alive, k_act)
        new_obs, new_state, reward, terminated, truncated, info = jax.vmap(step_one)(
            jax.random.split(k_step, n_episodes), state, action)

        def keep(new, old):
            return jnp.where(alive.reshape((-1,) + (1,) * (new.ndim - 1)), new, old)

        state = jax.tree_util.tree_map(keep, new_state, state)
        obs = jax.tree_util.tree_map(keep, new_obs, obs)
        out = dict(snapshot(obs, state), alive=alive, reward=reward, outcome=info.outcome,
                   terms=info.reward_terms)
        return (key, obs, state, carry, alive & ~(terminated | truncated)), out

    k_reset, k_loop = jax.random.split(key)
    obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(k_reset, n_episodes), params)
    first = snapshot(obs, state)
    loop = (k_loop, obs, state, policy.initialize_carry(n_episodes), jnp.ones(n_episodes, bool))
    _, outs = jax.lax.scan(body, loop, jnp.arange(n_steps))
    return first, outs


@functools.lru_cache(maxsize=None)
def _record_jit():
    import jax

    return jax.jit(_record, static_argnums=(0, 1, 3, 5))


def eval_key(seed: int):
    """The key with which `tgrf_jax.evaluate.evaluate(env, policy, jax.random.key(seed), n)` (and so `tgrf-eval
    --seed`) plays its episodes (its first batch): `record_episodes(env, policy, eval_key(seed), n)` replays them."""
    import jax

    return jax.random.fold_in(jax.random.key(seed), 0)


def record_episodes(env, policy, key, n_episodes: int = 1, params=None, *, label: str | None = None) -> list[Episode]:
    """Play `n_episodes` episodes of `policy` in `env` (one jitted scan, batched) and return them as `Episode`s.

    `policy` follows the `tgrf_jax.policies` interface (baselines or `LearnedPolicy`). Each episode runs until it
    ends (success, collision or the time limit). Keys and step order are those of `tgrf_jax.evaluate.run_episodes`,
    so the same key gives the same episodes; use `eval_key(seed)` to replay what `evaluate` / `tgrf-eval` played.
    """
    import jax

    if int(n_episodes) < 1:
        raise ValueError(f"n_episodes = {n_episodes} must be >= 1")
    params = env.default_params if params is None else params
    n_steps = int(round(float(params.time_limit) / float(params.dt)))
    first, outs = jax.device_get(_record_jit()(env, policy, key, int(n_episodes), params, n_steps))
    label = label or getattr(policy, "name", None) or type(policy).__name__
    k = env.config.pred_horizon if env.config.uses_predictions else 0
    episodes = []
    for b in range(int(n_episodes)):
        steps = int(outs["alive"][:, b].sum())
        seq = lambda name: np.concatenate([first[name][b][None], outs[name][:steps, b]])  # noqa: E731
        robot_pos = seq("robot_pos")
        obs_humans = seq("obs_humans")
        n = obs_humans.shape[1]
        obs_pos = obs_humans[:, :, :2] + robot_pos[:, None]
        pred = obs_humans[:, :, 2:].reshape(steps + 1, n, k, 2) + robot_pos[:, None, None] if k else None
        episodes.append(Episode(
            label=label, index=b, robot_pos=robot_pos, robot_vel=seq("robot_vel"), goal=np.asarray(first["goal"][b]),
            human_pos=seq("human_pos"), human_radius=seq("human_radius"), visible=seq("visible").astype(bool),
            obs_human_pos=obs_pos, obs_mask=seq("obs_mask").astype(bool), pred_pos=pred,
            reward=np.asarray(outs["reward"][:steps, b], np.float64),
            terms={f.name: np.asarray(getattr(outs["terms"], f.name)[:steps, b], np.float64)
                   for f in dataclasses.fields(outs["terms"])},
            outcomes=np.asarray(outs["outcome"][:steps, b]),
            dt=float(params.dt), robot_radius=float(params.robot_radius), sensor_range=float(params.sensor_range),
            d_disc=float(params.reward.d_disc), goal_tolerance=float(params.goal_tolerance), max_steps=n_steps,
        ))
    return episodes


# ------------------------------------------------------------------------------------------------ drawing


def view_limits(ep: Episode, margin: float = 0.8) -> tuple[float, float, float, float]:
    """A square window holding the robot, its goal and every human of the whole episode (fixed over frames)."""
    pts = [ep.robot_pos, ep.goal[None]]
    if ep.num_humans:
        pts.append(ep.human_pos.reshape(-1, 2))
    pts = np.concatenate(pts)
    lo, hi = pts.min(0) - margin - 0.5, pts.max(0) + margin + 0.5
    centre, half = (lo + hi) / 2, (hi - lo).max() / 2
    return centre[0] - half, centre[0] + half, centre[1] - half, centre[1] + half


def _trail_segments(points: np.ndarray, max_jump: float) -> list[np.ndarray]:
    """Split a (T, 2) track wherever it jumps further than `max_jump` in one step (a respawn)."""
    if len(points) < 2:
        return []
    jumps = np.nonzero(np.linalg.norm(np.diff(points, axis=0), axis=-1) > max_jump)[0] + 1
    return [seg for seg in np.split(points, jumps) if len(seg) >= 2]


def _legend_handles(ep: Episode):
    from matplotlib.lines import Line2D

    dot = dict(marker="o", linestyle="none", markersize=10)
    handles = [
        Line2D([], [], markerfacecolor=ROBOT_COLOR, markeredgecolor="black", label="robot", **dot),
        Line2D([], [], marker="*", linestyle="none", markersize=13, markerfacecolor=GOAL_COLOR,
               markeredgecolor="black", label="goal"),
        Line2D([], [], markerfacecolor=VISIBLE_COLOR, markeredgecolor=VISIBLE_EDGE, label="human, in sensor range",
               **dot),
        Line2D([], [], markerfacecolor=UNSEEN_COLOR, markeredgecolor=UNSEEN_EDGE, label="human, out of range", **dot),
        Line2D([], [], color=PRED_COLOR, marker="o", markersize=4, linewidth=1.3, label="predicted positions"),
        Line2D([], [], color="#606060", linestyle="--", label="sensor range"),
        Line2D([], [], color=DANGER_COLOR, linestyle=":", linewidth=1.5, label=f"danger zone (d_disc {ep.d_disc:g} m)"),
        Line2D([], [], color=PATH_COLOR, linewidth=2.2, label="robot path"),
    ]
    if ep.pred_pos is None:
        handles.pop(4)
    return handles


class FramePainter:
    """Draws the frames of one episode onto an axes: the artists are built once, `update(t)` moves them.

    `humans` (an EllipseCollection, gid "humans") holds one disc per human in human-index order, coloured
    `VISIBLE_COLOR` or `UNSEEN_COLOR` from the env's visibility mask of the frame.
    """

    def __init__(self, ax, ep: Episode, *, trail_steps: int | None = 20, show_legend: bool = True, limits=None,
                 title: str | None = None):
        from matplotlib.collections import EllipseCollection, LineCollection
        from matplotlib.patches import Circle

        self.ax, self.ep, self.trail_steps = ax, ep, trail_steps
        self.dmin = ep.dmin()
        ax.clear()
        x0, x1, y0, y1 = limits or view_limits(ep)
        ax.set_xlim(x0, x1)
        ax.set_ylim(y0, y1)
        ax.set_aspect("equal")
        ax.set_autoscale_on(False)
        ax.grid(alpha=0.25, linewidth=0.6)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_title(title if title is not None else f"{ep.label}: episode {ep.index}", fontsize=12)

        # Sensor range and danger zone, centred on the robot.
        r0 = ep.robot_pos[0]
        self.sensor_fill = ax.add_patch(Circle(r0, ep.robot_radius + ep.sensor_range, facecolor="#808080",
                                               alpha=0.06, edgecolor="none", zorder=0))
        self.sensor_edge = ax.add_patch(Circle(r0, ep.robot_radius + ep.sensor_range, fill=False, edgecolor="#606060",
                                               linestyle="--", linewidth=1.0, zorder=1, gid="sensor_range"))
        self.danger_fill = ax.add_patch(Circle(r0, ep.robot_radius + ep.d_disc, facecolor=DANGER_COLOR, alpha=0.07,
                                               edgecolor="none", zorder=2))
        self.danger_edge = ax.add_patch(Circle(r0, ep.robot_radius + ep.d_disc, fill=False, edgecolor=DANGER_COLOR,
                                               linestyle=":", linewidth=1.3, zorder=2, gid="danger_zone"))
        # Goal (it does not move, but is drawn with the moving artists to keep the stacking order).
        self.goal_ring = ax.add_patch(Circle(ep.goal, ep.goal_tolerance, fill=False, edgecolor=GOAL_COLOR,
                                             linewidth=1.2, zorder=3))
        (self.goal_star,) = ax.plot(*ep.goal, marker="*", markersize=16, color=GOAL_COLOR, markeredgecolor="black",
                                    markeredgewidth=0.6, zorder=3, linestyle="none")
        # Trajectories.
        self.trails = ax.add_collection(LineCollection([], colors="#7a7a7a", linewidths=1.0, alpha=0.55, zorder=4),
                                        autolim=False)
        (self.path,) = ax.plot([], [], color=PATH_COLOR, linewidth=2.2, zorder=5, solid_capstyle="round")
        # Humans, in human-index order.
        n = ep.num_humans
        self.humans = EllipseCollection(np.zeros(n), np.zeros(n), np.zeros(n), units="xy", offsets=np.zeros((n, 2)),
                                        offset_transform=ax.transData, linewidths=1.0, zorder=8, gid="humans")
        ax.add_collection(self.humans, autolim=False)
        # Observed predictions of the visible humans (over the humans, fading with the horizon).
        self.pred_lines = ax.add_collection(LineCollection([], colors=PRED_COLOR, linewidths=1.3, alpha=0.9, zorder=9),
                                            autolim=False)
        self.pred_dots = ax.scatter(np.zeros(0), np.zeros(0), s=22, edgecolors="none", zorder=9, gid="predictions")
        # Robot and its velocity tick.
        self.robot = ax.add_patch(Circle(r0, ep.robot_radius, facecolor=ROBOT_COLOR, edgecolor="black",
                                         linewidth=1.3, zorder=10, gid="robot"))
        (self.tick,) = ax.plot([], [], color="black", linewidth=1.6, zorder=11)
        # Captions.
        box = dict(boxstyle="round,pad=0.35", facecolor="white", alpha=0.85, edgecolor="#bbbbbb")
        self.caption = ax.text(0.015, 0.985, "", transform=ax.transAxes, va="top", ha="left", fontsize=9.5,
                               family="monospace", zorder=20, bbox=box)
        color = OUTCOME_COLORS.get(ep.outcome, "black")
        self.banner = ax.text(0.985, 0.985, f"{ep.outcome.upper()} at {ep.duration:.2f} s", transform=ax.transAxes,
                              va="top", ha="right", fontsize=13, fontweight="bold", color=color, zorder=20,
                              visible=False, bbox=dict(boxstyle="round,pad=0.35", facecolor="white", alpha=0.9,
                                                       edgecolor=color))
        if show_legend:
            ax.legend(handles=_legend_handles(ep), loc="upper center", bbox_to_anchor=(0.5, -0.09), ncol=4,
                      fontsize=8.5, frameon=False, handlelength=1.6, columnspacing=1.2)

    def update(self, t: int):
        """Show state `t` (0 = the reset state, `ep.steps` = the final state); returns the changed artists."""
        ep = self.ep
        t = int(np.clip(t, 0, ep.steps))
        rpos = ep.robot_pos[t]
        dmin = float(self.dmin[t])
        in_danger = dmin < ep.d_disc
        for patch in (self.sensor_fill, self.sensor_edge, self.danger_fill, self.danger_edge, self.robot):
            patch.set_center(rpos)
        self.danger_fill.set_alpha(0.3 if in_danger else 0.07)

        start = 0 if self.trail_steps is None else max(0, t - self.trail_steps)
        segs = []
        for i in range(ep.num_humans):
            segs += _trail_segments(ep.human_pos[start:t + 1, i], max_jump=1.0)
        self.trails.set_segments(segs)
        self.path.set_data(ep.robot_pos[:t + 1, 0], ep.robot_pos[:t + 1, 1])

        if ep.num_humans:
            vis = ep.visible[t]
            self.humans.set_offsets(ep.human_pos[t])
            self.humans.set_widths(2 * ep.human_radius[t])
            self.humans.set_heights(2 * ep.human_radius[t])
            self.humans.set_facecolor([VISIBLE_COLOR if v else UNSEEN_COLOR for v in vis])
            self.humans.set_edgecolor([VISIBLE_EDGE if v else UNSEEN_EDGE for v in vis])

        rows = np.nonzero(ep.obs_mask[t])[0] if ep.pred_pos is not None else np.zeros(0, int)
        if len(rows):
            k = ep.pred_pos.shape[2]
            self.pred_lines.set_segments([np.concatenate([ep.obs_human_pos[t, j][None], ep.pred_pos[t, j]])
                                          for j in rows])
            colors = np.zeros((len(rows) * k, 4))
            colors[:, :3] = (1.0, 0.55, 0.1)
            colors[:, 3] = np.tile(np.linspace(1.0, 0.45, k), len(rows))
            self.pred_dots.set_offsets(ep.pred_pos[t, rows].reshape(-1, 2))
            self.pred_dots.set_facecolor(colors)
        else:
            self.pred_lines.set_segments([])
            self.pred_dots.set_offsets(np.zeros((0, 2)))

        vel = ep.robot_vel[t]
        speed = float(np.linalg.norm(vel))
        if speed > 1e-6:
            tip = rpos + vel / speed * ep.robot_radius * (0.4 + 0.6 * min(speed, 1.0))
            self.tick.set_data([rpos[0], tip[0]], [rpos[1], tip[1]])
        else:
            self.tick.set_data([], [])

        n_vis = int(ep.visible[t].sum()) if ep.num_humans else 0
        lines = [f"t = {t * ep.dt:5.2f} s   step {t}/{ep.max_steps}",
                 f"visible {n_vis}/{ep.num_humans}   d_min {dmin:.2f} m" + ("  DANGER" if in_danger else "")]
        lines.append(f"r_t = {ep.reward[t - 1]:+.2f}   return {ep.reward[:t].sum():+.2f}" if t > 0 else
                     "r_t =   -     return +0.00")
        self.caption.set_text("\n".join(lines))
        self._banner_on = t == ep.steps and ep.steps > 0
        self.banner.set_visible(self._banner_on)
        return self.animated

    @property
    def animated(self) -> list:
        """The artists `update` changes (plus the goal), in drawing order."""
        artists = [self.sensor_fill, self.sensor_edge, self.danger_fill, self.danger_edge, self.goal_ring,
                   self.goal_star, self.trails, self.path, self.humans, self.pred_lines, self.pred_dots, self.robot,
                   self.tick, self.caption, self.banner]
        return sorted(artists, key=lambda a: a.get_zorder())

    def render_rgb(self) -> np.ndarray:
        """The current frame as an (H, W, 3) uint8 array (Agg canvas).

        The static part (axes, ticks, grid, legend) is drawn once and cached; each frame restores it and draws only
        the moving artists (blitting), several times faster than a full redraw.
        """
        fig = self.ax.figure
        canvas = fig.canvas
        key = (canvas.get_width_height(), fig.dpi)
        if getattr(self, "_background_key", None) != key:
            for a in self.animated:
                a.set_visible(False)
            canvas.draw()
            self._background = canvas.copy_from_bbox(fig.bbox)
            self._background_key = key
            for a in self.animated:
                a.set_visible(True)
            self.banner.set_visible(self._banner_on)
        canvas.restore_region(self._background)
        for a in self.animated:
            if a.get_visible():
                self.ax.draw_artist(a)
        return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def draw_frame(ax, ep: Episode, t: int, **kwargs) -> FramePainter:
    """Draw state `t` (0 = reset state, `ep.steps` = final state) of `ep` onto `ax` (cleared first).

    Keyword arguments go to `FramePainter` (trail_steps, show_legend, limits, title). To draw many frames, keep
    the returned painter and call its `update(t)`: that is several times faster than redrawing from scratch.
    """
    painter = FramePainter(ax, ep, **kwargs)
    painter.update(t)
    return painter


def new_figure(size: tuple[float, float] = (7.2, 8.0), dpi: float = 90):
    """A pyplot-free Figure with an Agg canvas and one axes laid out for `draw_frame` (legend strip below)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0.1, 0.15, 0.86, 0.8))
    return fig, ax


def plot_frame(ep: Episode, t: int | None = None, **kwargs):
    """A Figure of one frame (default: the last). Displays inline in Jupyter; `fig.savefig(path)` writes it."""
    fig, ax = new_figure()
    draw_frame(ax, ep, ep.steps if t is None else t, **kwargs)
    return fig


def _frame_indices(ep: Episode, stride: int) -> list[int]:
    idx = list(range(0, ep.steps + 1, stride))
    if idx[-1] != ep.steps:
        idx.append(ep.steps)  # always end on the outcome frame
    return idx


def ffmpeg_path() -> str | None:
    return shutil.which("ffmpeg")


def save_episode(ep: Episode, out_dir, *, name: str | None = None, frames: bool = True, gif: bool = True,
                 mp4: bool | None = None, fps: float = 8.0, dpi: int = 90, stride: int = 1,
                 hold_s: float = 1.5, **draw_kwargs) -> dict:
    """Write PNG frames (`<name>/frame_0000.png`...), `<name>.gif` and, when ffmpeg is on PATH, `<name>.mp4`.

    `mp4=None` writes the MP4 only if ffmpeg is found; `mp4=True` without ffmpeg raises. The last frame (the
    outcome) is held for `hold_s` seconds in the GIF and MP4. Returns {"frames": [...], "gif": path, "mp4": path}.
    """
    from PIL import Image

    if fps <= 0 or stride < 1 or dpi < 10:
        raise ValueError(f"need fps > 0, stride >= 1 and dpi >= 10, got fps={fps}, stride={stride}, dpi={dpi}")
    ffmpeg = ffmpeg_path()
    if mp4 and ffmpeg is None:
        raise RuntimeError("mp4=True but ffmpeg is not on PATH")
    want_mp4 = ffmpeg is not None if mp4 is None else bool(mp4)
    out_dir = pathlib.Path(out_dir)
    name = name or f"ep{ep.index:03d}"
    out_dir.mkdir(parents=True, exist_ok=True)
    frame_dir = out_dir / name
    if frames:
        frame_dir.mkdir(exist_ok=True)
        for old in frame_dir.glob("frame_*.png"):
            old.unlink()

    fig, ax = new_figure(dpi=dpi)
    painter = FramePainter(ax, ep, **draw_kwargs)
    written: dict = {"frames": [], "gif": None, "mp4": None}
    gif_frames = []
    proc = None
    mp4_path = out_dir / f"{name}.mp4"
    try:
        for t in _frame_indices(ep, stride):
            painter.update(t)
            rgb = painter.render_rgb()
            if frames:
                path = frame_dir / f"frame_{t:04d}.png"
                Image.fromarray(rgb).save(path)
                written["frames"].append(path)
            if gif:
                gif_frames.append(Image.fromarray(rgb).quantize(colors=128, method=Image.Quantize.MEDIANCUT))
            if want_mp4:
                if proc is None:
                    h, w = rgb.shape[:2]
                    proc = subprocess.Popen(
                        [ffmpeg, "-y", "-loglevel", "error", "-f", "rawvideo", "-pix_fmt", "rgb24", "-s", f"{w}x{h}",
                         "-r", f"{fps:g}", "-i", "-", "-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2", "-pix_fmt", "yuv420p",
                         str(mp4_path)],
                        stdin=subprocess.PIPE, stderr=subprocess.PIPE)
                proc.stdin.write(np.ascontiguousarray(rgb).tobytes())
        if proc is not None:
            for _ in range(int(round(hold_s * fps))):
                proc.stdin.write(np.ascontiguousarray(rgb).tobytes())
            _, err = proc.communicate()
            if proc.returncode != 0:
                raise RuntimeError(f"ffmpeg failed writing {mp4_path}: {err.decode(errors='replace').strip()}")
            written["mp4"] = mp4_path
            proc = None
    finally:
        if proc is not None:
            proc.kill()
            proc.wait()
    if gif and gif_frames:
        gif_path = out_dir / f"{name}.gif"
        frame_ms = int(round(1000.0 / fps))
        durations = [frame_ms] * (len(gif_frames) - 1) + [max(frame_ms, int(hold_s * 1000))]
        gif_frames[0].save(gif_path, save_all=True, append_images=gif_frames[1:], duration=durations, loop=0,
                           optimize=False, disposal=1)
        written["gif"] = gif_path
    return written


def animate(ep: Episode, *, stride: int = 1, fps: float = 8.0, dpi: int = 72, **draw_kwargs):
    """A `matplotlib.animation.FuncAnimation` of the episode (for notebooks: `.to_jshtml()`, or `show`)."""
    from matplotlib.animation import FuncAnimation

    fig, ax = new_figure(dpi=dpi)
    painter = FramePainter(ax, ep, **draw_kwargs)
    return FuncAnimation(fig, painter.update, frames=_frame_indices(ep, stride), interval=1000.0 / fps, repeat=True,
                         cache_frame_data=False)


def to_jshtml(ep: Episode, *, stride: int = 1, fps: float = 8.0, dpi: int = 72, **draw_kwargs) -> str:
    """The episode as a self-contained HTML/JavaScript player (matplotlib's `to_jshtml`)."""
    return animate(ep, stride=stride, fps=fps, dpi=dpi, **draw_kwargs).to_jshtml(fps=fps, default_mode="once")


def show(ep: Episode, **kwargs):
    """Inline player for Jupyter: `IPython.display.HTML` of `to_jshtml(ep, **kwargs)`."""
    from IPython.display import HTML

    return HTML(to_jshtml(ep, **kwargs))


def gif_bytes(ep: Episode, **kwargs) -> bytes:
    """The episode's GIF as bytes (e.g. `IPython.display.Image(data=gif_bytes(ep))` for static viewers)."""
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        paths = save_episode(ep, tmp, frames=False, gif=True, mp4=False, **kwargs)
        return pathlib.Path(paths["gif"]).read_bytes()


def plot_reward_terms(ep: Episode, *, title: str | None = None):
    """Figure: the reward of every step split into its terms (stacked bars, positive up, negative down, the total
    as a black line), and below it the return accumulated by each term."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 6.4), layout="constrained")
    FigureCanvasAgg(fig)
    ax_step, ax_cum = fig.subplots(2, 1, sharex=True, height_ratios=(1.2, 1))
    t = np.arange(1, ep.steps + 1) * ep.dt
    names = [n for n in TERM_COLORS if n in ep.terms and np.any(ep.terms[n] != 0)]
    pos_base = np.zeros(ep.steps)
    neg_base = np.zeros(ep.steps)
    for n in names:
        v = ep.terms[n]
        up, down = np.maximum(v, 0), np.minimum(v, 0)
        ax_step.bar(t, up, bottom=pos_base, width=ep.dt * 0.9, color=TERM_COLORS[n], label=TERM_LABELS[n])
        ax_step.bar(t, down, bottom=neg_base, width=ep.dt * 0.9, color=TERM_COLORS[n])
        pos_base += up
        neg_base += down
    ax_step.plot(t, ep.reward, color="black", linewidth=1.0, marker=".", markersize=3, label="total r_t")
    ax_step.axhline(0, color="#444444", linewidth=0.6)
    lo = min(neg_base.min(initial=0.0), ep.reward.min(initial=0.0))
    hi = max(pos_base.max(initial=0.0), ep.reward.max(initial=0.0))
    pad = 0.08 * max(hi - lo, 1e-3)
    ax_step.set_ylim(lo - pad, hi + pad)
    ax_step.set_ylabel("reward per step")
    ax_step.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=9, frameon=False)
    ax_step.grid(alpha=0.3)
    for n in names:
        ax_cum.plot(t, np.cumsum(ep.terms[n]), color=TERM_COLORS[n], linewidth=1.8, label=TERM_LABELS[n])
    ax_cum.plot(t, np.cumsum(ep.reward), color="black", linewidth=2.2, label="return so far")
    ax_cum.axhline(0, color="#444444", linewidth=0.6)
    ax_cum.set_xlabel("time (s)")
    ax_cum.set_ylabel("cumulative reward")
    ax_cum.grid(alpha=0.3)
    ax_cum.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=9, frameon=False)
    fig.suptitle(title or f"{ep.label}, episode {ep.index}: {ep.outcome} after {ep.duration:.2f} s, "
                 f"return {ep.ret:+.2f}")
    return fig


# ------------------------------------------------------------------------------------------------ tgrf-render


class RenderError(ValueError):
    """Invalid tgrf-render input (reported before anything compiles)."""


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="tgrf-render",
        description="Render episodes as PNG frames, a GIF and (when ffmpeg is on PATH) an MP4. With a RUN_DIR "
        "(from tgrf-train) the trained policy is rendered on the run's own scenario (plus any --policy "
        "baselines); otherwise --policy baselines on a YAML config (default: the paper scenario).",
    )
    p.add_argument("source", nargs="?", metavar="RUN_DIR|CONFIG.yaml",
                   help="a tgrf-train run directory, or a YAML file with env/reward sections")
    p.add_argument("--policy", action="append", choices=POLICY_CHOICES, help="baseline robot (repeatable)")
    p.add_argument("--episodes", type=int, default=1, help="episodes per policy (default 1)")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.add_argument("--seed", type=int, default=0,
                   help="episode i is episode i of tgrf-eval --seed S with as many episodes (default 0)")
    p.add_argument("--step", type=int, default=None, help="RUN_DIR: checkpoint (update) to render; default latest")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config value, e.g. --set env.num_humans=10")
    p.add_argument("--fps", type=float, default=8.0, help="GIF/MP4 frames per second (default 8 = 2x real time)")
    p.add_argument("--dpi", type=int, default=90, help="frame resolution (default 90: 648 x 720 pixels)")
    p.add_argument("--stride", type=int, default=1, help="draw every STRIDE-th step (default 1)")
    p.add_argument("--no-frames", action="store_true", help="skip the PNG frames")
    p.add_argument("--no-gif", action="store_true", help="skip the GIF")
    p.add_argument("--no-mp4", action="store_true", help="skip the MP4 even when ffmpeg is available")
    return p


def _resolve(args) -> dict:
    """Check everything that can be checked without compiling; returns what `main` needs."""
    from tgrf_jax.config import (
        ConfigError, EnvConfig, TrainConfig, apply_overrides, load_yaml, reward_config_from_dict,
    )

    if args.episodes < 1:
        raise RenderError(f"--episodes = {args.episodes} must be >= 1")
    if not (args.fps > 0 and math.isfinite(args.fps)):
        raise RenderError(f"--fps = {args.fps} must be > 0")
    if args.stride < 1:
        raise RenderError(f"--stride = {args.stride} must be >= 1")
    if not 10 <= args.dpi <= 600:
        raise RenderError(f"--dpi = {args.dpi} must be between 10 and 600")
    if args.seed < 0:
        raise RenderError(f"--seed = {args.seed} must be >= 0")
    out = pathlib.Path(args.out)
    if out.exists() and not out.is_dir():
        raise RenderError(f"--out {str(out)!r} exists and is not a directory")
    if args.no_frames and args.no_gif and (args.no_mp4 or ffmpeg_path() is None):
        raise RenderError("nothing to write: --no-frames and --no-gif" + (" and --no-mp4" if args.no_mp4 else
                                                                           " (and ffmpeg is not on PATH for an MP4)"))
    run_dir = None
    if args.source is not None:
        src = pathlib.Path(args.source)
        if src.is_dir():
            run_dir = src
        elif not src.exists():
            raise RenderError(f"{args.source!r} does not exist (expected a tgrf-train run directory or a YAML config)")
        elif not args.policy:
            raise RenderError(f"{args.source!r} is a config file: name the robot with --policy "
                              f"{'|'.join(POLICY_CHOICES)} (a trained policy needs its RUN_DIR)")
    elif not args.policy:
        raise RenderError(f"give a RUN_DIR or --policy {'|'.join(POLICY_CHOICES)}")
    if args.step is not None and run_dir is None:
        raise RenderError("--step selects a checkpoint of a RUN_DIR; no RUN_DIR given")

    try:
        if run_dir is not None:
            from tgrf_jax.train.loop import load_run_config

            config = load_run_config(run_dir)
            if args.overrides:
                bad = [o for o in args.overrides if o.split(".", 1)[0] not in ("env", "reward")]
                if bad:
                    raise ConfigError(f"with a RUN_DIR only env.* and reward.* can be overridden, not {bad}")
                config = TrainConfig.from_dict(apply_overrides(config.to_dict(), args.overrides))
            env_config, reward_config = config.env, config.reward
        else:
            config = None
            data = apply_overrides(load_yaml(args.source) if args.source else {}, args.overrides)
            unknown = set(data) - {"env", "reward"}
            if unknown:
                raise ConfigError(f"unknown config section(s) {sorted(unknown)}; tgrf-render reads: env, reward")
            env_config, reward_config = EnvConfig.from_dict(data.get("env")), reward_config_from_dict(data.get("reward"))
    except ConfigError as e:
        raise RenderError(str(e)) from None
    return dict(run_dir=run_dir, config=config, env_config=env_config, reward_config=reward_config, out=out)


def main(argv: Sequence[str] | None = None) -> int:
    """`tgrf-render`: returns the exit status (0 ok, 2 invalid input)."""
    args = _parser().parse_args(argv)
    try:
        r = _resolve(args)
    except RenderError as e:
        print(f"tgrf-render: error: {e}", file=sys.stderr)
        return 2

    import jax

    from tgrf_jax import compile_cache
    from tgrf_jax.env import CrowdNavEnv
    from tgrf_jax.policies import baseline

    compile_cache.enable()
    env = CrowdNavEnv(r["env_config"], r["reward_config"])
    policies = []
    if r["run_dir"] is not None:
        from tgrf_jax.train.checkpoint import CheckpointError
        from tgrf_jax.train.loop import restore_run
        from tgrf_jax.train.policy import LearnedPolicy
        from tgrf_jax.train.ppo import make_network_for

        try:
            _, state = restore_run(r["run_dir"], args.step)
        except (CheckpointError, ValueError) as e:
            print(f"tgrf-render: error: {e}", file=sys.stderr)
            return 2
        policies.append((f"learned (update {int(state.update)})", "learned",
                         LearnedPolicy(make_network_for(r["config"]), state.params)))
    for name in args.policy or ():
        if name not in [p[1] for p in policies]:
            policies.append((name, name, baseline(name)))

    out = r["out"]
    out.mkdir(parents=True, exist_ok=True)
    mp4 = False if args.no_mp4 else None
    if not args.no_mp4 and ffmpeg_path() is None:
        print("tgrf-render: ffmpeg is not on PATH: writing PNG frames and GIFs only", flush=True)
    print(f"{env} on {jax.devices()[0].platform}; {args.episodes} episode(s) per policy, seed {args.seed}", flush=True)
    summary = {"env": repr(env), "seed": args.seed, "source": None if args.source is None else str(args.source),
               "episodes": []}
    n_files = 0
    for label, slug, policy in policies:
        start = time.perf_counter()
        print(f"{label}: recording {args.episodes} episode(s) ...", flush=True)
        episodes = record_episodes(env, policy, eval_key(args.seed), args.episodes, label=label)
        print(f"  recorded in {time.perf_counter() - start:.1f} s (compile included)", flush=True)
        for ep in episodes:
            t0 = time.perf_counter()
            paths = save_episode(ep, out / slug, frames=not args.no_frames, gif=not args.no_gif, mp4=mp4,
                                 fps=args.fps, dpi=args.dpi, stride=args.stride)
            files = [str(p) for p in paths["frames"]] + [str(paths[k]) for k in ("gif", "mp4") if paths[k]]
            n_files += len(files)
            row = dict(ep.summary(), policy=slug, gif=paths["gif"] and str(paths["gif"]),
                       mp4=paths["mp4"] and str(paths["mp4"]), frames=len(paths["frames"]),
                       frame_dir=str(out / slug / f"ep{ep.index:03d}") if paths["frames"] else None)
            summary["episodes"].append(row)
            made = ", ".join(x for x in (paths["gif"] and str(paths["gif"]), paths["mp4"] and str(paths["mp4"]),
                                        paths["frames"] and f"{len(paths['frames'])} frames in {row['frame_dir']}")
                             if x)
            print(f"  episode {ep.index}: {ep.outcome} after {ep.duration:.2f} s ({ep.steps} steps), return "
                  f"{ep.ret:+.2f} -> {made} [{time.perf_counter() - t0:.1f} s]", flush=True)
    summary_path = out / "summary.json"
    summary_path.write_text(json.dumps(summary, indent=2))
    print(f"wrote {n_files + 1} files under {out}/ (index: {summary_path})")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
