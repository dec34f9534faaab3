"""An experiment's report from its rows' sweep results: Markdown and CSV, our value beside the paper's.

Per row and compared value (e.g. reward scheme): the success rate as mean ± sample std over the seeds, and the
best seed's (highest SR) SR, NT, PL and both ITRs, as the paper's tables report them. Rows still running show
'…'. The figures tgrf-sweep draws (heat maps, curves) are copied next to the report.
"""

from __future__ import annotations

import csv
import io
import json
import math
import pathlib
import shutil

import numpy as np

from tgrf_jax.config import ConfigError
from tgrf_jax.experiments.spec import BASELINES, Experiment, Row
from tgrf_jax.storage.files import write_atomic

REPORT_MD = "report.md"
TEST_FILE = "test_eval.json"  # a run's final policy on its row's test episodes (tgrf_jax.experiments.testing)
COMPARE_DIR = "compare"  # <row>/compare/<policy>.json: a compared policy on the same episodes
REPORT_CSV = "report.csv"
CSV_FIELDS = (
    "experiment",
    "row",
    "label",
    "axis",
    "value",
    "damaged",
    "seeds",
    "sr_mean",
    "sr_std",
    "best_seed",
    "sr",
    "nt",
    "pl",
    "itr",
    "itr_disc",
    "paper_sr_mean",
    "paper_sr_std",
    "paper_sr",
    "paper_nt",
    "paper_pl",
    "paper_itr",
    "row_wall_s",
    "commit",
)
_FIGURES = ("heatmap.png", "grid_metrics.png", "learning_curves.png", "eval_curves.png")


def _float(x) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return math.nan


# evals.csv columns every finished run fills with a finite number (the others may be NaN: no successful episode
# gives no navigation time)
_REQUIRED = ("success_rate",)
_NUMBERS = ("collision_rate", "timeout_rate", "nav_time", "path_length", "itr_future", "itr_disc")


def read_evals(row_dir: pathlib.Path) -> list[dict]:
    path = row_dir / "evals.csv"
    if not path.is_file():
        return []
    return _read_csv(path)


def _read_csv(path: pathlib.Path) -> list[dict]:
    try:
        with open(path, newline="", encoding="utf-8") as f:
            return list(csv.DictReader(f))
    except (OSError, UnicodeDecodeError, csv.Error):
        return [{}]  # unreadable: `evals_problem` names it


def _expected_runs(row_dir: pathlib.Path) -> int | None:
    """The number of runs the row's sweep.yaml lists (None where it cannot be read)."""
    import yaml

    try:
        runs = yaml.safe_load((row_dir / "sweep.yaml").read_text()).get("runs")
        return len(runs) if isinstance(runs, list) else None
    except Exception:  # a missing or damaged sweep.yaml: the row's own resume reports it
        return None


def evals_problem(row_dir: pathlib.Path) -> str | None:
    """What is wrong with a row's evals.csv (missing, cut, a value that is not a number), or None if every run of
    the row has its numbers."""
    path = row_dir / "evals.csv"
    if not path.is_file():
        return "evals.csv is missing"
    runs = _read_csv(path)
    expected = _expected_runs(row_dir)
    if runs == [{}] and path.stat().st_size:
        return "evals.csv is not readable UTF-8 CSV"
    if expected is not None and len(runs) != expected:
        return f"evals.csv holds {len(runs)} runs, its sweep {expected}"
    if not runs:
        return "evals.csv holds no runs"
    for i, r in enumerate(runs, start=2):
        seed = r.get("seed")
        if seed is None or not str(seed).isdigit():
            return f"evals.csv line {i}: seed = {str(seed)[:20]!r} is not a whole number"
        for k in _REQUIRED:
            if not math.isfinite(_float(r.get(k))):
                return f"evals.csv line {i}: {k} = {str(r.get(k))[:20]!r} is not a finite number"
        for k in _NUMBERS:
            if k in r and r[k] not in ("", "nan") and math.isnan(_float(r[k])):
                return f"evals.csv line {i}: {k} = {str(r[k])[:20]!r} is not a number"
    return None


