"""Whether the humans make progress: the stuck-human measure (docs/metrics.md) and the state it needs.

A human is *stuck* on a step when it is active, farther than `NEAR_GOAL` from its goal, and has stayed within
`STILL_DISTANCE` of one point for at least `STILL_SECONDS`. The point is an anchor that moves to the human
whenever the human gets `STILL_DISTANCE` away from it, so the state is two numbers per human whatever the time
step (a window of past positions would need a length fixed at compile time, while `env.dt` is traced).
"""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct

from tgrf_jax.env.types import Humans

STILL_DISTANCE = 0.5  # metres
STILL_SECONDS = 5.0
NEAR_GOAL = 1.0  # metres: a human this close to its goal is arriving, not stuck


@struct.dataclass
class Progress:
    """anchor (N, 2): where each human was when its current still spell began; since (N,) int32: that step."""

    anchor: jnp.ndarray
    since: jnp.ndarray


def fresh(humans: Humans, step_count=0) -> Progress:
    return Progress(humans.pos, jnp.full(humans.pos.shape[:-1], step_count, jnp.int32))


def update(progress: Progress, humans: Humans, step_count) -> Progress:
    """The anchors after a step: a human that got `STILL_DISTANCE` from its anchor starts a new still spell."""
    offset = humans.pos - progress.anchor
    moved = jnp.sum(offset * offset, axis=-1) >= STILL_DISTANCE**2
    return Progress(
        jnp.where(moved[..., None], humans.pos, progress.anchor), jnp.where(moved, step_count, progress.since)
    )


def still_seconds(progress: Progress, step_count, dt):
    """How long (N,) each human has stayed near its anchor."""
    return (step_count - progress.since).astype(jnp.float32) * dt


def away_from_goal(humans: Humans):
    offset = humans.pos - humans.goal
    return humans.active & (jnp.sum(offset * offset, axis=-1) > NEAR_GOAL**2)


def stuck(progress: Progress, humans: Humans, step_count, dt):
    """The humans (N,) stuck on this step (see the module doc)."""
    return away_from_goal(humans) & (still_seconds(progress, step_count, dt) >= STILL_SECONDS)


def restart(progress: Progress, who, step_count) -> Progress:
    """A new still spell for the humans `who` (N,) bool (given a new goal, they get a fresh chance)."""
    return progress.replace(since=jnp.where(who, step_count, progress.since))
