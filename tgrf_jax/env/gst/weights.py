"""Parameters from the reference's PyTorch state dict, and the shipped (pretrained) parameters.

Parameters travel as `.npz` files of flattened paths ("spatial/embed/kernel", ...) with a JSON sidecar of
metadata, so they load with numpy alone and carry what produced them.
"""

from __future__ import annotations

import functools
import json
import pathlib
from collections.abc import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from tgrf_jax.env.gst.model import init_params

_PREFIX = "w/"
_GST = "gumbel_social_transformer."
_LAYER = _GST + "node_encoder_layers.0."

# flax module -> reference module (Linear / LayerNorm layout)
_LINEAR = {
    "embed": _GST + "node_embedding.",
    "in_proj": _LAYER + "self_attn.in_proj_",
    "out_proj": _LAYER + "self_attn.out_proj.",
    "ff1": _LAYER + "linear1.",
    "ff2": _LAYER + "linear2.",
}
_NORM = {"norm_attn": _LAYER + "norm_node.", "norm_ff": _LAYER + "norm1_node."}

PACKAGE_DIR = pathlib.Path(__file__).resolve().parent
PRETRAINED = {"orca": "gst_orca", "social_force": "gst_social_force"}


class WeightsError(ValueError):
    """A parameter file or state dict is missing, corrupt or does not fit the model; names the path or key."""


def from_torch_state_dict(arrays: Mapping[str, np.ndarray]):
    """Model parameters from the reference checkpoint's 20 state-dict tensors.

    Keys are the PyTorch names, with or without the fixture's "w/" prefix (e.g. "lstm.weight_ih_l0" or
    "w/lstm.weight_ih_l0"); other keys are ignored. Layout as PyTorch stores it: Linear weights (out, in),
    attention in_proj rows [q; k; v], LSTM gate rows (i, f, g, o) with two bias vectors (summed here).
    """
    sd = {(k[len(_PREFIX) :] if k.startswith(_PREFIX) else k): np.asarray(v, np.float32) for k, v in arrays.items()}

    def get(name, shape):
        if name not in sd:
            raise WeightsError(f"state dict has no {name!r} (expected the GST checkpoint's tensors)")
        if sd[name].shape != shape:
            raise WeightsError(f"state dict {name!r} has shape {sd[name].shape}, expected {shape}")
        return sd[name]

    template = jax.tree_util.tree_map(lambda x: x.shape, jax.eval_shape(init_params, jax.random.key(0)))
    spatial = {}
    for ours, theirs in _LINEAR.items():
        k_shape = template["spatial"][ours]["kernel"]
        spatial[ours] = {
            "kernel": get(theirs + "weight", k_shape[::-1]).T,
            "bias": get(theirs + "bias", template["spatial"][ours]["bias"]),
        }
    for ours, theirs in _NORM.items():
        shape = template["spatial"][ours]["scale"]
        spatial[ours] = {"scale": get(theirs + "weight", shape), "bias": get(theirs + "bias", shape)}
    gates = template["lstm"]["ih"]["kernel"]
    lstm = {
        "ih": {
            "kernel": get("lstm.weight_ih_l0", gates[::-1]).T,
            "bias": get("lstm.bias_ih_l0", gates[1:]) + get("lstm.bias_hh_l0", gates[1:]),
        },
        "hh": {"kernel": get("lstm.weight_hh_l0", template["lstm"]["hh"]["kernel"][::-1]).T},
    }
    head = {
        "kernel": get("hidden2pos.weight", template["head"]["kernel"][::-1]).T,
        "bias": get("hidden2pos.bias", template["head"]["bias"]),
    }
    speed = {"kernel": np.zeros(template["speed"]["kernel"], np.float32)}  # not in the released model
    params = {"spatial": spatial, "lstm": lstm, "head": head, "speed": speed, "cv_prior": np.zeros((), np.float32)}
    return jax.tree_util.tree_map(lambda x: np.array(x, np.float32, order="C"), params)


