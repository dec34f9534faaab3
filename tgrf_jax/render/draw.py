"""Drawing recorded episodes with matplotlib. Conventions (the colours of the paper's Fig. 5):

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
    "goal": "#2ca02c", "collision": "#7f0000", "disc": "#d62728", "pot": "#1f77b4", "pred": "#ff8c1a",
    "kinematic": "#9467bd",
}
TERM_LABELS = {
    "goal": "r_goal", "collision": "r_col", "disc": "r_disc", "pot": "r_pot", "pred": "r_pred",
    "kinematic": "r_spin + r_back",
}
OUTCOME_COLORS = {"running": "#333333", "success": "#1a7f1a", "collision": "#b00000", "timeout": "#8a6d00"}


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
