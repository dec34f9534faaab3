"""Episode rendering: `record` plays episodes in one jitted scan, `draw` paints them with matplotlib, `export`
writes PNG frames, GIFs and MP4s or builds inline players. The `tgrf-render` command is `tgrf_jax.cli.render`.

Figures are built on `matplotlib.figure.Figure` with an Agg canvas, never through pyplot, so nothing here touches
the global backend or shows stray figures in notebooks.
"""

from tgrf_jax.render.draw import (
    DANGER_COLOR,
    GOAL_COLOR,
    LIDAR_COLOR,
    OBSTACLE_COLOR,
    OBSTACLE_EDGE,
    OUTCOME_COLORS,
    OUTCOME_LABELS,
    PATH_COLOR,
    PRED_COLOR,
    ROBOT_COLOR,
    TERM_COLORS,
    TERM_LABELS,
    UNSEEN_COLOR,
    UNSEEN_EDGE,
    VISIBLE_COLOR,
    VISIBLE_EDGE,
    FramePainter,
    draw_frame,
    new_figure,
    outcome_label,
    plot_frame,
    plot_reward_terms,
    view_limits,
)
from tgrf_jax.render.export import (
    animate,
    ffmpeg_path,
    gif_bytes,
    save_episode,
    show,
    to_jshtml,
)
from tgrf_jax.render.record import Episode, eval_key, record_episodes

__all__ = [
    "DANGER_COLOR",
    "GOAL_COLOR",
    "LIDAR_COLOR",
    "OBSTACLE_COLOR",
    "OBSTACLE_EDGE",
    "OUTCOME_COLORS",
    "OUTCOME_LABELS",
    "PATH_COLOR",
    "PRED_COLOR",
    "ROBOT_COLOR",
    "TERM_COLORS",
    "TERM_LABELS",
    "UNSEEN_COLOR",
    "UNSEEN_EDGE",
    "VISIBLE_COLOR",
    "VISIBLE_EDGE",
    "Episode",
    "FramePainter",
    "animate",
    "draw_frame",
    "eval_key",
    "ffmpeg_path",
    "gif_bytes",
    "new_figure",
    "outcome_label",
    "plot_frame",
    "plot_reward_terms",
    "record_episodes",
    "save_episode",
    "show",
    "to_jshtml",
    "view_limits",
]
