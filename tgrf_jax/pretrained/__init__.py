"""Trained policies that ship with the package, and exporting any run's policy in the same form.

A policy is a directory holding `config.yaml` (the run's TrainConfig), `params.npz` (the network parameters,
flattened with '/'-joined keys) and `meta.json` (where it comes from: experiment, row, seed, test metrics,
commit). `tgrf-eval --pretrained NAME` and `tgrf-render --pretrained NAME` play one; NAME is a directory under
this package (see `available()`) or a path to such a directory.
"""

from __future__ import annotations

import json
import os
import pathlib
import shutil
import tempfile

import numpy as np

from tgrf_jax.config import ConfigError, TrainConfig, load_yaml

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


def load(name_or_path: str):
    """(TrainConfig, params, meta) of a pretrained policy; the parameters are checked against the config's
    network (a mismatch names both shapes)."""
    import jax

    from tgrf_jax.policies import make_network_for

    path = resolve(name_or_path)
    config = TrainConfig.from_dict(load_yaml(path / "config.yaml"))
    try:
        with np.load(path / "params.npz") as data:
            flat = {k: data[k] for k in data.files}
        meta = json.loads((path / "meta.json").read_text())
    except (OSError, ValueError) as e:
        raise ConfigError(f"{str(path)!r}: cannot read the policy ({type(e).__name__}: {e})") from None
    net = make_network_for(config)
    expected = _flatten(jax.eval_shape(net.init, jax.random.PRNGKey(0)))
    if set(flat) != set(expected):
        raise ConfigError(
            f"{str(path / 'params.npz')!r} does not fit the {config.network.name}/"
            f"{config.network.size} network of its config.yaml: parameter names differ "
            f"({sorted(set(flat) ^ set(expected))[:4]} ...)"
        )
    for k, v in flat.items():
        if v.shape != expected[k].shape:
            raise ConfigError(
                f"{str(path / 'params.npz')!r}: {k} has shape {v.shape}, the config's network "
                f"expects {expected[k].shape}"
            )
    return config, _unflatten(flat), meta


def export(run_dir, dest, meta: dict | None = None, step: int | None = None) -> pathlib.Path:
    """Write the policy of a tgrf-train run directory (latest checkpoint unless `step`) to `dest` atomically."""
    import jax

    from tgrf_jax.train.run_dir import restore_run

    config, state = restore_run(run_dir, step)
    dest = pathlib.Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = pathlib.Path(tempfile.mkdtemp(prefix=f".{dest.name}.", dir=dest.parent))
    tmp.chmod(0o755)  # mkdtemp makes it private; an exported policy is data for every user of the checkout
    try:
        (tmp / "config.yaml").write_text(config.to_yaml())
        arrays = {k: np.asarray(v) for k, v in _flatten(jax.device_get(state.params)).items()}
        np.savez(tmp / "params.npz", **arrays)
        payload = dict(meta or {}, update=int(state.update), source=str(run_dir))
        (tmp / "meta.json").write_text(json.dumps(payload, indent=2))
        if dest.exists():
            shutil.rmtree(dest)
        os.replace(tmp, dest)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)
    return dest
