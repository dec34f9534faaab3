"""tgrf-export's work: one policy decision written as ONNX and as a serialized `jax.export` StableHLO artifact,
with `interface.json` stating every input and output, into a directory that appears whole or not at all.

The directory also holds the policy in the pretrained format (`config.yaml`, `params.npz`, `meta.json`), so
`tgrf-eval --pretrained DIR` and `tgrf_jax.deploy.Navigator(DIR)` accept it as they accept a shipped policy.
"""

from __future__ import annotations

import json
import os
import pathlib
import shutil
import tempfile

import numpy as np

from tgrf_jax.config import ConfigError
from tgrf_jax.deploy.policy import (
    INTERFACE_FILE,
    ONNX_FILE,
    OUTPUT_NAMES,
    STABLEHLO_FILE,
    PolicySource,
    PolicyStep,
)

FORMATS = ("onnx", "stablehlo")
INTERFACE_VERSION = 1
ONNX_OPSET = 17  # old enough for ONNX Runtime builds of the last few years, new enough for every op used here
# Lowered for both: a robot's computer may be a CPU or a CUDA board, and lowering needs no such device here.
STABLEHLO_PLATFORMS = ("cpu", "cuda")


def check_out_dir(out) -> pathlib.Path:
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


def interface(step: PolicyStep, source: PolicySource, formats) -> dict:
    """The JSON description of the exported decision, enough to feed it without tgrf-jax."""
    env = source.config.env
    n, d, k = step.num_humans, step.obs_human_dim, env.pred_horizon if env.uses_predictions else 0
    holonomic = env.kinematics == "holonomic"
    human_cols = ["x_rel", "y_rel"] + [f"{axis}_pred{j}_rel" for j in range(1, k + 1) for axis in ("x", "y")]
    rays = step.lidar_rays
    lidar = (
        []
        if not rays
        else [
            {
                "name": "lidar",
                "shape": [rays],
                "dtype": "float32",
                "frame": "robot body: ray 0 along robot_node's heading"
                + (
                    " (pi/2 for this holonomic policy: ray 0 along world +y; rotate the scan of a robot facing elsewhere "
                    "by its heading - pi/2, as tgrf_jax.deploy.Navigator does)"
                    if holonomic
                    else ""
                ),
                "units": "m",
                "layout": f"ray k at angle heading + 2 pi k / {rays} rad, counter-clockwise, k = 0 .. {rays - 1}",
                "meaning": f"2-D LiDAR ranges to the first return (obstacles and people), 360 degrees in {rays} rays; "
                f"values above the sensor range ({env.sensor_range} m) are read as it (clip them), and a ray with "
                "no return is the sensor range (NaN is read as no return)",
                "values": {"rays": rays, "angle_step_rad": 2 * np.pi / rays, "max_range_m": env.sensor_range},
            }
        ]
    )
    action = (
        {
            "name": "action",
            "shape": [2],
            "dtype": "float32",
            "frame": "world",
            "units": "m/s",
            "layout": ["vx", "vy"],
            "meaning": f"desired velocity; the robot drives at it after scaling its norm down to at most "
            f"v_max = {env.robot_v_max} m/s (larger outputs keep their direction)",
        }
        if holonomic
        else {
            "name": "action",
            "shape": [2],
            "dtype": "float32",
            "frame": "robot",
            "units": ["m/s", "rad"],
            "layout": ["dv", "dtheta"],
            "meaning": f"change of forward speed and of heading over one step of dt = {env.dt} s; clip dv to "
            f"[{env.unicycle_dv_min}, {env.unicycle_dv_max}] m/s and dtheta to "
            f"[-{env.unicycle_dtheta_max}, {env.unicycle_dtheta_max}] rad, then "
            f"v = clip(v + dv, -{env.robot_v_max}, {env.robot_v_max}) m/s and omega = dtheta / dt",
        }
    )
    return {
        "format": "tgrf-jax policy step",
        "version": INTERFACE_VERSION,
        "files": {f: {"onnx": ONNX_FILE, "stablehlo": STABLEHLO_FILE}[f] for f in formats},
        "stablehlo_platforms": list(STABLEHLO_PLATFORMS) if "stablehlo" in formats else [],
        "decision": "one deterministic step (the policy Gaussian's mean): call once per control period dt with "
        "the current observation and the previous call's new_state; all inputs are float32 and "
        "unbatched",
        "dt_s": env.dt,
        "inputs": [
            {
                "name": "robot_node",
                "shape": [7],
                "dtype": "float32",
                "frame": "world",
                "layout": ["px", "py", "radius", "gx", "gy", "v_max", "heading"],
                "units": ["m", "m", "m", "m", "m", "m/s", "rad"],
                "meaning": "robot position, its radius, goal position, top speed and heading"
                + (
                    " (a holonomic policy was trained with heading fixed at pi/2: pass 1.5707964)"
                    if holonomic
                    else " (counter-clockwise from the world x axis)"
                ),
                "values": {"radius": env.robot_radius, "v_max": env.robot_v_max},
            },
            {
                "name": "robot_vel",
                "shape": [2],
                "dtype": "float32",
                "frame": "world",
                "units": "m/s",
                "layout": ["vx", "vy"],
                "meaning": "the robot's velocity over the last step",
            },
            {
                "name": "humans",
                "shape": [n, d],
                "dtype": "float32",
                "frame": "world axes, origin at the robot",
                "units": "m",
                "layout": human_cols,
                "meaning": "one row per human in sensor range (edge-to-edge distance <= "
                f"{env.sensor_range} m): position minus the robot's position"
                + (
                    f", then the predicted positions at t + dt .. t + {k} dt ({env.predictor} predictions)"
                    " minus the robot's current position"
                    if k
                    else ""
                )
                + f"; rows sorted by centre distance, nearest first; if more than {n} humans are in "
                f"range keep the {n} nearest",
                "padding": "rows beyond the humans in range are all zeros and have human_mask 0; their values "
                "are ignored",
            },
            {
                "name": "human_mask",
                "shape": [n],
                "dtype": "float32",
                "units": "1",
                "meaning": "1.0 for a row holding a human in range, 0.0 for a padding row (ones first)",
            },
            *lidar,
            {
                "name": "state",
                "shape": [step.state_size],
                "dtype": "float32",
                "units": "none",
                "meaning": "the network's recurrent state: zeros at the start of every trip, then the previous "
                "call's new_state",
            },
        ],
        "outputs": [
            action,
            {
                "name": "new_state",
                "shape": [step.state_size],
                "dtype": "float32",
                "units": "none",
                "meaning": "recurrent state to pass as `state` on the next call",
            },
        ],
        "robot": {
            "kinematics": env.kinematics,
            "radius_m": env.robot_radius,
            "v_max_m_s": env.robot_v_max,
            "sensor_range_m": env.sensor_range,
            "lidar_rays": rays,
            **(
                {}
                if holonomic
                else {
                    "dv_min_m_s": env.unicycle_dv_min,
                    "dv_max_m_s": env.unicycle_dv_max,
                    "dtheta_max_rad": env.unicycle_dtheta_max,
                }
            ),
        },
        "predictions": {
            "predictor": env.predictor,
            "horizon_steps": k,
            "const_vel": "p + j * dt * v for j = 1..K, v the human's velocity over the last step",
            "note": (
                "predictions come from the learned GST model: tgrf_jax.deploy.Navigator runs it"
                if env.predictor == "gst"
                else "ground-truth futures exist only in simulation"
                if env.predictor == "truth"
                else ""
            ),
        },
        "network": {
            "name": source.config.network.name,
            "size": source.config.network.size,
            "frame": source.config.network.frame,
            "num_humans": n,
            "obs_human_dim": d,
            "lidar_rays": rays,
        },
        "source": source.origin,
    }


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
        return tuple(jaxpr_as_fun(closed)(*args))

    model = to_onnx(
        primitives,
        step.input_shapes(),
        input_names=list(step.input_names),
        output_names=list(OUTPUT_NAMES),
        model_name="tgrf_policy_step",
        opset=ONNX_OPSET,
    )
    return model.SerializeToString()


