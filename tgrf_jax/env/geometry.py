"""2-D vector helpers. Points are stored as (..., 2) arrays; norms are written per component because a
reduction over a trailing axis of size 2 vectorises poorly on CPU (about 3x slower in XLA:CPU)."""

from __future__ import annotations

import jax.numpy as jnp


def norm(v):
    """Euclidean norm over the trailing axis of size 2."""
    return jnp.sqrt(jnp.square(v[..., 0]) + jnp.square(v[..., 1]))


def safe_norm(v, eps=1e-12):
    """Norm whose value and gradient stay finite at zero."""
    return jnp.sqrt(jnp.maximum(jnp.square(v[..., 0]) + jnp.square(v[..., 1]), eps))
