"""Trained policies that ship with the package, and exporting any run's policy in the same form.

A policy is a directory holding `config.yaml` (the run's TrainConfig), `params.npz` (the network parameters,
flattened with '/'-joined keys, float32) and `meta.json` (where it comes from: experiment, row, seed, test metrics,
commit), sealed by `manifest.json`, the SHA-256 of every file (`tgrf_jax.pretrained.directory`). `tgrf-eval
--pretrained NAME` and `tgrf-render --pretrained NAME` play one; NAME is a directory under this package (see
`available()`) or a path to such a directory. `load` refuses a directory whose files do not match its manifest and
parameters that do not fit the config's network (names, shapes, dtype) or are not finite.
"""

from __future__ import annotations

import json
import pathlib

import numpy as np

from tgrf_jax.config import ConfigError, TrainConfig, load_yaml
from tgrf_jax.pretrained.directory import MANIFEST_FILE, verify, write_manifest, writing

__all__ = [
    "FILES",
    "MANIFEST_FILE",
    "available",
    "check_params",
    "export",
    "load",
    "resolve",
    "write_manifest",
    "write_policy",
]

ROOT = pathlib.Path(__file__).resolve().parent
FILES = ("config.yaml", "params.npz", "meta.json")


def available() -> list[str]:
    """Names of the shipped policies."""
    return sorted(p.name for p in ROOT.iterdir() if (p / "params.npz").is_file())


def resolve(name_or_path: str) -> pathlib.Path:
    path = pathlib.Path(name_or_path)
    if not path.is_dir():
        path = ROOT / name_or_path
    if not path.is_dir():
        names = ", ".join(available()) or "none shipped yet"
        raise ConfigError(
            f"no pretrained policy {name_or_path!r}: not a directory and not a shipped name (shipped: {names})"
        )
    missing = [f for f in FILES if not (path / f).is_file()]
    if missing:
        raise ConfigError(f"{str(path)!r} is not a pretrained policy: {', '.join(missing)} missing")
    return path


def _flatten(tree, prefix=""):
    out = {}
    for key, value in tree.items():
        name = f"{prefix}/{key}" if prefix else str(key)
        if isinstance(value, dict):
            out.update(_flatten(value, name))
        else:
            out[name] = value
    return out


def _unflatten(flat: dict) -> dict:
    tree: dict = {}
    for name, value in flat.items():
        node = tree
        *parents, leaf = name.split("/")
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    return tree


def _one_line(e: Exception) -> str:
    return " ".join(f"{type(e).__name__}: {e}".split())


def _read_params(path: pathlib.Path) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as data:
            return {k: np.asarray(data[k]) for k in data.files}
    # NumPy's zip and .npy readers raise a dozen exception types for a truncated or damaged file (BadZipFile,
    # zlib.error, EOFError, ValueError, KeyError, ...): each is the same "cannot read" for the user.
    except Exception as e:
        raise ConfigError(f"{str(path)!r}: cannot read the parameters ({_one_line(e)})") from None


def _read_meta(path: pathlib.Path) -> dict:
    try:
        meta = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise ConfigError(f"{str(path)!r}: cannot read the policy's metadata ({_one_line(e)})") from None
    if not isinstance(meta, dict):
        raise ConfigError(f"{str(path)!r} must hold a JSON object, not {type(meta).__name__}")
    return meta


def check_params(config: TrainConfig, params: dict, where: str) -> dict[str, np.ndarray]:
    """The parameters flattened ('/'-joined names), after checking them against the config's network: the same
    names, shapes and dtypes, every value finite. `where` names their file or origin in the ConfigError."""
    import jax

    from tgrf_jax.policies import make_network_for

    flat = {k: np.asarray(v) for k, v in _flatten(jax.device_get(params)).items()}
    net = make_network_for(config)
    expected = _flatten(jax.eval_shape(net.init, jax.random.PRNGKey(0)))
    if set(flat) != set(expected):
        raise ConfigError(
            f"{where} does not fit the {config.network.name}/{config.network.size} network of its config: "
            f"parameter names differ ({sorted(set(flat) ^ set(expected))[:4]} ...)"
        )
    for k in sorted(flat):
        v, want = flat[k], expected[k]
        if v.shape != want.shape:
            raise ConfigError(f"{where}: {k} has shape {v.shape}, the config's network expects {want.shape}")
        if v.dtype != want.dtype:
            raise ConfigError(f"{where}: {k} is {v.dtype}, the config's network expects {want.dtype}")
        bad = int(v.size - np.count_nonzero(np.isfinite(v)))
        if bad:
            raise ConfigError(
                f"{where}: {k} holds {bad} non-finite value(s) (NaN or inf); a usable policy's parameters are "
                "all finite"
            )
    return flat


def load(name_or_path: str) -> tuple[TrainConfig, dict, dict]:
    """(TrainConfig, params, meta) of a pretrained policy. Refuses (ConfigError, one line naming the file) a
    directory whose files do not match its manifest, an unreadable file, and parameters that do not fit the
    config's network or are not finite."""
    path = resolve(name_or_path)
    verify(path, FILES)
    try:
        config = TrainConfig.from_dict(load_yaml(path / "config.yaml"))
    except ConfigError as e:
        message = str(e)
        raise ConfigError(
            message if "config.yaml" in message else f"{str(path / 'config.yaml')!r}: {message}"
        ) from None
    flat = _read_params(path / "params.npz")
    meta = _read_meta(path / "meta.json")
    check_params(config, flat, repr(str(path / "params.npz")))
    return config, _unflatten(flat), meta


def write_policy(directory: pathlib.Path, config: TrainConfig, params: dict, meta: dict) -> None:
    """Write the pretrained format's files (`FILES`) into `directory`, refusing parameters `check_params` would.
    The manifest is the directory writer's (`tgrf_jax.pretrained.directory.writing`), written last."""
    flat = check_params(config, params, "the policy's parameters")
    (directory / "config.yaml").write_text(config.to_yaml())
    np.savez(directory / "params.npz", **flat)
    (directory / "meta.json").write_text(json.dumps(meta, indent=2))


def export(
    run_dir: str | pathlib.Path, dest: str | pathlib.Path, meta: dict | None = None, step: int | None = None
) -> pathlib.Path:
    """Write the policy of a tgrf-train run directory (latest checkpoint unless `step`) to `dest` atomically,
    replacing an existing `dest`."""
    import jax

    from tgrf_jax.train.run_dir import restore_run

    config, state = restore_run(run_dir, step)
    payload = dict(meta or {}, update=int(state.update), source=str(run_dir))
    with writing(dest, replace=True) as tmp:
        write_policy(tmp, config, jax.device_get(state.params), payload)
    return pathlib.Path(dest)
