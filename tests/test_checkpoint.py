"""Checkpoints: a checksum of every step's content verified on restore, the damaged step and the intact earlier ones
named, steps that do not fit the config described, zero-size arrays, steps without a checksum refused."""

import pathlib
import shutil

import jax
import numpy as np
import orbax.checkpoint as ocp
import pytest
from helpers import flip_a_bit

from tgrf_jax.storage.checkpoint import DATA_FILE_BYTES, Checkpointer, CheckpointError, tree_digest

ROOT = pathlib.Path(__file__).resolve().parents[1]


def state(step: int) -> dict:
    return {
        "params": {"w": np.arange(2000, dtype=np.float32) + step, "b": np.full(3, step, np.int32)},
        "humans": np.zeros((4, 0, 2), np.float32),
        "update": np.int32(step),
    }


@pytest.fixture
def saved(tmp_path):
    ckpt = Checkpointer(tmp_path / "ckpts", keep=5)
    for step in (0, 4, 8, 12):
        ckpt.save(step, state(step))
    yield ckpt
    ckpt.close()


def test_restore_returns_what_was_saved_zero_size_arrays_included(saved):
    restored = saved.restore(state(0))
    assert tree_digest(restored) == tree_digest(state(12))
    assert restored["humans"].shape == (4, 0, 2)  # orbax cannot store zero-size arrays: restored in their shape
    template = jax.tree_util.tree_map(lambda x: jax.ShapeDtypeStruct(np.shape(x), np.asarray(x).dtype), state(0))
    assert tree_digest(saved.restore(template, 4)) == tree_digest(state(4))


def overwrite(step_dir):
    for f in step_dir.rglob("*"):
        if f.is_file():
            f.write_bytes(b"garbage")


def drop_digest(step_dir):
    """A flipped bit in a step whose checksum was deleted: without the check it would restore other values."""
    flip_a_bit(step_dir)
    shutil.rmtree(step_dir / "digest")


@pytest.mark.parametrize(
    "damage, reason",
    [
        (flip_a_bit, "its content does not match the checksum written with it"),  # reads, with other values
        (overwrite, r"it cannot be read \(.*\)"),
        (drop_digest, r"its checksum \(digest/\) is missing, so its content cannot be verified"),
    ],
)
def test_a_damaged_step_is_an_error_naming_the_step_and_the_intact_ones(saved, damage, reason):
    damage(saved.path(12))
    flip_a_bit(saved.path(4))  # an earlier damaged step is not offered as intact
    message = rf"/12' \(step 12\) is damaged: {reason}; intact earlier steps: 0, 8$"
    with pytest.raises(CheckpointError, match=message) as e:
        saved.restore(state(0))
    assert (e.value.step, e.value.intact) == (12, (0, 8))
    assert tree_digest(saved.restore(state(0), 8)) == tree_digest(state(8))


def test_a_step_that_does_not_fit_says_what_it_holds(saved):
    bigger = state(0)
    bigger["params"]["w"] = np.zeros(4000, np.float32)
    with pytest.raises(
        CheckpointError,
        match=r"does not fit this config: params: 2,003 values in the checkpoint, "
        r"4,003 here \(e.g. params/w \(2000,\) in the checkpoint, \(4000,\) "
        r"here\)",
    ):
        saved.restore(bigger)
    renamed = state(0)
    renamed["params"]["v"] = renamed["params"].pop("w")
    with pytest.raises(
        CheckpointError,
        match=r"params/v absent in the checkpoint, \(2000,\) here; params/w \(2000,\) "
        r"in the checkpoint, absent here",
    ):
        saved.restore(renamed)


def test_delete_after_and_missing_steps(saved):
    assert saved.delete_after(4) == [8, 12] and saved.all_steps() == [0, 4]
    with pytest.raises(CheckpointError, match=r"/8' does not exist \(available steps: \[0, 4\]\)"):
        saved.restore(state(0), 8)


def test_a_step_without_a_checksum_is_refused_not_restored_unverified(tmp_path):
    def plain(step):
        return state(step)["params"]

    legacy = ocp.CheckpointManager(tmp_path, options=ocp.CheckpointManagerOptions(enable_async_checkpointing=False))
    legacy.save(2, args=ocp.args.StandardSave(plain(2)), force=True)  # a step written before checksums
    legacy.wait_until_finished()
    legacy.close()
    ckpt = Checkpointer(tmp_path)
    with pytest.raises(
        CheckpointError,
        match=r"/2' \(step 2\) is damaged: its checksum \(digest/\) is missing, so "
        r"its content cannot be verified; no earlier step is intact$",
    ):
        ckpt.restore(plain(0))
    ckpt.save(4, plain(4))  # a resumed run goes on writing verified steps
    assert tree_digest(ckpt.restore(plain(0))) == tree_digest(plain(4))
    with pytest.raises(CheckpointError, match=r"\(step 2\) is damaged: its checksum"):
        ckpt.restore(plain(0), 2)
    ckpt.close()