def cell(runs: list[dict]) -> dict:
    """SR mean ± std over seeds (in %) and the best seed's metrics, from one grid point's evals.csv rows (checked
    by `evals_problem`: every success rate is a number, so the mean and the seed count cover the same runs)."""
    if not runs:
        return {}
    sr = np.array([_float(r["success_rate"]) * 100.0 for r in runs])
    best = runs[int(np.argmax(sr))]
    return {
        "seeds": len(runs),
        "sr_mean": float(np.mean(sr)),
        "sr_std": float(np.std(sr, ddof=1)) if len(runs) > 1 else math.nan,
        "best_seed": int(best["seed"]),
        "sr": _float(best["success_rate"]) * 100.0,
        "nt": _float(best.get("nav_time")),
        "pl": _float(best.get("path_length")),
        "itr": _float(best.get("itr_future")),
        "itr_disc": _float(best.get("itr_disc")),
    }


def read_provenance(row_dir: pathlib.Path) -> dict | None:
    """A row's provenance.json (None where there is none); raises ConfigError naming a damaged one."""
    path = row_dir / "provenance.json"
    if not path.is_file():
        return None
    try:
        prov = json.loads(path.read_text(encoding="utf-8"))
        if (
            not isinstance(prov, dict)
            or not isinstance(prov.get("invocations"), list)
            or not all(isinstance(i, dict) for i in prov["invocations"])
        ):
            raise ValueError("no list of invocations")
        float(prov.get("wall_s", 0.0))
    except (OSError, UnicodeDecodeError, ValueError, TypeError) as e:
        raise ConfigError(
            f"{str(path)!r} is damaged ({type(e).__name__}: {str(e)[:80]}); restore it, or move it "
            "aside to record the row's invocations afresh"
        ) from None
    return prov


def _provenance(row_dir: pathlib.Path) -> dict:
    prov = read_provenance(row_dir)
    if prov is None:
        return {}
    invocations = prov.get("invocations") or []
    last = invocations[-1] if invocations else {}

    def distinct(key):  # in order of first use: a row may train over several commits and machines
        return list(dict.fromkeys(i[key] for i in invocations if i.get(key)))

    commits = distinct("commit")
    return {
        "row_wall_s": prov.get("wall_s"),
        "commit": last.get("commit"),
        "finished": last.get("finished"),
        "invocations": len(invocations),
        "machines": "; ".join(distinct("machine")),
        "commits": commits[0] if len(commits) < 2 else f"{commits[0]} to {commits[-1]}",
    }


def collect(exp: Experiment, out: pathlib.Path) -> list[dict]:
    """One record per (row, value of the compared axis): ours, the paper's, and the row's provenance."""
    axis = exp.column_axis
    records = []
    for row in exp.rows:
        runs = read_evals(out / row.name)
        problem = evals_problem(out / row.name) if (out / row.name / "evals.csv").is_file() else None
        if problem:
            runs = []
        elif row.test:  # the row's results are its tests, once every run has one
            runs = tested_runs(out / row.name)
        prov = _provenance(out / row.name) if runs else {}
        for value in row.grid[0][1]:
            ours = cell([r for r in runs if r.get(axis) == str(value)])
            if problem:
                ours = {"damaged": f"damaged ({problem}): rerun tgrf-reproduce {exp.name} --rows {row.name}"}
            paper = row.paper.get(str(value), {})
            rec = {
                "experiment": exp.name,
                "row": row.name,
                "label": row.label,
                "axis": axis,
                "value": str(value),
                **ours,
                **{f"paper_{k}": v for k, v in paper.items()},
            }
            rec.update({k: prov.get(k) for k in ("row_wall_s", "commit")})
            rec.update({f"_{k}": prov.get(k) for k in ("invocations", "commits", "machines", "finished")})
            records.append(rec)
    return records


def _num(x, fmt="{:.2f}") -> str:
    return "…" if x is None or (isinstance(x, float) and math.isnan(x)) else fmt.format(x)


def _pair(ours: str, paper: str | None) -> str:
    return ours if paper is None else f"{ours} ({paper})"


