"""A finished sweep's tables and figures: evals.csv, summary.csv / .md (mean and std over seeds per grid point),
the learning curves and a heatmap (two gridded axes) or metric-per-value plot (one)."""

from __future__ import annotations

import csv
import math
import pathlib
import warnings

import numpy as np

from tgrf_jax.sweep.grid import GridAxis, SweepSpec, _fmt_value
from tgrf_jax.train.curves import plot_curves, read_curve
from tgrf_jax.train.directory import EVAL_CURVES_FILE, METRICS_FILE

EVALS_FILE = "evals.csv"
SUMMARY_CSV = "summary.csv"
SUMMARY_MD = "summary.md"
HEATMAP_FILE = "heatmap.png"
GRID_PLOT_FILE = "grid_metrics.png"
CURVES_FILE = "learning_curves.png"
RUNS_DIR = "runs"

# Metrics of the summary table: final evaluation (docs/reference.md, "Metrics") and the end of training.
EVAL_METRICS = (
    "success_rate",
    "collision_rate",
    "timeout_rate",
    "nav_time",
    "path_length",
    "itr_future",
    "itr_disc",
    "intrusion_dist_future",
    "intrusion_dist_disc",
    "mean_return",
)
TRAIN_METRICS = ("train_return", "train_success_rate")
TRAIN_TAIL = 0.1  # training metrics: episode-weighted over the chunks of the last 10% of updates