def test_no_data_file_of_a_large_step_grows_past_its_cap(tmp_path):
    big = {
        "rollout": np.random.default_rng(0).random((5, 400_000), np.float32),  # 8 MB, one array
        "params": {f"w{i}": np.full((300, 300), i, np.float32) for i in range(8)},
    }  # 2.9 MB in small arrays
    ckpt = Checkpointer(tmp_path)
    ckpt.save(1, big)
    sizes = [f.stat().st_size for f in ckpt.path(1).rglob("*") if f.is_file()]
    assert sum(sizes) > 5 * DATA_FILE_BYTES  # random floats barely compress: the cap, not compression, splits them
    assert max(sizes) < 1.5 * DATA_FILE_BYTES
    assert tree_digest(ckpt.restore(big)) == tree_digest(big)
    ckpt.close()


def test_a_step_written_in_one_file_per_item_still_restores(tmp_path):
    """Steps saved before data files were capped (orbax's StandardSave, one large data file) resume as they are."""
    legacy = ocp.CheckpointManager(
        tmp_path,
        options=ocp.CheckpointManagerOptions(enable_async_checkpointing=False),
        item_names=("default", "digest"),
    )
    stored = {**state(3), "humans": np.zeros(1, np.float32)}  # zero-size arrays were stored as one element then too
    legacy.save(
        3,
        args=ocp.args.Composite(
            default=ocp.args.StandardSave(stored), digest=ocp.args.JsonSave({"sha256": tree_digest(state(3))})
        ),
        force=True,
    )
    legacy.wait_until_finished()
    legacy.close()
    ckpt = Checkpointer(tmp_path)
    assert tree_digest(ckpt.restore(state(0))) == tree_digest(state(3))
    ckpt.close()


def test_a_writer_removes_the_leftover_of_a_save_killed_mid_commit(saved):
    leftover = saved.directory / "16.orbax-checkpoint-tmp"  # orbax's name for step 16 before its commit
    leftover.mkdir()
    (leftover / "half_written").write_bytes(b"x")
    assert saved.all_steps() == [0, 4, 8, 12]
    reader = Checkpointer(saved.directory, create=False)
    assert tree_digest(reader.restore(state(0))) == tree_digest(state(12))
    reader.close()
    assert leftover.exists()  # a reader leaves it
    writer = Checkpointer(saved.directory, keep=5)
    writer.save(20, state(20))  # a writer has removed it by the time its first save returns
    writer.close()
    assert not leftover.exists() and saved.all_steps() == [0, 4, 8, 12, 20]


def test_a_run_without_humans_checkpoints_and_resumes(tmp_path):
    """env.num_humans = 0 is allowed (an empty crowd): its states hold zero-size arrays, which orbax cannot store."""
    from tgrf_jax.config import TrainConfig
    from tgrf_jax.train.run_dir import restore_run, train_run

    config = TrainConfig.from_yaml(ROOT / "configs" / "tiny.yaml", ["env.num_humans=0", "run.eval_episodes=0"])
    first = train_run(config, tmp_path / "run", log=lambda m: None, stop_after_updates=0)
    assert first.state.env_state.humans.pos.shape == (8, 0, 2)
    _, restored = restore_run(tmp_path / "run")
    assert tree_digest(restored) == tree_digest(first.state)
    again = train_run(config, tmp_path / "run", resume=True, log=lambda m: None, stop_after_updates=0)
    assert again.updates == 0 and tree_digest(again.state) == tree_digest(first.state)


def test_closed_event_loop_callbacks_of_a_failed_restore_are_muted_and_nothing_else():
    """A failed restore leaves tensorstore reads in flight that complete into orbax's closed event loop; Python
    reports each as an unraisable exception (hundreds of tracebacks after a one-line error). The process-wide hook
    of tgrf_jax.storage.checkpoint drops exactly those and passes any other unraisable exception on. (pytest swaps
    its own hook in around each test, so the wrapper is checked directly; test_bad_inputs runs the processes.)"""
    import asyncio
    import sys
    import types

    from tgrf_jax.storage import checkpoint

    loop = asyncio.new_event_loop()
    loop.close()
    try:
        loop.call_soon_threadsafe(print)
    except RuntimeError as e:
        closed = e
    try:
        raise RuntimeError("Event loop is closed")  # the same words from elsewhere: not orbax's noise
    except RuntimeError as e:
        other = e

    def unraisable(exc):
        return types.SimpleNamespace(
            exc_type=type(exc), exc_value=exc, exc_traceback=exc.__traceback__, err_msg=None, object=None
        )

    passed_on = []
    hook = checkpoint._muting(passed_on.append)
    for exc in (closed, other, ValueError("x")):
        hook(unraisable(exc))
    assert [u.exc_value for u in passed_on] == [other, passed_on[1].exc_value] and len(passed_on) == 2
    assert isinstance(passed_on[1].exc_value, ValueError)
    # installed once at import, outside any test's swap
    import subprocess

    code = "import sys, tgrf_jax.storage.checkpoint; print(sys.unraisablehook._tgrf_mutes_closed_loop)"
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        check=False,
        env={**__import__("os").environ, "JAX_PLATFORMS": "cpu"},
        timeout=120,
    )
    assert out.stdout.strip() == "True", out.stderr[-2000:]
