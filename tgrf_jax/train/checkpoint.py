"""Orbax checkpoints of the complete `TrainState` (parameters, optimiser, env states, carries, RNG key, hparams).

Orbax writes each step into a temporary directory and renames it only once every file is on disk (its atomic
"finalize"), so a process killed mid-save leaves a `*.orbax-checkpoint-tmp-*` directory that `latest_step`
ignores, never a half-written step. Saves here are synchronous: when `save` returns, the step is final.

A missing or unreadable checkpoint raises `CheckpointError` naming the path; nothing restarts silently.
"""

from __future__ import annotations

import pathlib

import jax
import orbax.checkpoint as ocp


class CheckpointError(RuntimeError):
    """A checkpoint is missing, incomplete or cannot be read; the message names the path."""


class Checkpointer:
    def __init__(self, directory, keep: int = 3, create: bool = True):
        self.directory = pathlib.Path(directory).resolve()
        if not create and not self.directory.is_dir():
            raise CheckpointError(f"checkpoint directory {str(self.directory)!r} does not exist")
        options = ocp.CheckpointManagerOptions(max_to_keep=keep, create=create, enable_async_checkpointing=False)
        self._manager = ocp.CheckpointManager(self.directory, options=options)

    def all_steps(self) -> list[int]:
        self._manager.reload()
        return sorted(self._manager.all_steps())

    def latest_step(self) -> int | None:
        steps = self.all_steps()
        return steps[-1] if steps else None

    def save(self, step: int, state) -> pathlib.Path:
        state = jax.device_get(state)
        self._manager.save(int(step), args=ocp.args.StandardSave(state), force=True)
        self._manager.wait_until_finished()
        return self.directory / str(step)

    def restore(self, template, step: int | None = None):
        """Restore into the structure of `template` (a TrainState or its `jax.eval_shape`)."""
        if step is None:
            step = self.latest_step()
            if step is None:
                raise CheckpointError(f"no checkpoint found in {str(self.directory)!r}")
        path = self.directory / str(step)
        if not path.is_dir():
            raise CheckpointError(f"checkpoint {str(path)!r} does not exist (available steps: {self.all_steps()})")
        abstract = jax.tree_util.tree_map(
            lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype) if hasattr(x, "shape") else x, template
        )
        try:
            return self._manager.restore(step, args=ocp.args.StandardRestore(abstract))
        except Exception as e:  # orbax / tensorstore raise many types for damaged files
            raise CheckpointError(f"checkpoint {str(path)!r} is corrupt or incompatible with this run: "
                                  f"{type(e).__name__}: {e}") from e

    def close(self):
        self._manager.close()
