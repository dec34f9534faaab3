"""What a training run reports after every compiled chunk, and the writers that plug into the outer loop's
`progress_fn(step, metrics)` seam: the metrics CSV, TensorBoard and the progress line.

`metrics` is a `ChunkMetrics`: one CSV row per run plus the row of all runs together. A writer that keeps a file
per run also implements `truncate(update)`, which the outer loop calls (and only it) when a run resumes from a
checkpoint older than the file's last row.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
import pathlib
from collections.abc import Callable, Sequence

import numpy as np

from tgrf_jax.fields import ConfigError
from tgrf_jax.storage.files import write_atomic
from tgrf_jax.train.ppo import METRIC_NAMES, SUMMED_METRICS

# Columns of metrics.csv: counters and timings, episode outcomes as rates, then the averaged update metrics.
CSV_FIELDS = (
    "update",
    "env_steps",
    "wall_s",
    "sps",
    "episodes",
    "episode_return",
    "success_rate",
    "collision_rate",
    "timeout_rate",
) + tuple(k for k in METRIC_NAMES if k not in SUMMED_METRICS)


@dataclasses.dataclass(frozen=True)
class ChunkMetrics:
    """One chunk of updates of G runs: `runs[i]` is run i's CSV row, `total` the row of all runs together (episode
    sums added, other metrics averaged, steps/s over all runs)."""

    update: int
    total_updates: int
    env_steps: int  # per run
    total_env_steps: int  # per run, at the end of training
    eta_s: float
    runs: tuple[dict, ...]
    total: dict


def csv_row(metrics: dict, update: int, env_steps: int, wall_s: float, sps: float) -> dict:
    """A metrics.csv row from one run's reduced chunk metrics (`METRIC_NAMES` -> scalar)."""
    m = {k: float(v) for k, v in metrics.items()}
    episodes = m["episodes"]
    rate = lambda x: x / episodes if episodes > 0 else float("nan")
    row = dict(
        update=update,
        env_steps=env_steps,
        wall_s=round(wall_s, 3),
        sps=round(sps, 1),
        episodes=int(episodes),
        episode_return=rate(m["return_sum"]),
        success_rate=rate(m["successes"]),
        collision_rate=rate(m["collisions"]),
        timeout_rate=rate(m["timeouts"]),
    )
    row.update({k: m[k] for k in CSV_FIELDS if k not in row})
    return row


def combine_runs(per_run: Sequence[dict]) -> dict:
    """The chunk metrics of several runs as one: episode sums added, the other metrics averaged over runs."""
    return {
        k: (float(np.sum(v)) if k in SUMMED_METRICS else float(np.mean(v)))
        for k, v in ((k, [float(m[k]) for m in per_run]) for k in per_run[0])
    }


def _fmt_steps(n: float) -> str:
    for unit, scale in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if n >= scale:
            return f"{n / scale:.2f}{unit}"
    return f"{int(n)}"


def _fmt_time(s: float) -> str:
    if not math.isfinite(s):
        return "?"
    s = int(round(s))
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"


def progress_line(metrics: ChunkMetrics) -> str:
    """The line printed after every chunk (with several runs: steps per run; rates and steps/s of all runs)."""
    row = metrics.total
    f = lambda x, spec: "  -  " if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, spec)
    runs = len(metrics.runs)
    prefix, per_run = (f"[{runs} runs] ", " per run") if runs > 1 else ("", "")
    return (
        f"{prefix}[{_fmt_steps(metrics.env_steps)}/{_fmt_steps(metrics.total_env_steps)} steps{per_run}, "
        f"update {metrics.update}] {row['sps']:,.0f} steps/s | return {f(row['episode_return'], '7.2f')} | "
        f"success {f(row['success_rate'], '.2f')} coll {f(row['collision_rate'], '.2f')} "
        f"timeout {f(row['timeout_rate'], '.2f')} ({row['episodes']} eps) | "
        f"ent {row['entropy']:.3f} vf {row['vf_loss']:.3g} | ETA {_fmt_time(metrics.eta_s)}"
    )


class ProgressPrinter:
    """progress_fn: prints `progress_line` through `say`."""

    def __init__(self, say: Callable[[str], None]):
        self.say = say

    def __call__(self, step: int, metrics: ChunkMetrics) -> None:
        self.say(progress_line(metrics))


