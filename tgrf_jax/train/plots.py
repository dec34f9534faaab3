"""Learning-curve figure from a run's metrics CSV.

Figures are built on their own Agg canvas rather than through pyplot, so writing a PNG neither needs a display
nor switches the backend of a Jupyter session that called the trainer."""

from __future__ import annotations

import csv
import pathlib


def read_metrics(path) -> list[dict]:
    with open(path, newline="") as f:
        return [
            {k: float(v) if v not in ("", None) else float("nan") for k, v in row.items()} for row in csv.DictReader(f)
        ]


def plot_learning_curve(csv_path, png_path, title: str = "") -> pathlib.Path:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rows = read_metrics(csv_path)
    png_path = pathlib.Path(png_path)
    fig = Figure(figsize=(15, 4))
    FigureCanvasAgg(fig)
    ax_ret, ax_rate, ax_loss = fig.subplots(1, 3)
    if rows:
        steps = [r["env_steps"] for r in rows]
        ax_ret.plot(steps, [r["episode_return"] for r in rows], color="C0")
        for key, color in (("success_rate", "C2"), ("collision_rate", "C3"), ("timeout_rate", "C7")):
            ax_rate.plot(steps, [r[key] for r in rows], color=color, label=key.replace("_rate", ""))
        ax_loss.plot(steps, [r["vf_loss"] for r in rows], color="C1", label="value loss")
        ax_ent = ax_loss.twinx()
        ax_ent.plot(steps, [r["entropy"] for r in rows], color="C4", label="entropy")
        ax_ent.set_ylabel("entropy")
    ax_ret.set(xlabel="env steps", ylabel="mean episode return", title="return (training episodes)")
    ax_rate.set(xlabel="env steps", ylabel="rate", ylim=(-0.02, 1.02), title="outcomes (training episodes)")
    ax_rate.legend(loc="best")
    ax_loss.set(xlabel="env steps", ylabel="value loss", title="losses")
    for ax in (ax_ret, ax_rate, ax_loss):
        ax.grid(alpha=0.3)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    png_path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png_path, dpi=100)
    return png_path
