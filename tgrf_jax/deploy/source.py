"""Where a policy to deploy comes from: a tgrf-train run directory, a tgrf-export directory or a pretrained name /
directory, each checked whole before it is used (`load_source`)."""

from __future__ import annotations

import dataclasses
import pathlib

from tgrf_jax.config import ConfigError, TrainConfig
from tgrf_jax.deploy.interface import check_interface
from tgrf_jax.deploy.policy import INTERFACE_FILE


@dataclasses.dataclass
class PolicySource:
    """A trained policy: its TrainConfig, network parameters and a description of where it came from."""

    config: TrainConfig
    params: dict
    origin: dict
    exported_dir: pathlib.Path | None = None  # set when loaded from a tgrf-export directory


def is_exported(path: str | pathlib.Path) -> bool:
    return (pathlib.Path(path) / INTERFACE_FILE).is_file()


def load_source(source: str | pathlib.Path, *, step: int | None = None) -> PolicySource:
    """A policy from a tgrf-train run directory (latest checkpoint unless `step`), a tgrf-export directory, or a
    pretrained name / directory. Raises ConfigError or CheckpointError naming the path and what is wrong: a
    directory whose files do not match its manifest, parameters that do not fit the config's network or are not
    finite, an interface.json other than the one the policy gives."""
    from tgrf_jax import pretrained

    path = pathlib.Path(source)
    if path.is_dir() and (path / "checkpoints").exists():
        import jax

        from tgrf_jax.train.run_dir import restore_run

        config, state = restore_run(path, step)
        params = jax.device_get(state.params)
        pretrained.check_params(config, params, f"the checkpoint of update {int(state.update)} in {str(path)!r}")
        return PolicySource(config, params, {"run_dir": str(path), "update": int(state.update)})
    if step is not None:
        raise ConfigError(
            f"step selects a checkpoint of a run directory; {str(source)!r} is not one (no checkpoints/ in it)"
        )
    if path.is_dir() and not (path / "params.npz").exists() and (path / "config.yaml").exists():
        raise ConfigError(
            f"{str(path)!r} looks like a tgrf-train run directory without checkpoints/: nothing trained to load"
        )
    config, params, meta = pretrained.load(str(source))
    directory = pretrained.resolve(str(source))
    origin = {"pretrained": str(source), **{k: meta[k] for k in ("experiment", "row", "seed", "update") if k in meta}}
    if not is_exported(directory):
        return PolicySource(config, params, origin)
    check_interface(directory, config, params, meta)
    return PolicySource(config, params, origin, directory)
