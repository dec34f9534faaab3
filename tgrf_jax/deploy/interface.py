"""interface.json: what the exported decision takes and returns, derived from the policy's config alone, and the
check that an exported directory's interface.json is exactly that derivation (a reader never trusts it alone)."""

from __future__ import annotations

import json
import pathlib
from collections.abc import Sequence

import numpy as np

from tgrf_jax.config import ConfigError, TrainConfig
from tgrf_jax.deploy.policy import FORMAT_FILES, INTERFACE_FILE, PolicyStep, read_interface

INTERFACE_VERSION = 1
# Lowered for both: a robot's computer may be a CPU or a CUDA board, and lowering needs no such device here.
STABLEHLO_PLATFORMS = ("cpu", "cuda")
EXPORTED_BY = "tgrf-export"  # meta.json's "exported_by" in an exported directory


def interface(step: PolicyStep, config: TrainConfig, origin: dict, formats: Sequence[str]) -> dict:
    """The JSON description of the exported decision, enough to feed it without tgrf-jax. `origin` is where
    the policy comes from (meta.json less its "exported_by")."""
    env = config.env
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
                    " (pi/2 for this holonomic policy: ray 0 along world +y; rotate the scan of a robot facing "
                    "elsewhere by its heading - pi/2, as tgrf_jax.deploy.Navigator does)"
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
        "files": {f: FORMAT_FILES[f] for f in formats},
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
            "name": config.network.name,
            "size": config.network.size,
            "frame": config.network.frame,
            "num_humans": n,
            "obs_human_dim": d,
            "lidar_rays": rays,
        },
        "source": origin,
    }


def _first_difference(a, b, where: str = "") -> tuple[str, object, object] | None:
    """(path, a's value, b's value) of the first place two JSON values differ, None when equal."""
    if isinstance(a, dict) and isinstance(b, dict):
        for key in sorted(set(a) | set(b)):
            if key not in a or key not in b:
                return f"{where}.{key}".lstrip("."), a.get(key, "(absent)"), b.get(key, "(absent)")
            found = _first_difference(a[key], b[key], f"{where}.{key}")
            if found:
                return found
        return None
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        for i, (x, y) in enumerate(zip(a, b)):
            found = _first_difference(x, y, f"{where}[{i}]")
            if found:
                return found
        return None
    return None if a == b else (where.lstrip(".") or "(the whole file)", a, b)


def check_interface(directory: str | pathlib.Path, config: TrainConfig, params: dict, meta: dict) -> None:
    """Refuse an exported directory whose interface.json differs from the one its config.yaml, parameters and
    meta.json give (ConfigError naming the file and the first differing entry)."""
    directory = pathlib.Path(directory)
    formats = [f for f, name in FORMAT_FILES.items() if (directory / name).is_file()]
    origin = {k: v for k, v in meta.items() if k != "exported_by"}
    derived = json.loads(json.dumps(interface(PolicyStep(config, params), config, origin, formats)))
    found = _first_difference(read_interface(directory), derived)
    if found:
        where, stored, expected = found
        raise ConfigError(
            f"{str(directory / INTERFACE_FILE)!r} does not match the policy it describes: {where} is "
            f"{json.dumps(stored)[:80]} there, {json.dumps(expected)[:80]} from config.yaml; export the policy again"
        )