def format_table(exp: Experiment, records: list[dict]) -> str:
    """The paper's layout: one block per compared value, one line per row; cells 'ours (paper)'."""
    lines = [
        "| reward | navigation method | SR mean ± std (%) | SR (%) | NT (s) | PL (m) | ITR (%) | ITR disc (%) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for value in exp.column_values:
        first = True
        for rec in (r for r in records if r["value"] == str(value)):
            has_paper = "paper_sr" in rec
            pp = lambda k, fmt="{:.2f}", rec=rec, has_paper=has_paper: (
                _num(rec.get(f"paper_{k}"), fmt) if has_paper else None
            )
            sr_mean = (
                rec["damaged"]
                if "damaged" in rec
                else "…"
                if "sr_mean" not in rec
                else (f"{rec['sr_mean']:.1f}" + (f" ± {rec['sr_std']:.1f}" if not math.isnan(rec["sr_std"]) else ""))
            )
            paper_mean = (
                f"{rec['paper_sr_mean']:.1f} ± {rec['paper_sr_std']:.1f}"
                if has_paper and "paper_sr_mean" in rec
                else ("–" if has_paper else None)
            )
            lines.append(
                "| "
                + " | ".join(
                    [
                        exp.column_label(value) if first else "",
                        rec["label"],
                        _pair(sr_mean, paper_mean),
                        _pair(_num(rec.get("sr"), "{:.1f}"), pp("sr", "{:.1f}")),
                        _pair(_num(rec.get("nt")), pp("nt")),
                        _pair(_num(rec.get("pl")), pp("pl")),
                        _pair(_num(rec.get("itr")), pp("itr")),
                        _num(rec.get("itr_disc")),
                    ]
                )
                + " |"
            )
            first = False
    return "\n".join(lines)


def _mean_std(values, scale: float, fmt: str) -> str:
    """'mean ± sample std' of the finite numbers among `values` x `scale` ('mean' alone for one, '–' for none)."""
    x = np.array([_float(v) * scale for v in values])
    x = x[np.isfinite(x)]
    if not x.size:
        return "–"
    return fmt.format(x.mean()) + (f" ± {fmt.format(x.std(ddof=1))}" if x.size > 1 else "")


def _grid_points(exp: Experiment, row: Row, out: pathlib.Path) -> str:
    """Mean ± std over seeds of SR and both ITRs for every grid point of a row (heat maps, curves)."""
    runs = read_evals(out / row.name)
    problem = evals_problem(out / row.name) if runs else None
    if problem:
        return f"damaged ({problem}): rerun tgrf-reproduce {exp.name} --rows {row.name}"
    names = exp.grid_names
    lines = [
        "| " + " | ".join(names) + " | seeds | SR (%) | ITR (%) | ITR disc (%) | NT (s) | PL (m) |",
        "|" + "---|" * (len(names) + 6),
    ]
    groups: dict[tuple, list[dict]] = {}
    for r in runs:
        groups.setdefault(tuple(r[n] for n in names), []).append(r)

    def ms(rs, key, scale=1.0):
        return _mean_std([r.get(key) for r in rs], scale, "{:.1f}")

    for key, rs in groups.items():
        lines.append(
            "| " + " | ".join(key) + f" | {len(rs)} | {ms(rs, 'success_rate', 100.0)} | "
            f"{ms(rs, 'itr_future')} | {ms(rs, 'itr_disc')} | {ms(rs, 'nav_time')} | {ms(rs, 'path_length')} |"
        )
    return "\n".join(lines) if groups else "(no finished runs yet)"


def format_report(exp: Experiment, out: pathlib.Path, records: list[dict]) -> str:
    done = sorted({r["row"] for r in records if "sr_mean" in r})
    parts = [
        f"# {exp.title}",
        "",
        f"Rows finished: {len(done)}/{len(exp.rows)}; {exp.seeds} seeds per cell; compared inside each row: "
        + " x ".join(f"`{name}` = {', '.join(map(str, exp.axis_values(name)))}" for name in exp.grid_names)
        + ".",
    ]
    if exp.layout == "table":
        parts += [
            "",
            ("Each cell: ours (the paper's). " if any(row.paper for row in exp.rows) else "")
            + "SR mean ± sample std over seeds; SR, NT, PL and ITR of the best seed. "
            "ITR is the reference's itr_future; ITR disc is the share of steps with the nearest human closer "
            "than d_disc (ours only).",
            "",
            format_table(exp, records),
        ]
    else:
        for row in exp.rows:
            parts += ["", f"## {row.label}", "", _grid_points(exp, row, out)]
            for fig in _FIGURES:
                if (out / f"{row.name}_{fig}").is_file():
                    parts += ["", f"![{row.label}: {fig}]({row.name}_{fig})"]
    if any(row.test for row in exp.rows):
        parts += ["", "## On the test episodes", "", _tests_table(exp, out)]
    prov = [r for r in records if r.get("commit")]
    if prov:
        parts += ["", "| row | wall time | invocations | commits | machines | finished |", "|---|---|---|---|---|---|"]
        seen = set()
        for r in prov:
            if r["row"] in seen:
                continue
            seen.add(r["row"])
            wall = r["row_wall_s"] or 0.0
            parts.append(
                f"| {r['row']} | {wall / 60:.1f} min | {r['_invocations']} | {r['_commits']} | {r['_machines']} "
                f"| {r['_finished']} |"
            )
    if exp.notes:
        parts += ["", exp.notes.strip()]
    return "\n".join(parts) + "\n"


_TEST_COLUMNS = (
    ("success_rate", "SR (%)", 100.0),
    ("collision_rate", "collision (%)", 100.0),
    ("timeout_rate", "timeout (%)", 100.0),
    ("nav_time", "NT (s)", 1.0),
    ("path_length", "PL (m)", 1.0),
    ("itr_disc", "ITR disc (%)", 1.0),
    ("spl", "SPL", 1.0),
    ("personal_space_compliance", "PS compliance (%)", 1.0),
)


def _tests_table(exp: Experiment, out: pathlib.Path) -> str:
    """Per tested row: each compared value's policies (mean ± std over seeds) and every compared policy, on the
    same test episodes."""
    header = "| row | policy | seeds | " + " | ".join(label for _, label, _ in _TEST_COLUMNS) + " |"
    lines = [header, "|" + "---|" * (len(_TEST_COLUMNS) + 3)]

    def ms(values, scale):
        return _mean_std(values, scale, "{:.2f}")

    axis = exp.column_axis
    for row in (r for r in exp.rows if r.test):
        runs = tested_runs(out / row.name)
        for value in row.grid[0][1]:
            members = [r for r in runs if r.get(axis) == str(value)]
            cells = [ms([m.get(k) for m in members], scale) for k, _, scale in _TEST_COLUMNS] if members else None
            label = f"this row ({exp.column_label(value)})"
            shown = " | ".join(cells) if cells else " | ".join("…" for _ in _TEST_COLUMNS)
            lines.append(f"| {row.name} | {label} | {len(members) or '…'} | {shown} |")
        played = compared(exp, out / row.name)
        for name in exp.compare:
            result = played.get(name)
            shown = (
                " | ".join(ms([result.get(k)], scale) for k, _, scale in _TEST_COLUMNS)
                if result
                else " | ".join("…" for _ in _TEST_COLUMNS)
            )
            lines.append(f"| {row.name} | {name} | {'1' if result else '…'} | {shown} |")
    return "\n".join(lines)


def write(exp: Experiment, out) -> list[pathlib.Path]:
    """report.md and report.csv in `out` (and the rows' figures); returns the written paths."""
    out = pathlib.Path(out)
    for row in exp.rows:
        for fig in _FIGURES:
            src = out / row.name / fig
            if src.is_file():
                shutil.copyfile(src, out / f"{row.name}_{fig}")
    records = collect(exp, out)
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=CSV_FIELDS, extrasaction="ignore")
    w.writeheader()
    w.writerows(records)
    write_atomic(out / REPORT_CSV, buf.getvalue())
    write_atomic(out / REPORT_MD, format_report(exp, out, records))
    return [out / REPORT_MD, out / REPORT_CSV]


