"""Drawing recorded episodes with matplotlib. Conventions (the colours of the paper's Fig. 5):

* robot: yellow disc with its velocity as a short black tick; goal: a star inside the goal-tolerance circle;
* humans inside the sensor range (the env's `visible_mask`): solid blue; humans outside it: pale red (with
  `env.occlusion`, humans hidden behind an obstacle are pale red too: the robot does not see them);
* predicted positions (t+1..t+K) of visible humans, as the robot observes them: orange dots, fading with k;
* sensor range: dashed grey circle of radius r_robot + sensor_range around the robot (the range is edge-to-edge,
  so a human is visible exactly when its body reaches into this circle);
* danger zone: a ring of radius r_robot + d_disc around the robot. d_disc is an edge-to-edge distance, so the
  robot is in the danger zone exactly when a human's body overlaps this ring; one ring around the robot shows the
  same condition as a ring of r_human + d_disc around every human, without twenty overlapping rings. It fills red
  on danger steps;
* trajectories so far: the robot's whole path (orange), the humans' recent trails (grey; broken where a human
  respawns);
* static obstacles: filled grey polygons, wall segments as thick dark grey lines (in every frame);
* LiDAR (`show_rays=True`, off by default): a thin teal line from the robot to the end of every ray, a dot where a
  ray hits something (obstacle or human); rays that hit nothing end faintly at the range;
* a caption with time, step, visible count, nearest distance (and nearest obstacle), step reward, return and, at
  the end, the outcome.

Figures are built on `matplotlib.figure.Figure` with an Agg canvas, never through pyplot, so nothing here touches
the global backend or shows stray figures in notebooks.
"""

from __future__ import annotations

import numpy as np

from tgrf_jax.render.record import Episode

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
    "goal": "#2ca02c",
    "collision": "#7f0000",
    "disc": "#d62728",
    "pot": "#1f77b4",
    "pred": "#ff8c1a",
    "kinematic": "#9467bd",
}
TERM_LABELS = {
    "goal": "r_goal",
    "collision": "r_col",
    "disc": "r_disc",
    "pot": "r_pot",
    "pred": "r_pred",
    "kinematic": "r_spin + r_back",
}
OUTCOME_COLORS = {
    "running": "#333333",
    "success": "#1a7f1a",
    "collision": "#b00000",
    "timeout": "#8a6d00",
    "obstacle_collision": "#7b1fa2",
}
OUTCOME_LABELS = {
    "running": "running",
    "success": "success",
    "collision": "collision",
    "timeout": "timeout",
    "obstacle_collision": "obstacle collision",
}
OBSTACLE_COLOR = "#9a9a9a"
OBSTACLE_EDGE = "#474747"
WALL_WIDTH = 4.0  # points: a wall segment has no thickness, so it is drawn as a thick line
LIDAR_COLOR = "#009e9e"


def outcome_label(outcome: str) -> str:
    """How an outcome name is written in figures ("obstacle_collision" -> "obstacle collision")."""
    return OUTCOME_LABELS.get(outcome, outcome.replace("_", " "))