def flatten(params) -> dict[str, np.ndarray]:
    flat = {}
    for path, leaf in jax.tree_util.tree_leaves_with_path(dict(params)):
        flat["/".join(p.key for p in path)] = np.asarray(leaf, np.float32)
    return flat


def unflatten(flat: Mapping[str, np.ndarray], source: str):
    """Nested params from flattened paths, checked against the model's parameter shapes."""
    template = _template()
    missing = sorted(set(template) - set(flat))
    extra = sorted(set(flat) - set(template))
    if missing or extra:
        raise WeightsError(f"{source}: parameters do not fit the GST model (missing {missing}, unexpected {extra})")
    params: dict = {}
    for name, ref in template.items():
        if flat[name].shape != ref.shape:
            raise WeightsError(f"{source}: {name!r} has shape {flat[name].shape}, expected {ref.shape}")
        node = params
        *parents, leaf = name.split("/")
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = np.asarray(flat[name], np.float32)
    return params


@functools.cache
def _template() -> dict:
    """Flattened path -> shape/dtype of the model's parameters (traced abstractly: no computation)."""
    shapes = jax.eval_shape(init_params, jax.random.key(0))
    return {"/".join(p.key for p in path): leaf for path, leaf in jax.tree_util.tree_leaves_with_path(shapes)}


def save_params(path, params, metadata: dict) -> pathlib.Path:
    """Write `<path>.npz` and `<path>.json` atomically (temporary file, then rename)."""
    path = pathlib.Path(path).with_suffix("")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez(tmp, **flatten(params))
    tmp.replace(path.with_suffix(".npz"))
    tmp_json = path.with_name(path.name + ".tmp.json")
    tmp_json.write_text(json.dumps(metadata, indent=2, sort_keys=True))
    tmp_json.replace(path.with_suffix(".json"))
    return path.with_suffix(".npz")


def load_params(path):
    """(params, metadata) from a file written by `save_params`; clear errors for missing or corrupt files."""
    path = pathlib.Path(path)
    npz = path if path.suffix == ".npz" else path.with_suffix(".npz")
    if not npz.is_file():
        raise WeightsError(f"predictor parameters {str(npz)!r} do not exist")
    try:
        with np.load(npz) as data:
            flat = {k: data[k] for k in data.files}
    except Exception as e:  # numpy raises several types for damaged archives
        raise WeightsError(f"predictor parameters {str(npz)!r} are corrupt: {type(e).__name__}: {e}") from e
    meta_path = npz.with_suffix(".json")
    metadata = json.loads(meta_path.read_text()) if meta_path.is_file() else {}
    return unflatten(flat, str(npz)), metadata


def pretrained(crowd: str = "orca"):
    """The shipped parameters trained on `crowd` ("orca" or "social_force") crowds of the JAX simulator."""
    if crowd not in PRETRAINED:
        raise WeightsError(f"pretrained(crowd={crowd!r}): allowed crowds are {', '.join(map(repr, PRETRAINED))}")
    return load_params(PACKAGE_DIR / (PRETRAINED[crowd] + ".npz"))[0]


def pretrained_metadata(crowd: str = "orca") -> dict:
    return load_params(PACKAGE_DIR / (PRETRAINED[crowd] + ".npz"))[1]


def for_env(config) -> dict:
    """The shipped parameters an env config asks for (`env.predictor_params`; auto: its crowd's, else orca's)."""
    choice = config.predictor_params
    if choice == "auto":
        shipped = PACKAGE_DIR / (PRETRAINED.get(config.human_policy, "") + ".npz")
        choice = config.human_policy if config.human_policy in PRETRAINED and shipped.is_file() else "orca"
    return _pretrained_arrays(choice)


@functools.cache
def _pretrained_arrays(crowd: str):
    return jax.tree_util.tree_map(jnp.asarray, pretrained(crowd))