def _read_csv(path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _float(x) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return float("nan")


def training_tail(rows: list[dict], total_updates: int) -> dict:
    """Episode-weighted training return and success rate over the chunks of the last 10% of updates."""
    last = max(int(float(r["update"])) for r in rows) if rows else 0
    cut = last - max(1, int(math.ceil(TRAIN_TAIL * total_updates)))
    tail = [r for r in rows if int(float(r["update"])) > cut] or rows[-1:]
    eps = np.array([_float(r["episodes"]) for r in tail])
    if eps.sum() == 0:
        return {"train_return": float("nan"), "train_success_rate": float("nan")}
    ret = np.array([_float(r["episode_return"]) for r in tail])
    sr = np.array([_float(r["success_rate"]) for r in tail])
    w = eps / eps.sum()
    return {
        "train_return": float(np.nansum(w * np.where(eps > 0, ret, 0.0))),
        "train_success_rate": float(np.nansum(w * np.where(eps > 0, sr, 0.0))),
    }


def write_results(sweep_dir, spec: SweepSpec, evals: list | None) -> list[dict]:
    """evals.csv (one row per run) and summary.csv / summary.md (mean and std over seeds per grid point).
    Returns the summary rows."""
    sweep_dir = pathlib.Path(sweep_dir)
    runs = spec.runs()
    total = spec.base_config.ppo.num_updates
    per_run = []
    for i, r in enumerate(runs):
        row = {"run": r.name, "point": r.point, "seed": r.seed, **r.values}
        row.update(training_tail(_read_csv(sweep_dir / RUNS_DIR / r.name / METRICS_FILE), total))
        if evals is not None:
            res = evals[i]["results"]["learned"]
            row.update({k: (float("nan") if res.get(k) is None else res[k]) for k in EVAL_METRICS})
            row["eval_episodes"] = res["n_episodes"]
        per_run.append(row)
    metric_names = (list(EVAL_METRICS) if evals is not None else []) + list(TRAIN_METRICS)
    run_fields = (
        ["run", "point", "seed"]
        + [a.name for a in spec.axes]
        + metric_names
        + (["eval_episodes"] if evals is not None else [])
    )
    with open(sweep_dir / EVALS_FILE, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=run_fields)
        w.writeheader()
        w.writerows(per_run)

    summary = []
    for p, values in enumerate(spec.points()):
        members = [row for row in per_run if row["point"] == p]
        srow = {"point": p, **values, "seeds": len(members)}
        for m in metric_names:
            x = np.array([_float(row[m]) for row in members], float)
            x = x[np.isfinite(x)]
            srow[f"{m}_mean"] = float(np.mean(x)) if x.size else float("nan")
            srow[f"{m}_std"] = float(np.std(x, ddof=1)) if x.size > 1 else float("nan")
        summary.append(srow)
    fields = (
        ["point"]
        + [a.name for a in spec.axes]
        + ["seeds"]
        + [f"{m}_{s}" for m in metric_names for s in ("mean", "std")]
    )
    with open(sweep_dir / SUMMARY_CSV, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        w.writerows(summary)
    (sweep_dir / SUMMARY_MD).write_text(format_summary_markdown(spec, summary) + "\n")
    return summary


_LABELS = {
    "success_rate": ("SR", "{:.1%}"),
    "collision_rate": ("collision", "{:.1%}"),
    "timeout_rate": ("timeout", "{:.1%}"),
    "nav_time": ("NT (s)", "{:.2f}"),
    "path_length": ("PL (m)", "{:.2f}"),
    "itr_future": ("ITR future (%)", "{:.2f}"),
    "itr_disc": ("ITR disc (%)", "{:.2f}"),
    "intrusion_dist_future": ("dist ITR future (m)", "{:.3f}"),
    "intrusion_dist_disc": ("dist ITR disc (m)", "{:.3f}"),
    "mean_return": ("return", "{:.2f}"),
    "train_return": ("train return", "{:.2f}"),
    "train_success_rate": ("train SR", "{:.1%}"),
}


def format_summary_markdown(spec: SweepSpec, summary: list[dict]) -> str:
    """Markdown table: one row per grid point, 'mean ± std' over seeds (sample std; '–' with one seed)."""
    if not summary:
        return ""
    metrics = [m for m in list(EVAL_METRICS) + list(TRAIN_METRICS) if f"{m}_mean" in summary[0]]
    axes = [a.name for a in spec.axes]
    header = "| " + " | ".join([a.split(".", 1)[1] for a in axes] + ["seeds"] + [_LABELS[m][0] for m in metrics]) + " |"
    lines = [header, "|" + "---|" * (len(axes) + 1 + len(metrics))]
    for row in summary:
        cells = [_fmt_value(row[a]) for a in axes] + [str(row["seeds"])]
        for m in metrics:
            fmt = _LABELS[m][1]
            mean, std = row[f"{m}_mean"], row[f"{m}_std"]
            if not math.isfinite(mean):
                cells.append("n/a")
            else:
                cells.append(fmt.format(mean) + (" ± " + fmt.format(std) if math.isfinite(std) else " ± –"))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _figure(figsize, ncols: int):
    """A figure on its own Agg canvas (no pyplot: no display needed, a Jupyter session's backend is left alone)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize)
    FigureCanvasAgg(fig)
    return fig, fig.subplots(1, ncols, squeeze=False)[0]


def plot_sweep(sweep_dir, spec: SweepSpec, summary: list[dict]) -> list[pathlib.Path]:
    """learning_curves.png, plus heatmap.png (two multi-valued axes) or grid_metrics.png (one) unless the axes are
    paired."""
    sweep_dir = pathlib.Path(sweep_dir)
    out = [plot_learning_curves(sweep_dir, spec)]
    # paired points do not fill a grid: a heat map or a metric-per-value plot of them would mislead
    multi = [] if spec.paired else [a for a in spec.axes if len(a.values) > 1]
    have_eval = bool(summary) and "success_rate_mean" in summary[0]
    metrics = ["success_rate", "itr_disc", "itr_future"] if have_eval else ["train_success_rate", "train_return"]
    if len(multi) == 2:
        out.append(plot_heatmap(sweep_dir / HEATMAP_FILE, spec, summary, multi[0], multi[1], metrics))
    elif len(multi) == 1:
        out.append(plot_grid_metrics(sweep_dir / GRID_PLOT_FILE, spec, summary, multi[0], metrics))
    curves = read_curve(sweep_dir / EVAL_CURVES_FILE)
    if curves:
        groups: dict[str, dict[str, list[dict]]] = {}
        for r in spec.runs():
            label = ", ".join(f"{k.split('.', 1)[1]}={_fmt_value(v)}" for k, v in r.values.items()) or "all runs"
            groups.setdefault(label, {})[r.name] = [row for row in curves if row["run"] == r.name]
        out.append(
            plot_curves(
                {k: list(v.values()) for k, v in groups.items()},
                sweep_dir / "eval_curves.png",
                title="test episodes during training (mean over seeds, band: ± std)",
            )
        )
    return out


def _title(m: str) -> str:
    return {
        "success_rate": "success rate (eval)",
        "itr_disc": "ITR disc (%) (eval)",
        "itr_future": "ITR future (%) (eval)",
        "train_success_rate": "success rate (training, end)",
        "train_return": "return (training, end)",
    }.get(m, m)


def plot_heatmap(path, spec: SweepSpec, summary, ax_y: GridAxis, ax_x: GridAxis, metrics) -> pathlib.Path:
    """Mean over seeds of each metric over two gridded parameters (other axes: their single value)."""
    fig, axs = _figure((4.8 * len(metrics), 4.2), len(metrics))
    for ax, m in zip(axs, metrics):
        mean = np.full((len(ax_y.values), len(ax_x.values)), np.nan)
        std = np.full_like(mean, np.nan)
        for row in summary:
            i, j = ax_y.values.index(row[ax_y.name]), ax_x.values.index(row[ax_x.name])
            mean[i, j], std[i, j] = row[f"{m}_mean"], row[f"{m}_std"]
        im = ax.imshow(mean, origin="lower", cmap="viridis" if "success" in m else "magma_r", aspect="auto")
        fig.colorbar(im, ax=ax, shrink=0.85)
        pct = "success" in m
        for i in range(mean.shape[0]):
            for j in range(mean.shape[1]):
                if np.isfinite(mean[i, j]):
                    s = f"{mean[i, j]:.0%}" if pct else f"{mean[i, j]:.2f}"
                    if np.isfinite(std[i, j]):
                        s += "\n±" + (f"{std[i, j]:.0%}" if pct else f"{std[i, j]:.2f}")
                    r, g, b, _ = im.cmap(im.norm(mean[i, j]))
                    ax.text(
                        j,
                        i,
                        s,
                        ha="center",
                        va="center",
                        fontsize=8,
                        color="k" if 0.299 * r + 0.587 * g + 0.114 * b > 0.5 else "w",
                    )
        ax.set_xticks(range(len(ax_x.values)), [_fmt_value(v) for v in ax_x.values])
        ax.set_yticks(range(len(ax_y.values)), [_fmt_value(v) for v in ax_y.values])
        ax.set(xlabel=ax_x.name, ylabel=ax_y.name, title=_title(m))
    fig.suptitle(f"mean over {len(spec.seeds)} seed(s)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    return pathlib.Path(path)


def plot_grid_metrics(path, spec: SweepSpec, summary, axis: GridAxis, metrics) -> pathlib.Path:
    fig, axs = _figure((4.5 * len(metrics), 3.8), len(metrics))
    xs = np.arange(len(axis.values))
    for ax, m in zip(axs, metrics):
        mean = [next(r[f"{m}_mean"] for r in summary if r[axis.name] == v) for v in axis.values]
        std = [next(r[f"{m}_std"] for r in summary if r[axis.name] == v) for v in axis.values]
        ax.errorbar(xs, mean, yerr=np.nan_to_num(std), marker="o", capsize=3)
        ax.set_xticks(xs, [_fmt_value(v) for v in axis.values])
        ax.set(xlabel=axis.name, title=_title(m))
        ax.grid(alpha=0.3)
    fig.suptitle(f"mean ± std over {len(spec.seeds)} seed(s)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    return pathlib.Path(path)


def plot_learning_curves(sweep_dir, spec: SweepSpec) -> pathlib.Path:
    """Training return and success rate per grid point: mean over seeds, band = ± std over seeds."""
    import matplotlib

    sweep_dir = pathlib.Path(sweep_dir)
    rows = _read_csv(sweep_dir / METRICS_FILE)
    fig, (ax_ret, ax_sr) = _figure((13, 4.5), 2)
    points = spec.points()
    cmap = matplotlib.colormaps["viridis" if len(points) > 10 else "tab10"]
    for p, values in enumerate(points):
        color = cmap(p / max(len(points) - 1, 1)) if len(points) > 10 else cmap(p % 10)
        by_seed = {}
        for r in rows:
            if int(r["point"]) == p:
                by_seed.setdefault(int(r["seed"]), {})[int(float(r["update"]))] = r
        if not by_seed:
            continue
        updates = sorted(set.intersection(*[set(d) for d in by_seed.values()]))
        if not updates:
            continue
        steps = [_float(next(iter(by_seed.values()))[u]["env_steps"]) for u in updates]
        for ax, key in ((ax_ret, "episode_return"), (ax_sr, "success_rate")):
            y = np.array([[_float(d[u][key]) for u in updates] for d in by_seed.values()])
            with np.errstate(all="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns (chunks without episodes)
                mean = np.nanmean(y, axis=0)
                std = np.nanstd(y, axis=0, ddof=1) if y.shape[0] > 1 else np.zeros_like(mean)
            ax.plot(steps, mean, color=color, label=spec.point_label(values))
            if y.shape[0] > 1:
                ax.fill_between(steps, mean - std, mean + std, color=color, alpha=0.2, linewidth=0)
    ax_ret.set(xlabel="env steps per run", ylabel="mean episode return", title="return (training episodes)")
    ax_sr.set(
        xlabel="env steps per run", ylabel="success rate", ylim=(-0.02, 1.02), title="success rate (training episodes)"
    )
    for ax in (ax_ret, ax_sr):
        ax.grid(alpha=0.3)
    ax_sr.legend(
        loc="center left",
        bbox_to_anchor=(1.02, 0.5),
        fontsize=7 if len(points) > 10 else 8,
        ncol=1 if len(points) <= 20 else 2,
    )
    fig.suptitle(f"{len(points)} grid point(s): mean over {len(spec.seeds)} seed(s), band ± std")
    fig.tight_layout()
    path = sweep_dir / CURVES_FILE
    fig.savefig(path, dpi=100)
    return path
