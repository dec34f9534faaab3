"""Rules between environment fields that no single field's declared range can state: the ordered pairs of bounds,
an arena that can hold the start-goal distance, a time limit of at least one step, a detection latency of whole
steps within the delay buffer, the mix's scenario list and its weights. `tgrf_jax.config.EnvConfig` checks a
config with them, `tgrf_jax.env.types.EnvParams.validate` concrete parameters (batched ones element by element).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from tgrf_jax import scenario_registry as registry
from tgrf_jax.fields import ConfigError, _show, first_where

__all__ = ["check_detection_latency", "check_env_relations", "check_scenario_weights", "check_weights", "scenario_list"]

_F32 = np.finfo(np.float32)


def scenario_list(names) -> tuple[str, ...]:
    """env.mix_scenarios as a tuple of distinct registered scenario names."""
    known = registry.names()
    allowed = f"allowed: a non-empty list of distinct names among {', '.join(known)}"
    if isinstance(names, (str, bytes)) or not hasattr(names, "__iter__"):
        raise ConfigError(f"env.mix_scenarios = {_show(names)} must be a list of scenario names; {allowed}")
    names = tuple(names)
    for i, name in enumerate(names):
        if not isinstance(name, str) or name not in known:
            raise ConfigError(f"env.mix_scenarios[{i}] = {name!r} is not a scenario; {allowed}")
    if not names or len(set(names)) != len(names):
        raise ConfigError(f"env.mix_scenarios = {_show(list(names))} is empty or names a scenario twice; {allowed}")
    return names


def check_env_relations(values: Mapping[str, Any]) -> None:
    """The constraints between numeric env fields, on a config's values or on concrete `EnvParams` leaves (arrays:
    every element); the scenario weights have their own `check_scenario_weights`."""
    for lo, hi in (
        ("human_radius_min", "human_radius_max"),
        ("human_v_pref_min", "human_v_pref_max"),
        ("orca_neighbor_dist_min", "orca_neighbor_dist_max"),
        ("active_humans_min", "active_humans_max"),
    ):
        hit = first_where(np.asarray(values[lo]) > np.asarray(values[hi]), values[lo], values[hi])
        if hit:
            raise ConfigError(f"env.{lo} = {hit[0]!s} must be <= env.{hi} = {hit[1]!s}")
    diagonal = 2.0 * np.sqrt(2.0) * np.asarray(values["arena_size"])
    hit = first_where(
        np.asarray(values["min_start_goal_dist"]) >= diagonal,
        values["min_start_goal_dist"],
        values["arena_size"],
        diagonal,
    )
    if hit:
        raise ConfigError(
            f"env.min_start_goal_dist = {hit[0]!s} cannot be met in an arena of half-size {hit[1]!s}; "
            f"allowed: < {hit[2]:.3f}"
        )
    hit = first_where(np.asarray(values["time_limit"]) < np.asarray(values["dt"]), values["time_limit"], values["dt"])
    if hit:
        raise ConfigError(f"env.time_limit = {hit[0]!s} must be >= env.dt = {hit[1]!s}")
    latency = np.asarray(values["detection_latency"])
    hit = first_where(latency != np.round(latency), latency)
    if hit:
        raise ConfigError(f"env.detection_latency = {hit[0]!s} must be a whole number of steps")


def check_detection_latency(latency, capacity: int) -> None:
    """env.detection_latency (every element of a batch) within the delay buffer's static capacity."""
    hit = first_where(np.asarray(latency) > capacity, latency)
    if hit:
        raise ConfigError(
            f"env.detection_latency = {hit[0]!s} must be <= env.max_detection_latency = {capacity} (the delay "
            "buffer's capacity, static: raise it to delay detections further)"
        )


def check_scenario_weights(weights, drawn_scenarios=None) -> None:
    """One weight per scenario of the mix (the last axis; leading axes: a batch), as the env draws with them in
    float32 (`check_weights`). `drawn_scenarios` None: any length."""
    check_weights(weights, "env.scenario_weights", "scenario of the mix", drawn_scenarios)


def check_weights(weights, field: str, each: str, labels=None) -> None:
    """Relative frequencies (the last axis; leading axes: a batch), one per `each` (named by `labels`, whose
    number they must match), as the env draws with them in float32: each finite and non-negative, at least one
    positive and their sum finite. Positive means a normal float32 (XLA flushes smaller numbers to zero) and
    finite means within float32's range (a config's 1e39 is float32's inf). `labels` None: any length."""
    w = np.asarray(weights, np.float64)
    names = labels or ()
    count = len(names) if labels is not None else (w.shape[-1] if w.ndim else 1)
    allowed = (
        f"allowed: {count} finite, non-negative numbers, one per {each}"
        + (f" ({', '.join(names)})" if names else "")
        + f", at least one of them positive (>= {_F32.tiny:.3g}) and their sum finite (<= {_F32.max:.3g}, float32)"
    )
    if w.ndim == 0 or w.shape[-1] != count:
        raise ConfigError(f"{field} has {1 if w.ndim == 0 else w.shape[-1]} value(s); {allowed}")
    shown = np.vectorize(lambda x: float(f"{x:.6g}"), otypes=[float])(w).tolist()
    if not np.all(np.isfinite(w) & (w >= 0)):
        raise ConfigError(f"{field} = {shown} has a negative or non-finite weight; {allowed}")
    if np.any(w > _F32.max):
        raise ConfigError(f"{field} = {shown} has a weight beyond float32's range (inf); {allowed}")
    if np.any(w.sum(-1) > _F32.max):
        raise ConfigError(f"{field} = {shown} sum beyond float32's range; {allowed}")
    if np.any(w.max(-1) < _F32.tiny):
        raise ConfigError(f"{field} = {shown} are all zero (in float32); {allowed}")
