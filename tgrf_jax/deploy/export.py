"""tgrf-export's work: one policy decision written as ONNX and as a serialized `jax.export` StableHLO artifact,
with `interface.json` stating every input and output, into a directory that appears whole or not at all, sealed by
`manifest.json` (the SHA-256 of every file, written last; `tgrf_jax.pretrained.directory`).

The directory also holds the policy in the pretrained format (`config.yaml`, `params.npz`, `meta.json`), so
`tgrf-eval --pretrained DIR` and `tgrf_jax.deploy.Navigator(DIR)` accept it as they accept a shipped policy.
"""

from __future__ import annotations

import json
import os
import pathlib
from collections.abc import Callable, Sequence

import numpy as np

from tgrf_jax.config import ConfigError
from tgrf_jax.deploy.interface import EXPORTED_BY, STABLEHLO_PLATFORMS, interface
from tgrf_jax.deploy.policy import FORMATS, INTERFACE_FILE, ONNX_FILE, OUTPUT_NAMES, STABLEHLO_FILE, PolicyStep
from tgrf_jax.deploy.source import PolicySource
from tgrf_jax.pretrained import check_params, write_policy
from tgrf_jax.pretrained.directory import writing

ONNX_OPSET = 17  # old enough for ONNX Runtime builds of the last few years, new enough for every op used here


def check_out_dir(out: str | pathlib.Path) -> pathlib.Path:
    """Refuse an existing output directory, or one that cannot be created, before anything is computed."""
    out = pathlib.Path(out)
    if out.exists() or out.is_symlink():
        raise ConfigError(f"--out {str(out)!r} already exists; give a new directory (nothing is overwritten)")
    parent = out.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        raise ConfigError(f"--out {str(out)!r} cannot be created: {str(parent)!r} is not a writable directory")
    return out


def _used_names(graph) -> set[str]:
    """Every value name read by a node of `graph` (its subgraphs included) or returned by it."""
    names = {o.name for o in graph.output}
    for node in graph.node:
        names.update(node.input)
        for attr in node.attribute:
            for sub in ([attr.g] if attr.HasField("g") else []) + list(attr.graphs):
                names |= _used_names(sub)
    return names


def _drop_unused_initializers(model) -> None:
    """Remove the constants no node reads (jax2onnx keeps some of the jaxpr's), which ONNX Runtime would
    otherwise report one warning each for when it loads the file."""
    used = _used_names(model.graph)
    keep = [init for init in model.graph.initializer if init.name in used]
    del model.graph.initializer[:]
    model.graph.initializer.extend(keep)


def _onnx_bytes(step: PolicyStep) -> bytes:
    import jax
    import jax.numpy as jnp
    from jax.extend.core import jaxpr_as_fun
    from jax2onnx import to_onnx

    # jax2onnx converts by tracing with its own versions of jnp functions, some of which refuse arguments the
    # networks use (jnp.max(..., initial=...) in the masked softmax). Tracing to primitives first hands it
    # only lax-level operations, which it converts whole.
    closed = jax.make_jaxpr(step)(*[jnp.zeros(s, jnp.float32) for s in step.input_shapes()])

    def primitives(*args):
        # Each output is copied (an ONNX Identity): a network without recurrence passes its state through
        # unchanged, and ONNX cannot name one value both the input `state` and the output `new_state`.
        return tuple(jnp.array(out, copy=True) for out in jaxpr_as_fun(closed)(*args))

    model = to_onnx(
        primitives,
        step.input_shapes(),
        input_names=list(step.input_names),
        output_names=list(OUTPUT_NAMES),
        model_name="tgrf_policy_step",
        opset=ONNX_OPSET,
    )
    _drop_unused_initializers(model)
    return model.SerializeToString()


def _stablehlo_bytes(step: PolicyStep) -> bytes:
    import jax

    shapes = [jax.ShapeDtypeStruct(s, np.float32) for s in step.input_shapes()]
    exported = jax.export.export(jax.jit(step.__call__), platforms=STABLEHLO_PLATFORMS)(*shapes)
    return bytes(exported.serialize())


def export(
    source: PolicySource,
    out: str | pathlib.Path,
    formats: Sequence[str] = FORMATS,
    *,
    say: Callable[[str], object] = print,
) -> pathlib.Path:
    """Write `source`'s decision to the new directory `out` (refused if it exists). Files are built in a hidden
    sibling directory renamed to `out` once its manifest is written, so an interrupted or failed export leaves
    nothing behind (and the next export into the same parent removes what a killed one left)."""
    formats = tuple(formats)
    unknown = [f for f in formats if f not in FORMATS]
    if unknown or not formats:
        raise ConfigError(f"unknown export format(s) {unknown or formats}; allowed: {', '.join(FORMATS)}")
    out = check_out_dir(out)
    check_params(source.config, source.params, "the policy's parameters")
    step = PolicyStep(source.config, source.params)
    meta = {**source.origin, "exported_by": EXPORTED_BY}
    with writing(out, replace=False) as tmp:
        if "onnx" in formats:
            say("  ONNX ...")
            (tmp / ONNX_FILE).write_bytes(_onnx_bytes(step))
        if "stablehlo" in formats:
            say("  StableHLO ...")
            (tmp / STABLEHLO_FILE).write_bytes(_stablehlo_bytes(step))
        spec = interface(step, source.config, source.origin, formats)
        (tmp / INTERFACE_FILE).write_text(json.dumps(spec, indent=2))
        write_policy(tmp, source.config, source.params, meta)
    return out
