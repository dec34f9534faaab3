"""Learning curves under test conditions: every `run.eval_every` updates (and at the end of training) each run's
deterministic policy plays the fixed test episodes (`run.curve_episodes` of them, from `run.eval_seed`), as the
paper's Fig. 6 plots SR, NT, PL and ITR during training.

`PeriodicEvaluation` plugs into the outer loop's `state_fn(update, state)` seam; the chunk plan is cut at its period,
so the evaluated parameters are exactly those of the checkpoints at the same updates (`tgrf-eval --step` on a
kept checkpoint reproduces a row). Rows go to `eval_curve.csv` per run (and, in a sweep, to the long
`eval_curves.csv` of all runs); a resumed run drops the rows after its checkpoint, as for metrics.csv.
"""

from __future__ import annotations

import csv
import math
import pathlib
from collections.abc import Callable, Sequence
from typing import Any

EVAL_CURVE_CSV = "eval_curve.csv"
EVAL_CURVE_PNG = "eval_curve.png"
CURVE_METRICS = (
    "success_rate",
    "collision_rate",
    "timeout_rate",
    "nav_time",
    "path_length",
    "itr_future",
    "itr_disc",
    "mean_return",
)
CURVE_FIELDS = ("update", "env_steps", "episodes") + CURVE_METRICS
# The four panels of the paper's Fig. 6.
PANELS = (
    ("success_rate", "SR", 100.0),
    ("nav_time", "NT (s)", 1.0),
    ("path_length", "PL (m)", 1.0),
    ("itr_future", "ITR (%)", 1.0),
)


class PeriodicEvaluation:
    """state_fn: evaluates every run at multiples of `every` updates and at `total`, handing writers the rows."""

    def __init__(
        self, program, every: int, episodes: int, seed: int, writers: Sequence[Any], say: Callable[[str], None] = print
    ):
        self.program, self.every, self.episodes, self.seed = program, every, episodes, seed
        self.writers, self.say = list(writers), say

    def __call__(self, update: int, state) -> None:
        if update % self.every and update != self.program.num_updates:
            return
        evals = self.program.evaluate(state, self.episodes, self.seed)
        rows = []
        for payload in evals:
            res = payload["results"]["learned"]
            rows.append(
                {
                    "update": update,
                    "env_steps": update * self.program.batch_size,
                    "episodes": self.episodes,
                    **{k: (math.nan if res[k] is None else res[k]) for k in CURVE_METRICS},
                }
            )
        for writer in self.writers:
            writer(update, rows)
        sr = [r["success_rate"] for r in rows]
        self.say(
            f"test episodes at update {update}: success {min(sr):.2f}"
            + (f"-{max(sr):.2f} over {len(sr)} runs" if len(sr) > 1 else "")
            + f" ({self.episodes} episodes)"
        )

    def truncate(self, update: int) -> float:
        for writer in self.writers:
            writer.truncate(update)
        return 0.0


def read_curve(path) -> list[dict]:
    path = pathlib.Path(path)
    if not path.is_file():
        return []
    with open(path, newline="") as f:
        return [
            {k: (float(v) if v not in ("", None) else math.nan) if k in CURVE_FIELDS else v for k, v in row.items()}
            for row in csv.DictReader(f)
        ]


def plot_curves(groups: dict[str, list[list[dict]]], png_path, title: str = "") -> pathlib.Path:
    """Fig. 6-style panels (SR, NT, PL, ITR against env steps); `groups` maps a label to the curves of its seeds,
    drawn as their mean with a band of ± one std where there are several."""
    import numpy as np
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(16, 4))
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, len(PANELS))
    for i, (label, curves) in enumerate(groups.items()):
        curves = [c for c in curves if c]
        if not curves:
            continue
        n = min(len(c) for c in curves)
        steps = np.array([r["env_steps"] for r in curves[0][:n]])
        for ax, (key, _name, scale) in zip(axes, PANELS):
            values = np.array([[r[key] * scale for r in c[:n]] for c in curves])
            mean = np.nanmean(values, axis=0)
            ax.plot(steps, mean, color=f"C{i}", label=label)
            if len(curves) > 1:
                std = np.nanstd(values, axis=0, ddof=1)
                ax.fill_between(steps, mean - std, mean + std, color=f"C{i}", alpha=0.2)
    for ax, (_, name, _) in zip(axes, PANELS):
        ax.set(xlabel="env steps", ylabel=name, title=f"{name} (test episodes)")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="best")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    png_path = pathlib.Path(png_path)
    png_path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png_path, dpi=100)
    return png_path
