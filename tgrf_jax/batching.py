"""A conditional that stays a conditional under ``jax.vmap``.

``lax.cond`` with a batched predicate becomes a select: every element pays for both branches. Environments
are stepped as vmapped batches, and some per-step work is rarely needed by any element (human goal changes
fall due once every 20 steps), so a batch should skip it when no element needs it.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax

__all__ = ["cond_any"]


def cond_any(pred, true_fn, false_fn, *operands):
    """``lax.cond(pred, true_fn, false_fn, *operands)`` that, under ``vmap``, runs ``true_fn`` on the batch
    (and selects its result per element by ``pred``) only when some element's ``pred`` holds, and only
    ``false_fn`` otherwise.

    Both functions must be pure and take every traced value they use as an operand (a ``custom_vmap``
    function may not close over tracers). Results equal ``lax.cond``'s bit for bit. Not differentiable.
    Under nested ``vmap`` the outer levels fall back to a select, which is still correct.
    """

    @jax.custom_batching.custom_vmap
    def branch(pred, *ops):
        return lax.cond(pred, true_fn, false_fn, *ops)

    @branch.def_vmap
    def _rule(axis_size, in_batched, pred, *ops):
        pred_batched, *ops_batched = in_batched
        if not pred_batched:
            pred = jnp.broadcast_to(pred, (axis_size,))
        axes = tuple(jax.tree_util.tree_map(lambda b: 0 if b else None, b) for b in ops_batched)

        def per_element(fn, ops):
            return jax.vmap(fn, in_axes=axes, axis_size=axis_size)(*ops)

        def both(pred, ops):
            chosen, other = per_element(true_fn, ops), per_element(false_fn, ops)
            return jax.tree_util.tree_map(
                lambda a, b: jnp.where(pred.reshape(pred.shape + (1,) * (a.ndim - 1)), a, b), chosen, other)

        out = lax.cond(jnp.any(pred), both, lambda pred, ops: per_element(false_fn, ops), pred, ops)
        return out, jax.tree_util.tree_map(lambda _: True, out)

    return branch(pred, *operands)