def tested_runs(row_dir: pathlib.Path) -> list[dict]:
    """The row's evals.csv rows with the metrics of each run's test in place of its final evaluation's ([] until
    every run is tested)."""
    runs = read_evals(row_dir)
    out = []
    for r in runs:
        result = _learned(row_dir / "runs" / r.get("run", "") / TEST_FILE)
        if result is None:
            return []
        out.append({**r, **{k: "" if v is None else str(v) for k, v in result.items()}})
    return out


def compared(exp: Experiment, row_dir: pathlib.Path) -> dict[str, dict]:
    """name -> the metrics of each compared policy on the row's test episodes (those played so far)."""
    out = {}
    for name in exp.compare:
        payload = _payload(row_dir / COMPARE_DIR / f"{name}.json")
        if payload is None:
            continue
        results = payload.get("results", {})
        result = results.get(name if name in BASELINES else "learned")
        if isinstance(result, dict):
            out[name] = result
    return out


def _payload(path: pathlib.Path) -> dict | None:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        return data if isinstance(data, dict) else None
    except (OSError, ValueError):
        return None


def _learned(path: pathlib.Path) -> dict | None:
    payload = _payload(path)
    result = None if payload is None else payload.get("results", {}).get("learned")
    return result if isinstance(result, dict) else None
