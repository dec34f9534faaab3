"""The runner's reporting seams (tgrf_jax.train.progress) and chunk plan, on synthetic metrics (no training)."""

import csv
import time

import numpy as np
import pytest

from tgrf_jax.config import RunConfig
from tgrf_jax.storage.checkpoint import Checkpointer
from tgrf_jax.train.directory import RunDirectory
from tgrf_jax.train.outer_loop import chunk_plan, train_program
from tgrf_jax.train.ppo import METRIC_NAMES, SUMMED_METRICS
from tgrf_jax.train.progress import (
    CSV_FIELDS,
    ChunkMetrics,
    CsvWriter,
    combine_runs,
    csv_row,
    run_rows,
)


def _metrics(scale: float) -> dict:
    m = {k: scale * (i + 1) for i, k in enumerate(METRIC_NAMES)}
    m["episodes"] = 4.0 * scale
    return m


def _chunk(update: int, runs: list[dict]) -> ChunkMetrics:
    rows = tuple(csv_row(m, update, 10 * update, float(update), 1.0) for m in runs)
    return ChunkMetrics(
        update, 12, 10 * update, 120, 0.0, rows, csv_row(combine_runs(runs), update, 10 * update, float(update), 2.0)
    )


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
    assert CsvWriter(tmp_path / "none.csv", run_rows(0)).truncate(0) == 0.0
    assert CsvWriter(tmp_path / "none.csv", run_rows(0), every_chunk=False).truncate(4) == 0.0  # (eval curves)


def _written(path, updates=(2, 4, 6, 8)) -> list[str]:
    writer = CsvWriter(path, run_rows(0))
    for update in updates:
        writer(10 * update, _chunk(update, [_metrics(1.0)]))
    writer.close()
    return path.read_text().splitlines(keepends=True)


def _torn(lines):
    return lines[:-1] + [lines[-1][:25]]


def _repeated(lines):
    return lines + lines[1:3]  # rows of updates 2 and 4 once more


def _non_utf8(lines):
    return [lines[0], lines[1][:10] + "\udcff" + lines[1][10:]] + lines[2:]


def _headerless(lines):
    return lines[1:]


def _short_row(lines):
    return lines[:2] + [lines[2].rsplit(",", 3)[0] + "\n"] + lines[3:]


def _word_value(lines):
    return lines[:2] + [lines[2].replace(",", ",abc,", 1).replace(",", "", 1)] + lines[3:]


def _out_of_order(lines):
    return [lines[0], lines[2], lines[1]] + lines[3:]


def _same_update_other_values(lines):
    return lines[:3] + [lines[2].replace(",", ",9", 2)] + lines[3:]


def _emptied(lines):
    return []


def _deleted(lines):
    return None


# A metrics.csv corrupted in each way, then cut back to the checkpoint of update 6: repaired (the kept updates)
# or refused (a ConfigError naming the file and the line).
CSV_CORRUPTIONS = {
    "torn last line": (_torn, "repaired", [2, 4, 6]),
    "rows repeated": (_repeated, "repaired", [2, 4, 6]),
    "not UTF-8": (_non_utf8, "refused", "is damaged: line 2 is not UTF-8 text"),
    "headerless": (_headerless, "refused", "is damaged: line 1 is not its header (expected update,env_steps"),
    "a field missing": (_short_row, "refused", "is damaged: line 3: 15 fields instead of 18"),
    "a word for a number": (_word_value, "refused", "is damaged: line 3: update = '4abc' is not a number"),
    "updates out of order": (_out_of_order, "refused", "is damaged: line 3: its update 2 comes after update 4"),
    "an update twice, other values": (_same_update_other_values, "refused", "line 4: it repeats update 4 with other"),
    "emptied": (_emptied, "refused", "holds no rows, but the run resumes from its checkpoint of update 6"),
    "deleted": (
        _deleted,
        "refused",
        "is missing, but the run resumes from its checkpoint of update 6: its rows cannot be rebuilt",
    ),
}


@pytest.mark.parametrize("case", list(CSV_CORRUPTIONS))
def test_a_damaged_csv_is_repaired_or_refused_on_resume_never_kept(case, tmp_path):
    import re

    from tgrf_jax.config import ConfigError

    damage, outcome, expected = CSV_CORRUPTIONS[case]
    path = tmp_path / "metrics.csv"
    lines = damage(_written(path))
    if lines is None:
        path.unlink()
    else:
        path.write_bytes("".join(lines).encode("utf-8", "surrogateescape"))
    writer = CsvWriter(path, run_rows(0))
    if outcome == "refused":
        before = path.read_bytes() if path.exists() else None
        with pytest.raises(ConfigError, match=re.escape(expected)) as e:
            writer.truncate(6)
        assert "\n" not in str(e.value) and str(path) in str(e.value)
        assert (path.read_bytes() if path.exists() else None) == before  # nothing the user had is lost
        return
    assert writer.truncate(6) == 6.0
    writer(80, _chunk(8, [_metrics(1.0)]))  # the resumed run's next row lands on a line of its own
    writer.close()
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["update"]) for r in rows] == expected + [8]
    assert all(None not in r and len(r) == len(CSV_FIELDS) for r in rows)


def test_chunk_plan_cuts_at_every_period():
    assert list(chunk_plan(0, 12, 5, 4)) == [4, 1, 3, 2, 2]  # log (5, 10) and checkpoint (4, 8, 12) multiples
    assert list(chunk_plan(4, 12, 5, 4)) == [1, 3, 2, 2]  # absolute boundaries: the same chunks after a resume
    assert list(chunk_plan(0, 12, 5, 4, 3)) == [3, 1, 1, 1, 2, 1, 1, 2]  # an extra period (e.g. periodic evaluation)
    assert sum(chunk_plan(3, 1000, 7, 50)) == 997
    # lazy: the largest run allowed (2^31 - 1 one-update chunks) starts at once instead of listing its chunks first
    plan = chunk_plan(0, 2**31 - 1, 1, 1)
    assert [next(plan) for _ in range(3)] == [1, 1, 1]


class _InstantProgram:
    """A training program whose chunks take no time (the outer loop's accounting without training)."""

    num_runs, num_updates, batch_size = 1, 8, 4

    def init(self):
        return 0

    def is_compiled(self, state):
        return True

    def run_chunk(self, state, n_updates):
        return state + n_updates, None

    def run_metrics(self, raw):
        return [dict.fromkeys(METRIC_NAMES, 0.0)]

    def host_state(self, state):
        return {"update": np.int32(state)}

    def describe(self, state):
        return "instant"


def test_the_eta_counts_the_work_between_chunks(tmp_path):
    # instant chunks, each followed by 0.05 s of work in a state_fn (as a periodic evaluation is): the ETA must
    # expect that work, not only the chunks' own time
    etas = {}
    directory = RunDirectory(
        root=tmp_path,
        run_dirs=(tmp_path,),
        say=lambda line: None,
        checkpointer=Checkpointer(tmp_path / "checkpoints"),
        progress_fns=(lambda step, metrics: etas.__setitem__(metrics.update, metrics.eta_s),),
        state_fns=(lambda update, state: time.sleep(0.05),),
        cut_every=(),
        write_evals=False,
        where="run dir",
    )
    result = train_program(_InstantProgram(), directory, RunConfig(log_every=2, checkpoint_every=8, eval_episodes=0))
    assert result.updates == 8 and sorted(etas) == [2, 4, 6, 8]
    # at update 4, one 0.05 s pause came after the 4 updates done, and 4 updates remain
    assert etas[4] >= 0.05
    assert etas[8] == 0.0
