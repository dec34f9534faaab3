"""The runner's reporting seams (tgrf_jax.train.progress) and chunk plan, on synthetic metrics (no training)."""

import csv

import pytest

from tgrf_jax.train.ppo import METRIC_NAMES, SUMMED_METRICS
from tgrf_jax.train.progress import CSV_FIELDS, ChunkMetrics, CsvWriter, combine_runs, csv_row, run_rows
from tgrf_jax.train.runner import chunk_plan


def _metrics(scale: float) -> dict:
    m = {k: scale * (i + 1) for i, k in enumerate(METRIC_NAMES)}
    m["episodes"] = 4.0 * scale
    return m


def _chunk(update: int, runs: list[dict]) -> ChunkMetrics:
    rows = tuple(csv_row(m, update, 10 * update, float(update), 1.0) for m in runs)
    return ChunkMetrics(update, 12, 10 * update, 120, 0.0, rows, csv_row(combine_runs(runs), update, 10 * update,
                                                                          float(update), 2.0))


def test_runs_combine_by_summing_episode_counts_and_averaging_the_rest():
    a, b = _metrics(1.0), _metrics(3.0)
    both = combine_runs([a, b])
    for k in METRIC_NAMES:
        assert both[k] == pytest.approx(a[k] + b[k] if k in SUMMED_METRICS else (a[k] + b[k]) / 2), k
    row = csv_row(both, 4, 40, 1.0, 2.0)
    assert list(row) == list(CSV_FIELDS)
    assert row["episodes"] == 16 and row["success_rate"] == pytest.approx((a["successes"] + b["successes"]) / 16)


def test_csv_writer_appends_and_truncates_to_a_checkpoint(tmp_path):
    path = tmp_path / "metrics.csv"
    writer = CsvWriter(path, run_rows(1, seed=7), list(CSV_FIELDS) + ["seed"])
    for update in (2, 4, 6):
        writer(10 * update, _chunk(update, [_metrics(1.0), _metrics(2.0)]))
    writer.close()
    rows = list(csv.DictReader(open(path)))
    assert [int(r["update"]) for r in rows] == [2, 4, 6] and {r["seed"] for r in rows} == {"7"}
    assert float(rows[0]["loss"]) == _metrics(2.0)["loss"]  # run 1's row
    assert writer.truncate(4) == 4.0  # the kept rows' last wall_s: where the resumed clock continues
    assert [int(r["update"]) for r in csv.DictReader(open(path))] == [2, 4]
    assert CsvWriter(tmp_path / "none.csv", run_rows(0)).truncate(4) == 0.0


def test_chunk_plan_cuts_at_every_period():
    assert list(chunk_plan(0, 12, 5, 4)) == [4, 1, 3, 2, 2]  # log (5, 10) and checkpoint (4, 8, 12) multiples
    assert list(chunk_plan(4, 12, 5, 4)) == [1, 3, 2, 2]  # absolute boundaries: the same chunks after a resume
    assert list(chunk_plan(0, 12, 5, 4, 3)) == [3, 1, 1, 1, 2, 1, 1, 2]  # an extra period (e.g. periodic evaluation)
    assert sum(chunk_plan(3, 1000, 7, 50)) == 997
    # lazy: the largest run allowed (2^31 - 1 one-update chunks) starts at once instead of listing its chunks first
    plan = chunk_plan(0, 2**31 - 1, 1, 1)
    assert [next(plan) for _ in range(3)] == [1, 1, 1]