def _clip_segment(a: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray | None:
    """The part (2, 2) of segment a-b inside the box [lo, hi] (Liang-Barsky), None when none is."""
    d = b - a
    t0, t1 = 0.0, 1.0
    for p, q in ((-d[0], a[0] - lo[0]), (d[0], hi[0] - a[0]), (-d[1], a[1] - lo[1]), (d[1], hi[1] - a[1])):
        if p == 0:
            if q < 0:
                return None
            continue
        r = q / p
        if p < 0:
            t0 = max(t0, r)
        else:
            t1 = min(t1, r)
        if t0 > t1:
            return None
    return np.stack([a + t0 * d, a + t1 * d])


def _edges(polygon: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The edges of a polygon (V, 2): one for a wall segment (2 vertices), V (closed) otherwise."""
    if len(polygon) == 2:
        return [(polygon[0], polygon[1])]
    return list(zip(polygon, np.roll(polygon, -1, axis=0)))


def view_limits(ep: Episode, margin: float = 0.8, obstacle_reach: float = 1.5) -> tuple[float, float, float, float]:
    """A square window holding the robot, its goal and every human of the whole episode (fixed over frames), and
    the obstacles near them: the parts of obstacle edges within `obstacle_reach` metres of the box around the
    robot, goal and humans (a corridor's long walls are cut there instead of zooming out to their ends)."""
    pts = [ep.robot_pos, ep.goal[None]]
    if ep.num_humans:
        pts.append(ep.human_pos.reshape(-1, 2))
    pts = np.concatenate(pts)
    pts = pts[np.isfinite(pts).all(axis=1)]  # NaN: an empty slot of a replayed recording
    if ep.obstacles:
        lo, hi = pts.min(0) - obstacle_reach, pts.max(0) + obstacle_reach
        near = [c for poly in ep.obstacles for a, b in _edges(poly) if (c := _clip_segment(a, b, lo, hi)) is not None]
        if near:
            pts = np.concatenate([pts] + near)
    lo, hi = pts.min(0) - margin - 0.5, pts.max(0) + margin + 0.5
    centre, half = (lo + hi) / 2, (hi - lo).max() / 2
    return centre[0] - half, centre[0] + half, centre[1] - half, centre[1] + half


def _trail_segments(points: np.ndarray, max_jump: float) -> list[np.ndarray]:
    """Split a (T, 2) track wherever it jumps further than `max_jump` in one step (a respawn) or is NaN (an empty
    slot of a replayed recording)."""
    if len(points) < 2:
        return []
    jumps = np.nonzero(~(np.linalg.norm(np.diff(points, axis=0), axis=-1) <= max_jump))[0] + 1
    return [seg for seg in np.split(points, jumps) if len(seg) >= 2 and np.isfinite(seg).all()]


def _legend_handles(ep: Episode, show_rays: bool = False):
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    dot = dict(marker="o", linestyle="none", markersize=10)
    unseen = "human, out of sight" if ep.occlusion else "human, out of range"  # occlusion: range or a wall
    handles = [
        Line2D([], [], markerfacecolor=ROBOT_COLOR, markeredgecolor="black", label="robot", **dot),
        Line2D(
            [],
            [],
            marker="*",
            linestyle="none",
            markersize=13,
            markerfacecolor=GOAL_COLOR,
            markeredgecolor="black",
            label="goal",
        ),
        Line2D(
            [], [], markerfacecolor=VISIBLE_COLOR, markeredgecolor=VISIBLE_EDGE, label="human, in sensor range", **dot
        ),
        Line2D([], [], markerfacecolor=UNSEEN_COLOR, markeredgecolor=UNSEEN_EDGE, label=unseen, **dot),
        Line2D([], [], color=PRED_COLOR, marker="o", markersize=4, linewidth=1.3, label="predicted positions"),
        Line2D([], [], color="#606060", linestyle="--", label="sensor range"),
        Line2D([], [], color=DANGER_COLOR, linestyle=":", linewidth=1.5, label=f"danger zone (d_disc {ep.d_disc:g} m)"),
        Line2D([], [], color=PATH_COLOR, linewidth=2.2, label="robot path"),
    ]
    if ep.pred_pos is None:
        handles.pop(4)
    if any(len(p) >= 3 for p in ep.obstacles):
        handles.append(Patch(facecolor=OBSTACLE_COLOR, edgecolor=OBSTACLE_EDGE, label="obstacle"))
    if any(len(p) == 2 for p in ep.obstacles):
        handles.append(Line2D([], [], color=OBSTACLE_EDGE, linewidth=WALL_WIDTH, label="wall"))
    if show_rays:
        handles.append(
            Line2D(
                [],
                [],
                color=LIDAR_COLOR,
                linewidth=0.8,
                marker="o",
                markersize=3.5,
                label=f"LiDAR, {ep.lidar_rays} rays",
            )
        )
    return handles


class FramePainter:
    """Draws the frames of one episode onto an axes: the artists are built once, `update(t)` moves them.

    `humans` (an EllipseCollection, gid "humans") holds one disc per human in human-index order, coloured
    `VISIBLE_COLOR` or `UNSEEN_COLOR` from the env's visibility mask of the frame. The episode's obstacles are
    `obstacles` (a PolyCollection of the polygons, gid "obstacles") and `walls` (a LineCollection of the wall
    segments, gid "walls"), None where the episode has none. With `show_rays` (the episode needs LiDAR scans:
    `env.lidar_rays` > 0) `rays` (a LineCollection, gid "lidar_rays") holds one segment per ray from the robot to
    its end point and `ray_hits` (gid "lidar_hits") the points where rays hit something.
    """

    def __init__(
        self,
        ax,
        ep: Episode,
        *,
        trail_steps: int | None = 20,
        show_legend: bool = True,
        limits=None,
        title: str | None = None,
        show_rays: bool = False,
    ):
        from matplotlib.collections import EllipseCollection, LineCollection, PolyCollection
        from matplotlib.patches import Circle

        if show_rays and ep.lidar is None:
            raise ValueError(
                "show_rays needs LiDAR scans, and this episode's env has none: set env.lidar_rays > 0 "
                "(rays per scan) to record them"
            )
        self.ax, self.ep, self.trail_steps, self.show_rays = ax, ep, trail_steps, bool(show_rays)
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
        self.sensor_fill = ax.add_patch(
            Circle(r0, ep.robot_radius + ep.sensor_range, facecolor="#808080", alpha=0.06, edgecolor="none", zorder=0)
        )
        self.sensor_edge = ax.add_patch(
            Circle(
                r0,
                ep.robot_radius + ep.sensor_range,
                fill=False,
                edgecolor="#606060",
                linestyle="--",
                linewidth=1.0,
                zorder=1,
                gid="sensor_range",
            )
        )
        self.danger_fill = ax.add_patch(
            Circle(r0, ep.robot_radius + ep.d_disc, facecolor=DANGER_COLOR, alpha=0.07, edgecolor="none", zorder=2)
        )
        self.danger_edge = ax.add_patch(
            Circle(
                r0,
                ep.robot_radius + ep.d_disc,
                fill=False,
                edgecolor=DANGER_COLOR,
                linestyle=":",
                linewidth=1.3,
                zorder=2,
                gid="danger_zone",
            )
        )
        # Goal (it does not move, but is drawn with the moving artists to keep the stacking order).
        self.goal_ring = ax.add_patch(
            Circle(ep.goal, ep.goal_tolerance, fill=False, edgecolor=GOAL_COLOR, linewidth=1.2, zorder=3)
        )
        (self.goal_star,) = ax.plot(
            *ep.goal,
            marker="*",
            markersize=16,
            color=GOAL_COLOR,
            markeredgecolor="black",
            markeredgewidth=0.6,
            zorder=3,
            linestyle="none",
        )
        # Static obstacles (drawn with the moving artists, so that every frame stacks them the same way).
        polygons = [p for p in ep.obstacles if len(p) >= 3]
        walls = [p for p in ep.obstacles if len(p) == 2]
        self.obstacles = (
            ax.add_collection(
                PolyCollection(
                    polygons,
                    facecolors=OBSTACLE_COLOR,
                    edgecolors=OBSTACLE_EDGE,
                    linewidths=1.2,
                    zorder=1.7,
                    gid="obstacles",
                ),
                autolim=False,
            )
            if polygons
            else None
        )
        self.walls = (
            ax.add_collection(
                LineCollection(
                    walls, colors=OBSTACLE_EDGE, linewidths=WALL_WIDTH, capstyle="round", zorder=1.7, gid="walls"
                ),
                autolim=False,
            )
            if walls
            else None
        )
        # LiDAR rays (over the obstacles, under the agents) and their hits.
        self.rays = self.ray_hits = None
        if self.show_rays:
            self.rays = ax.add_collection(
                LineCollection([], colors=LIDAR_COLOR, linewidths=0.7, zorder=3.5, gid="lidar_rays"), autolim=False
            )
            # the hits lie on the humans' edges: drawn over the discs
            self.ray_hits = ax.scatter(
                np.zeros(0), np.zeros(0), s=9, color=LIDAR_COLOR, edgecolors="none", zorder=9.5, gid="lidar_hits"
            )
        # Trajectories.
        self.trails = ax.add_collection(
            LineCollection([], colors="#7a7a7a", linewidths=1.0, alpha=0.55, zorder=4), autolim=False
        )
        (self.path,) = ax.plot([], [], color=PATH_COLOR, linewidth=2.2, zorder=5, solid_capstyle="round")
        # Humans, in human-index order.
        n = ep.num_humans
        self.humans = EllipseCollection(
            np.zeros(n),
            np.zeros(n),
            np.zeros(n),
            units="xy",
            offsets=np.zeros((n, 2)),
            offset_transform=ax.transData,
            linewidths=1.0,
            zorder=8,
            gid="humans",
        )
        ax.add_collection(self.humans, autolim=False)
        # Observed predictions of the visible humans (over the humans, fading with the horizon).
        self.pred_lines = ax.add_collection(
            LineCollection([], colors=PRED_COLOR, linewidths=1.3, alpha=0.9, zorder=9), autolim=False
        )
        self.pred_dots = ax.scatter(np.zeros(0), np.zeros(0), s=22, edgecolors="none", zorder=9, gid="predictions")
        # Robot and its velocity tick.
        self.robot = ax.add_patch(
            Circle(r0, ep.robot_radius, facecolor=ROBOT_COLOR, edgecolor="black", linewidth=1.3, zorder=10, gid="robot")
        )
        (self.tick,) = ax.plot([], [], color="black", linewidth=1.6, zorder=11)
        # Captions.
        box = dict(boxstyle="round,pad=0.35", facecolor="white", alpha=0.85, edgecolor="#bbbbbb")
        self.caption = ax.text(
            0.015,
            0.985,
            "",
            transform=ax.transAxes,
            va="top",
            ha="left",
            fontsize=9.5,
            family="monospace",
            zorder=20,
            bbox=box,
        )
        color = OUTCOME_COLORS.get(ep.outcome, "black")
        self.banner = ax.text(
            0.985,
            0.985,
            f"{outcome_label(ep.outcome).upper()} at {ep.duration:.2f} s",
            transform=ax.transAxes,
            va="top",
            ha="right",
            fontsize=13,
            fontweight="bold",
            color=color,
            zorder=20,
            visible=False,
            bbox=dict(boxstyle="round,pad=0.35", facecolor="white", alpha=0.9, edgecolor=color),
        )
        if show_legend:
            handles = _legend_handles(ep, self.show_rays)
            many = len(handles) > 8  # a third row: set closer, so that it fits the strip below the axes
            ax.legend(
                handles=handles,
                loc="upper center",
                bbox_to_anchor=(0.5, -0.09),
                ncol=4,
                fontsize=8 if many else 8.5,
                labelspacing=0.3 if many else 0.5,
                frameon=False,
                handlelength=1.6,
                columnspacing=1.2,
            )

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
            segs += _trail_segments(ep.human_pos[start : t + 1, i], max_jump=1.0)
        self.trails.set_segments(segs)
        self.path.set_data(ep.robot_pos[: t + 1, 0], ep.robot_pos[: t + 1, 1])

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
            self.pred_lines.set_segments(
                [np.concatenate([ep.obs_human_pos[t, j][None], ep.pred_pos[t, j]]) for j in rows]
            )
            colors = np.zeros((len(rows) * k, 4))
            colors[:, :3] = (1.0, 0.55, 0.1)
            colors[:, 3] = np.tile(np.linspace(1.0, 0.45, k), len(rows))
            self.pred_dots.set_offsets(ep.pred_pos[t, rows].reshape(-1, 2))
            self.pred_dots.set_facecolor(colors)
        else:
            self.pred_lines.set_segments([])
            self.pred_dots.set_offsets(np.zeros((0, 2)))

        if self.show_rays:
            from matplotlib.colors import to_rgba

            ends = ep.lidar_points(t)
            hit = ep.lidar[t] < ep.sensor_range * (1 - 1e-5)
            self.rays.set_segments([np.stack([rpos, e]) for e in ends])
            colors = np.zeros((len(ends), 4))
            colors[:] = to_rgba(LIDAR_COLOR)
            colors[:, 3] = np.where(hit, 0.55, 0.15)
            self.rays.set_color(colors)
            self.ray_hits.set_offsets(ends[hit].reshape(-1, 2))

        vel = ep.robot_vel[t]
        speed = float(np.linalg.norm(vel))
        if speed > 1e-6:
            tip = rpos + vel / speed * ep.robot_radius * (0.4 + 0.6 * min(speed, 1.0))
            self.tick.set_data([rpos[0], tip[0]], [rpos[1], tip[1]])
        else:
            self.tick.set_data([], [])

        n_vis = int(ep.visible[t].sum()) if ep.num_humans else 0
        d_obs = np.inf if ep.obstacle_dist is None else float(ep.obstacle_dist[t])
        lines = [
            f"t = {t * ep.dt:5.2f} s   step {t}/{ep.max_steps}",
            f"visible {n_vis}/{ep.num_humans}   d_min {dmin:.2f} m" + ("  DANGER" if in_danger else ""),
        ]
        if np.isfinite(d_obs):
            lines.append(f"nearest obstacle {d_obs:.2f} m")
        lines.append(
            f"r_t = {ep.reward[t - 1]:+.2f}   return {ep.reward[:t].sum():+.2f}"
            if t > 0
            else "r_t =   -     return +0.00"
        )
        self.caption.set_text("\n".join(lines))
        self._banner_on = t == ep.steps and ep.steps > 0
        self.banner.set_visible(self._banner_on)
        return self.animated

    @property
    def animated(self) -> list:
        """The artists `update` changes (plus the goal and the obstacles), in drawing order."""
        artists = [
            self.sensor_fill,
            self.sensor_edge,
            self.danger_fill,
            self.danger_edge,
            self.goal_ring,
            self.goal_star,
            self.trails,
            self.path,
            self.humans,
            self.pred_lines,
            self.pred_dots,
            self.robot,
            self.tick,
            self.caption,
            self.banner,
            self.obstacles,
            self.walls,
            self.rays,
            self.ray_hits,
        ]
        return sorted((a for a in artists if a is not None), key=lambda a: a.get_zorder())

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

    Keyword arguments go to `FramePainter` (trail_steps, show_legend, limits, title, show_rays). To draw many
    frames, keep the returned painter and call its `update(t)`: that is several times faster than redrawing from
    scratch.
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
    fig.suptitle(
        title
        or f"{ep.label}, episode {ep.index}: {outcome_label(ep.outcome)} after {ep.duration:.2f} s, "
        f"return {ep.ret:+.2f}"
    )
    return fig


# ------------------------------------------------------------------------------------------------ tgrf-render
