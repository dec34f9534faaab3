"""A people sensor's errors: noisy positions and velocities, missed people, phantoms and late frames (docs/sensing.md).

They change what the robot observes and nothing else: the env judges collisions, rewards and metrics on the true
state. A frame (`Detections`) is built from the true humans, the people the sensor could see (range, occlusion,
field of view) and the predictor's predictions; the observation then reads the frame `latency` steps old.
Every error is a traced number: zero (the default) leaves the frame exactly the true one.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from tgrf_jax.env.prediction import constant_velocity
from tgrf_jax.env.types import Detections, EnvParams, Humans, Robot, SensorErrors


def configured_errors(params: EnvParams, capacity: int) -> SensorErrors:
    """The params' sensor errors; the latency rounded to whole steps within the delay buffer's `capacity`."""
    return SensorErrors(
        noise=params.detection_noise,
        dropout=params.detection_dropout,
        false_rate=params.false_detections,
        latency=jnp.clip(jnp.round(params.detection_latency), 0, capacity).astype(jnp.int32),
        fov=params.sensor_fov,
    )


def draw_errors(key, params: EnvParams, capacity: int) -> SensorErrors:
    """An episode's sensor errors, each uniform between perfect sensing and the params' value: noise, dropout and
    false detections from 0, the latency among 0..L steps, the field of view between the params' and 360 degrees."""
    top = configured_errors(params, capacity)
    u = jax.random.uniform(key, (5,))
    return SensorErrors(
        noise=u[0] * top.noise,
        dropout=u[1] * top.dropout,
        false_rate=u[2] * top.false_rate,
        latency=jnp.minimum(jnp.floor(u[3] * (top.latency + 1)).astype(jnp.int32), top.latency),
        fov=360.0 - u[4] * (360.0 - top.fov),
    )


def capped_poisson(key, mean, cap: int):
    """A Poisson(mean) count capped at `cap`, by inverting its CDF over 0..cap-1 (fixed size, vmappable)."""
    j = jnp.arange(1, cap, dtype=jnp.float32)
    # log pmf(j) = -mean + sum_{i<=j} log(mean / i); a zero mean gives -inf terms and pmf (1, 0, 0, ...)
    log_pmf = -mean + jnp.concatenate([jnp.zeros(1), jnp.cumsum(jnp.log(mean / j))])
    cdf = jnp.cumsum(jnp.exp(log_pmf))
    return jnp.minimum(jnp.sum(jax.random.uniform(key) >= cdf, dtype=jnp.int32), cap)


def perceive(
    key, robot: Robot, humans: Humans, visible, predictions, params: EnvParams, errors: SensorErrors, predictor: str
) -> Detections:
    """This step's frame: the visible humans with Gaussian errors on position and velocity, each missed with the
    dropout probability, then phantoms in the free slots. An error that is zero costs nothing: where the params are
    shared by a batch (training, evaluation) its step is skipped, and the frame is exactly the true one."""
    k_noise, k_drop, k_phantom = jax.random.split(key, 3)
    frame = Detections(pos=humans.pos, vel=humans.vel, radius=humans.radius, seen=visible, pred=predictions)
    frame = _when(errors.noise > 0, lambda f: add_noise(k_noise, f, errors.noise, params.dt, predictor), frame)
    frame = _when(errors.dropout > 0, lambda f: drop(k_drop, f, errors.dropout), frame)
    return _when(errors.false_rate > 0, lambda f: add_phantoms(k_phantom, f, robot, params, errors), frame)


def _when(flag, change, frame: Detections) -> Detections:
    return jax.lax.cond(flag, change, lambda f: f, frame)


def add_noise(key, frame: Detections, std, dt, predictor: str) -> Detections:
    """`frame` with Gaussian errors of `std` on every position and velocity component. Predictions follow the
    perceived detection: const_vel extrapolates the noisy position and velocity; truth and gst keep the predicted
    displacements of the true state (their model reads true tracks) from the noisy position."""
    k_pos, k_vel = jax.random.split(key)
    pos = frame.pos + std * jax.random.normal(k_pos, frame.pos.shape)
    vel = frame.vel + std * jax.random.normal(k_vel, frame.vel.shape)
    if frame.pred is None:
        pred = None
    elif predictor == "const_vel":
        pred = constant_velocity(pos, vel, dt, frame.pred.shape[1])
    else:
        pred = frame.pred + (pos - frame.pos)[:, None, :]
    return frame.replace(pos=pos, vel=vel, pred=pred)


def drop(key, frame: Detections, probability) -> Detections:
    """`frame` with each detected person missed with `probability`."""
    return frame.replace(seen=frame.seen & ~(jax.random.uniform(key, frame.seen.shape) < probability))


def add_phantoms(key, frame: Detections, robot: Robot, params: EnvParams, errors: SensorErrors) -> Detections:
    """`frame` with phantom people in its first free slots: a Poisson(false_rate) count capped by the free slots,
    each placed uniformly over the sensed area (within range and field of view, clear of the robot) with a human's
    radius and a walking velocity in any direction, predicted at constant velocity."""
    n = frame.seen.shape[0]
    k_count, k_draw = jax.random.split(key)
    free = ~frame.seen
    phantom = free & (jnp.cumsum(free, dtype=jnp.int32) <= capped_poisson(k_count, errors.false_rate, n))
    u = jax.random.uniform(k_draw, (n, 5))
    radius = params.human_radius_min + u[:, 0] * (params.human_radius_max - params.human_radius_min)
    near = params.robot_radius + radius  # edge distance 0 .. sensor_range, uniform over the area
    far = near + params.sensor_range
    dist = jnp.sqrt(jnp.square(near) + u[:, 1] * (jnp.square(far) - jnp.square(near)))
    bearing = robot.heading + (u[:, 2] - 0.5) * jnp.deg2rad(errors.fov)
    pos = robot.pos + dist[:, None] * jnp.stack([jnp.cos(bearing), jnp.sin(bearing)], axis=-1)
    direction = 2.0 * jnp.pi * u[:, 3]
    vel = (u[:, 4] * params.human_v_pref_max)[:, None] * jnp.stack([jnp.cos(direction), jnp.sin(direction)], axis=-1)
    pred = None if frame.pred is None else constant_velocity(pos, vel, params.dt, frame.pred.shape[1])
    fake = Detections(pos=pos, vel=vel, radius=radius, seen=phantom, pred=pred)
    return jax.tree_util.tree_map(
        lambda p, f: jnp.where(phantom.reshape(phantom.shape + (1,) * (f.ndim - 1)), p, f), fake, frame
    )


def fill_buffer(frame: Detections, capacity: int) -> Detections:
    """A delay buffer of `capacity` frames, every one `frame` (an episode starts as if it had always looked so)."""
    return jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (capacity,) + x.shape), frame)


def delay(buffer: Detections, frame: Detections, latency) -> tuple[Detections, Detections]:
    """(the frame `latency` steps old, the buffer with `frame` pushed in); `latency` 0 is `frame` itself."""
    frames = jax.tree_util.tree_map(lambda b, f: jnp.concatenate([f[None], b]), buffer, frame)
    late = jax.tree_util.tree_map(lambda x: x[latency], frames)
    return late, jax.tree_util.tree_map(lambda x: x[:-1], frames)
