"""A tune's figures: the lineage (who copied whom, when) and the schedule the best member's ancestry followed."""

from __future__ import annotations

import pathlib

from tgrf_jax.tune.spec import TuneSpec


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_lineage(path: pathlib.Path, spec: TuneSpec, lineage: list[dict]) -> pathlib.Path:
    """Members on the y axis, updates on the x axis; an arrow from donor to member at every copy, each member's
    score at each step as the marker colour."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8, max(3, 0.3 * spec.population + 1)))
    updates = sorted({int(r["update"]) for r in lineage})
    if lineage:
        scores = [float(r["score"]) for r in lineage]
        finite = [s for s in scores if s > float("-inf")] or [0.0]
        points = ax.scatter(
            [int(r["update"]) for r in lineage],
            [int(r["member"]) for r in lineage],
            c=[max(s, min(finite)) for s in scores],
            cmap="viridis",
            s=25,
            zorder=3,
        )
        fig.colorbar(points, ax=ax, label="objective")
    for u in updates:
        for r in (r for r in lineage if int(r["update"]) == u and int(r["donor"]) != int(r["member"])):
            ax.annotate(
                "",
                xy=(u, int(r["member"])),
                xytext=(u - 0.35 * spec.interval, int(r["donor"])),
                arrowprops=dict(arrowstyle="->", color="tab:red", lw=0.8),
            )
    ax.set_xlabel("update")
    ax.set_ylabel("member")
    ax.set_title("lineage: red arrows from the member copied to the member replaced")
    ax.set_ylim(-0.5, spec.population - 0.5)
    ax.set_xlim(0, spec.base_config.ppo.num_updates)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_schedule(path: pathlib.Path, spec: TuneSpec, schedule: list[dict]) -> pathlib.Path:
    """One panel per searched field: its value along the best member's ancestry, as a step function."""
    plt = _pyplot()
    fig, axes = plt.subplots(len(spec.dims), 1, figsize=(7, 2.4 * len(spec.dims)), sharex=True, squeeze=False)
    updates = [int(r["update"]) for r in schedule] + [spec.base_config.ppo.num_updates]
    for ax, dim in zip(axes[:, 0], spec.dims):
        values = [float(r[dim.name]) for r in schedule]
        ax.step(updates, values + values[-1:], where="post")
        ax.set_ylabel(dim.name)
        ax.set_ylim(dim.low, dim.high)
        if dim.log:
            ax.set_yscale("log")
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("update")
    axes[0, 0].set_title("the schedule the tune found (the best member's ancestry)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