def _stablehlo_bytes(step: PolicyStep) -> bytes:
    import jax

    shapes = [jax.ShapeDtypeStruct(s, np.float32) for s in step.input_shapes()]
    exported = jax.export.export(jax.jit(step.__call__), platforms=STABLEHLO_PLATFORMS)(*shapes)
    return bytes(exported.serialize())


def flat_params(params) -> dict[str, np.ndarray]:
    """Parameters keyed by '/'-joined paths, the pretrained format's params.npz."""
    import jax

    flat = {}
    for path, leaf in jax.tree_util.tree_flatten_with_path(jax.device_get(params))[0]:
        flat["/".join(str(getattr(p, "key", p)) for p in path)] = np.asarray(leaf)
    return flat


def export(source: PolicySource, out, formats=FORMATS, *, say=print) -> pathlib.Path:
    """Write `source`'s decision to the new directory `out` (refused if it exists). Files are built in a hidden
    sibling directory renamed to `out` at the end, so an interrupted or failed export leaves nothing behind."""
    formats = tuple(formats)
    unknown = [f for f in formats if f not in FORMATS]
    if unknown or not formats:
        raise ConfigError(f"unknown export format(s) {unknown or formats}; allowed: {', '.join(FORMATS)}")
    out = check_out_dir(out)
    step = PolicyStep(source.config, source.params)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = pathlib.Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    tmp.chmod(0o755)  # mkdtemp makes it private; an exported policy is for every user of the machine
    try:
        if "onnx" in formats:
            say("  ONNX ...")
            (tmp / ONNX_FILE).write_bytes(_onnx_bytes(step))
        if "stablehlo" in formats:
            say("  StableHLO ...")
            (tmp / STABLEHLO_FILE).write_bytes(_stablehlo_bytes(step))
        (tmp / INTERFACE_FILE).write_text(json.dumps(interface(step, source, formats), indent=2))
        (tmp / "config.yaml").write_text(source.config.to_yaml())
        np.savez(tmp / "params.npz", **flat_params(source.params))
        (tmp / "meta.json").write_text(json.dumps({**source.origin, "exported_by": "tgrf-export"}, indent=2))
        if out.exists():
            raise ConfigError(f"--out {str(out)!r} appeared while exporting; the export is discarded")
        os.rename(tmp, out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)
    return out
