"""Orbax checkpoints of the complete `TrainState` (parameters, optimiser, env states, carries, RNG key, hparams),
each with a checksum of its content.

Orbax writes each step into a temporary directory and renames it only once every file is on disk (its atomic
"finalize"), so a process killed mid-save leaves a `*.orbax-checkpoint-tmp-*` directory that `latest_step`
ignores (and the next writer removes before its first save), never a half-written step. Saves here are synchronous:
when `save` returns, the step is final.

A step holds the state (item "default") and, written in the same atomic save, the SHA-256 of its arrays (item
"digest", `tree_digest`). `restore` recomputes the digest of what it read, so a step whose files changed after
the save (a flipped bit) is an error naming the step and the intact earlier steps, never a silently different
state. A step must also fit the template: orbax would hand back an array of the stored shape where the template
asks for another, so paths and shapes are compared first, and a mismatch says what the checkpoint holds.
A step without its "digest" item (deleted, or written before checksums existed) cannot be verified, so it counts
as damaged: restoring it unverified could resume silently from a flipped bit.

No data file of a step grows much past `DATA_FILE_BYTES` (1 MiB): arrays are cut into chunks of half that size, and
orbax's OCDBT store starts a new data file once one holds that much, so a run directory fits storage that caps file
sizes: a git host, an artifact store, a mail attachment.

Orbax cannot store zero-size arrays (a crowd of 0 humans); they are stored as one element and restored in the
template's shape. A missing, damaged or unfitting checkpoint raises `CheckpointError` naming the path.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import pathlib
import sys
import traceback

import jax
import numpy as np
import orbax.checkpoint as ocp

STATE_ITEM = "default"  # orbax's name for a single item: steps written before checksums read the same
DIGEST_ITEM = "digest"
DATA_FILE_BYTES = 1 << 20


class CheckpointError(RuntimeError):
    """A checkpoint is missing, damaged or does not fit; the message names the path. For a damaged step, `step`
    is that step and `intact` the earlier steps that verified (oldest first)."""

    def __init__(self, message: str, *, step: int | None = None, intact: tuple[int, ...] = ()):
        super().__init__(message)
        self.step, self.intact = step, tuple(intact)


class _Damaged(Exception):
    """A step that cannot be read or does not match its checksum (the reason is the message)."""


def _key_name(entry) -> str:
    for attr in ("key", "name", "idx"):
        if hasattr(entry, attr):
            return str(getattr(entry, attr))
    return str(entry)


def _leaves(tree) -> list[tuple[str, object]]:
    """(path, leaf) pairs with paths as 'a/b/c', the same for a dataclass field and the dict key orbax stores."""
    return [
        ("/".join(_key_name(k) for k in path), leaf) for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]
    ]


def tree_digest(tree) -> str:
    """SHA-256 over every array of `tree`: path, dtype, shape and bytes."""
    h = hashlib.sha256()
    for path, leaf in _leaves(jax.device_get(tree)):
        a = np.ascontiguousarray(np.asarray(leaf))
        h.update(f"{path}:{a.dtype.str}:{a.shape};".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _shape(x) -> tuple:
    return tuple(x.shape) if hasattr(x, "shape") else np.shape(x)


def _stored_shape(x) -> tuple:
    """The shape `x` (an array or `jax.ShapeDtypeStruct`) is stored in: zero-size arrays as one element."""
    return (1,) if 0 in _shape(x) else _shape(x)


def _is_closed_loop_callback(unraisable) -> bool:
    """An asyncio "Event loop is closed" raised in `call_soon_threadsafe` by a callback with no Python caller.

    When one read of a restore fails (a truncated or missing data file), orbax's restore raises and closes the
    event loop it ran on while tensorstore still has the step's other reads in flight. As each of them completes,
    tensorstore's own thread hands the result to that closed loop, and Python prints the RuntimeError it raises
    as an unraisable exception: hundreds of tracebacks around the one-line error, for as long as reads complete
    (also after `main` returns). Nothing is lost by dropping them: the restore already failed and says why."""
    exc = unraisable.exc_value
    if not (isinstance(exc, RuntimeError) and str(exc) == "Event loop is closed"):
        return False
    frames = traceback.extract_tb(unraisable.exc_traceback) if unraisable.exc_traceback else []
    return any(
        f.name == "call_soon_threadsafe" and f.filename.endswith(("asyncio/base_events.py", "asyncio\\base_events.py"))
        for f in frames
    )


def _mute_closed_loop_callbacks() -> None:
    """Install (once per process) an unraisable-exception hook that drops `_is_closed_loop_callback` noise and
    passes everything else on to the hook installed before it. Process-wide, because the noise arrives from
    tensorstore threads at any time after a failed restore, not only inside `_quiet_orbax`."""
    if not getattr(sys.unraisablehook, "_tgrf_mutes_closed_loop", False):
        sys.unraisablehook = _muting(sys.unraisablehook)


def _muting(previous):
    """`previous`, an unraisable-exception hook, without the `_is_closed_loop_callback` noise."""

    def hook(unraisable):
        if not _is_closed_loop_callback(unraisable):
            previous(unraisable)

    hook._tgrf_mutes_closed_loop = True
    return hook


_mute_closed_loop_callbacks()


def _reason(e: Exception, limit: int = 300) -> str:
    """An orbax / tensorstore error as one short clause: tensorstore appends the whole spec of the store it read
    (kilobytes of JSON naming every option), which says nothing about what is damaged."""
    text = " ".join(str(e).split(" [tensorstore_spec=")[0].split())
    text = text if len(text) <= limit else text[:limit] + "..."
    return f"{type(e).__name__}: {text}"


@contextlib.contextmanager
def _quiet_orbax():
    """Orbax logs every unreadable file through absl (also while listing steps); a damaged step is reported by the
    error `restore` raises instead."""
    logger = logging.getLogger("absl")
    level = logger.level
    logger.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        logger.setLevel(level)


class _SmallChunkWarning(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return "target_byte_size too small" not in record.getMessage()


@contextlib.contextmanager
def _without_small_chunk_warning():
    """Orbax warns on every save that chunks under 1 MiB may read slowly from cloud storage; the chunks are that
    small on purpose (they bound the data files), and a state of a few MB reads in milliseconds either way."""
    logger, quiet = logging.getLogger("absl"), _SmallChunkWarning()
    logger.addFilter(quiet)
    try:
        yield
    finally:
        logger.removeFilter(quiet)


class Checkpointer:
    def __init__(self, directory, keep: int = 3, create: bool = True):
        self.directory = pathlib.Path(directory).resolve()
        if not create and not self.directory.is_dir():
            raise CheckpointError(f"checkpoint directory {str(self.directory)!r} does not exist")
        options = ocp.CheckpointManagerOptions(
            max_to_keep=keep, create=create, enable_async_checkpointing=False, cleanup_tmp_directories=create
        )
        # named items: a directory may hold steps with and without a digest (a run resumed across versions)
        with _quiet_orbax():
            self._manager = ocp.CheckpointManager(self.directory, options=options, item_names=(STATE_ITEM, DIGEST_ITEM))

    def all_steps(self) -> list[int]:
        with _quiet_orbax():
            self._manager.reload()
            return sorted(self._manager.all_steps())

    def latest_step(self) -> int | None:
        steps = self.all_steps()
        return steps[-1] if steps else None

    def path(self, step: int) -> pathlib.Path:
        return self.directory / str(step)

    def save(self, step: int, state) -> pathlib.Path:
        state = jax.device_get(state)
        storable = jax.tree_util.tree_map(lambda x: np.zeros(1, np.asarray(x).dtype) if 0 in _shape(x) else x, state)
        chunking = jax.tree_util.tree_map(lambda _: ocp.SaveArgs(chunk_byte_size=DATA_FILE_BYTES // 2), storable)
        state_args = ocp.args.PyTreeSave(storable, save_args=chunking, ocdbt_target_data_file_size=DATA_FILE_BYTES)
        args = ocp.args.Composite(
            **{STATE_ITEM: state_args, DIGEST_ITEM: ocp.args.JsonSave({"sha256": tree_digest(state)})}
        )
        with _without_small_chunk_warning():
            self._manager.save(int(step), args=args, force=True)
        self._manager.wait_until_finished()
        return self.path(step)

    def delete(self, step: int) -> None:
        self._manager.delete(step)

    def delete_after(self, step: int) -> list[int]:
        """Delete the steps after `step` (a run resumed from an earlier step trains them again)."""
        later = [s for s in self.all_steps() if s > step]
        for s in later:
            self._manager.delete(s)
        return later

    def restore(self, template, step: int | None = None):
        """Restore into the structure of `template` (a TrainState or its `jax.eval_shape`), verified against the
        step's checksum."""
        steps = self.all_steps()
        if step is None:
            if not steps:
                raise CheckpointError(f"no checkpoint found in {str(self.directory)!r}")
            step = steps[-1]
        path = self.path(step)
        if step not in steps:
            raise CheckpointError(f"checkpoint {str(path)!r} does not exist (available steps: {steps})")
        self._check_fits(template, step)
        try:
            return self._read(template, step)
        except _Damaged as e:
            intact = tuple(s for s in steps if s < step and self._intact(template, s))
            earlier = f"intact earlier steps: {', '.join(map(str, intact))}" if intact else "no earlier step is intact"
            raise CheckpointError(
                f"checkpoint {str(path)!r} (step {step}) is damaged: {e}; {earlier}", step=step, intact=intact
            ) from None

    def _intact(self, template, step: int) -> bool:
        try:
            self._read(template, step)
        except _Damaged:
            return False
        return True

    def _check_fits(self, template, step: int) -> None:
        """Array paths and shapes of the step against the template; where they differ, what the checkpoint holds."""
        handler = ocp.StandardCheckpointHandler()
        with _quiet_orbax():
            try:
                stored = handler.metadata(self.path(step) / STATE_ITEM)
            except Exception:
                return  # unreadable metadata: the restore reports the step as damaged
            finally:
                handler.close()
        have = {p: tuple(m.shape) for p, m in _leaves(stored.tree)}
        want = {p: _stored_shape(x) for p, x in _leaves(template)}
        if have == want:
            return

        def values(shapes: dict, group: str) -> int:
            return sum(int(np.prod(s)) for p, s in shapes.items() if p.split("/")[0] == group)

        groups = sorted({p.split("/")[0] for p in set(have) | set(want) if have.get(p) != want.get(p)})
        held = [f"{g}: {values(have, g):,} values in the checkpoint, {values(want, g):,} here" for g in groups]
        examples = [
            f"{p} {have.get(p, 'absent')} in the checkpoint, {want.get(p, 'absent')} here"
            for p in dict.fromkeys([*want, *have])
            if have.get(p) != want.get(p)
        ][:2]
        raise CheckpointError(
            f"checkpoint {str(self.path(step))!r} does not fit this config: "
            f"{'; '.join(held)} (e.g. {'; '.join(examples)})",
            step=step,
        )

    def _read(self, template, step: int):
        path = self.path(step)
        abstract = jax.tree_util.tree_map(
            lambda x: jax.ShapeDtypeStruct(_stored_shape(x), x.dtype) if hasattr(x, "shape") else x, template
        )
        if not (path / DIGEST_ITEM).is_dir():
            raise _Damaged(f"its checksum ({DIGEST_ITEM}/) is missing, so its content cannot be verified")
        as_numpy = jax.tree_util.tree_map(
            lambda x: (
                ocp.RestoreArgs(restore_type=np.ndarray, dtype=x.dtype) if isinstance(x, jax.ShapeDtypeStruct) else None
            ),
            abstract,
        )
        items = {
            STATE_ITEM: ocp.args.PyTreeRestore(abstract, restore_args=as_numpy),
            DIGEST_ITEM: ocp.args.JsonRestore(),
        }
        with _quiet_orbax():
            try:
                out = self._manager.restore(step, args=ocp.args.Composite(**items))
            except Exception as e:  # orbax / tensorstore raise many types for damaged files
                raise _Damaged(f"it cannot be read ({_reason(e)})") from None
        state = jax.tree_util.tree_map(
            lambda x, t: np.zeros(_shape(t), np.asarray(x).dtype) if 0 in _shape(t) else x, out[STATE_ITEM], template
        )
        digest = out[DIGEST_ITEM]
        if not isinstance(digest, dict) or digest.get("sha256") != tree_digest(state):
            raise _Damaged("its content does not match the checksum written with it")
        return state

    def close(self):
        self._manager.close()
