"""A conditional that stays a conditional under ``jax.vmap``, and runs its true branch only where needed.

``lax.cond`` with a batched predicate becomes a select: every element pays for both branches. Environments
are stepped as vmapped batches, and some per-step work is needed by few elements (a human goal change falls due
once every 20 steps of an episode, so about one environment in 20 of a batch needs it on any step once the
episodes are out of step), so a batch should run it only for those elements.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax

__all__ = ["cond_gathered"]


def cond_gathered(pred, true_fn, false_fn, *operands, chunk: int = 32):
    """``lax.cond(pred, true_fn, false_fn, *operands)`` that, under ``vmap``, runs ``false_fn`` on the whole
    batch and ``true_fn`` only on the elements whose ``pred`` holds, gathered into chunks of ``chunk``
    elements (as many chunks as they fill: none when no element needs it), whose results replace those
    elements' results.

    Both functions must be pure, return the same structure, and take every traced value they use as an
    operand (a ``custom_vmap`` function may not close over tracers). Per element the results equal
    ``lax.cond``'s. Not differentiable. Under nested ``vmap`` the outer levels run the chunk loop as often as
    their largest count needs, selecting per element, which is still correct.
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
        size = max(1, min(int(chunk), axis_size))
        n_chunks = -(-axis_size // size)
        order = jnp.nonzero(pred, size=n_chunks * size, fill_value=axis_size)[0].astype(jnp.int32)
        count = jnp.sum(pred, dtype=jnp.int32)

        def gather(rows):
            return tuple(
                jax.tree_util.tree_map(lambda x, a: x if a is None else x[rows], op, ax) for op, ax in zip(ops, axes)
            )

        def run_chunk(c, out):
            sel = lax.dynamic_slice_in_dim(order, c * size, size)
            part = jax.vmap(true_fn, in_axes=axes, axis_size=size)(*gather(jnp.minimum(sel, axis_size - 1)))
            return jax.tree_util.tree_map(lambda o, v: o.at[sel].set(v, mode="drop"), out, part)  # padding: dropped

        out = jax.vmap(false_fn, in_axes=axes, axis_size=axis_size)(*ops)
        out = lax.fori_loop(0, (count + size - 1) // size, run_chunk, out)
        return out, jax.tree_util.tree_map(lambda _: True, out)

    return branch(pred, *operands)