class CsvWriter:
    """progress_fn: appends the rows `rows(metrics)` to a CSV file (header written once).

    `every_chunk`: the file gets a row at every chunk end, so on a resume from update u > 0 it must reach u (a
    missing or shortened file cannot be rebuilt from a checkpoint). The columns from "update" on are numbers."""

    def __init__(
        self,
        path,
        rows: Callable[[ChunkMetrics], list[dict]],
        fields: Sequence[str] = CSV_FIELDS,
        every_chunk: bool = True,
    ):
        self.path, self.rows, self.fields = pathlib.Path(path), rows, list(fields)
        self.every_chunk = every_chunk
        self.file = None

    def _open(self):
        if self.file is None:
            new = not self.path.is_file() or self.path.stat().st_size == 0
            self.file = open(self.path, "a", newline="")
            self.writer = csv.DictWriter(self.file, fieldnames=self.fields)
            if new:
                self.writer.writeheader()

    def __call__(self, step: int, metrics: ChunkMetrics) -> None:
        self._open()
        self.writer.writerows(self.rows(metrics))
        self.file.flush()

    def truncate(self, update: int) -> float:
        """Cut the file back to the checkpoint of `update` a run resumes from, after checking it: a torn last line
        (a crash mid-write) and exact repeats of a row are dropped; a wrong header, a row with another field count,
        an unparseable value or updates out of order before the checkpoint raise ConfigError naming the line.
        Returns the last kept row's wall_s, where the resumed run's clock continues."""
        rows, changed = self._intact_rows(update)
        if self.every_chunk and update > 0:
            reached = max((int(r["update"]) for r in rows), default=None)
            if reached is None or reached < update:
                have = "holds no rows" if reached is None else f"ends at update {reached}"
                raise ConfigError(
                    f"{str(self.path)!r} {have}, but the run resumes from its checkpoint of update "
                    f"{update}: the missing rows cannot be rebuilt from a checkpoint; put the file "
                    "back, or train the run again in a new directory"
                )
        if changed:
            buf = io.StringIO()
            w = csv.DictWriter(buf, fieldnames=self.fields)
            w.writeheader()
            w.writerows(rows)
            write_atomic(self.path, buf.getvalue())
        return max((float(r.get("wall_s") or 0.0) for r in rows), default=0.0)

    def _intact_rows(self, update: int) -> tuple[list[dict], bool]:
        """(rows up to `update`, whether the file must be rewritten to hold exactly them)."""
        if not self.path.is_file():
            if self.every_chunk and update > 0:
                raise ConfigError(
                    f"{str(self.path)!r} is missing, but the run resumes from its checkpoint of "
                    f"update {update}: its rows cannot be rebuilt from a checkpoint; put the file "
                    "back, or train the run again in a new directory"
                )
            return [], False
        name = repr(str(self.path))
        raw = self.path.read_bytes()
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as e:
            line = raw[: e.start].count(b"\n") + 1
            raise ConfigError(
                f"{name} is damaged: line {line} is not UTF-8 text; restore the file or delete that line"
            ) from None
        lines = text.splitlines(keepends=True)
        torn = bool(lines) and not lines[-1].endswith("\n")  # every row written ends with a line break
        if torn:
            lines = lines[:-1]
        if not lines:
            return [], True  # (re)written with its header
        parsed = list(csv.reader(lines))
        if parsed[0] != self.fields:
            shown = ",".join(self.fields[:4])
            raise ConfigError(
                f"{name} is damaged: line 1 is not its header (expected {shown},...); restore the "
                "file or put the header back"
            )
        first_number = self.fields.index("update") if "update" in self.fields else 0
        rows, seen, changed, last = [], {}, torn, -1
        for i, values in enumerate(parsed[1:], start=2):
            problem = self._check(values, first_number)
            if problem is None:
                row = dict(zip(self.fields, values))
                u = int(float(row["update"]))
                key = (row.get("run"), u)
                if seen.get(key) == values:  # an exact repeat of an earlier row (a block appended twice, say)
                    changed = True
                    continue
                if key in seen:
                    problem = f"it repeats update {u} with other values"
                elif u < last:
                    problem = f"its update {u} comes after update {last}"
            if problem is not None:
                if last > update:  # past the checkpoint: dropped anyway
                    return rows, True
                raise ConfigError(f"{name} is damaged: line {i}: {problem}; restore the file or delete that line")
            last = u
            seen[key] = values
            if u > update:
                changed = True
                continue
            rows.append(row)
        return rows, changed

    def _check(self, values: list[str], first_number: int) -> str | None:
        if len(values) != len(self.fields):
            return f"{len(values)} fields instead of {len(self.fields)}"
        for field, value in zip(self.fields[first_number:], values[first_number:]):
            if value == "":
                continue  # a value the run did not have (None)
            try:
                float(value)
            except ValueError:
                return f"{field} = {_clip(value)} is not a number"
        try:
            int(float(values[self.fields.index("update")]))
        except (ValueError, OverflowError):
            return "its update is not a whole number"
        return None

    def close(self) -> None:
        if self.file is not None:
            self.file.close()
            self.file = None


def _clip(value: str, limit: int = 40) -> str:
    return repr(value if len(value) <= limit else value[:limit] + "...")


def run_rows(i: int, **columns) -> Callable[[ChunkMetrics], list[dict]]:
    """`CsvWriter` rows: run i's row, with constant extra columns."""
    return lambda metrics: [dict(metrics.runs[i], **columns)]


class TensorBoardWriter:
    """progress_fn: run i's scalars as TensorBoard events (tensorboardX, else torch.utils.tensorboard, else
    nothing: TensorBoard is optional)."""

    def __init__(self, logdir, run: int = 0):
        self.writer, self.run = None, run
        for module in ("tensorboardX", "torch.utils.tensorboard"):
            try:
                self.writer = __import__(module, fromlist=["SummaryWriter"]).SummaryWriter(str(logdir))
                break
            except Exception:
                continue

    def __call__(self, step: int, metrics: ChunkMetrics) -> None:
        if self.writer is None:
            return
        for k, v in metrics.runs[self.run].items():
            if k not in ("update", "env_steps") and isinstance(v, (int, float)) and math.isfinite(v):
                self.writer.add_scalar(f"train/{k}", v, step)
        self.writer.flush()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()


class LogFile:
    """`say(msg)`: print a message through `log` and append it to a progress.log (only where `enabled`: on a
    multi-host sweep, process 0 writes)."""

    def __init__(self, path, log: Callable[[str], None] = print, enabled: bool = True):
        self.log, self.file = log, open(path, "a") if enabled else None

    def __call__(self, msg: str) -> None:
        if self.file is not None:
            self.log(msg)
            self.file.write(msg + "\n")
            self.file.flush()

    def close(self) -> None:
        if self.file is not None:
            self.file.close()
