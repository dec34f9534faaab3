"""linearProgram3 for the problems whose linearProgram2 failed, as a worklist: each round compacts the pending
problems into chunks and re-solves one line each, a direction-mode linearProgram2 over the projected lines."""

from __future__ import annotations

import jax.numpy as jnp
from jax import lax

from tgrf_jax.env.orca.linear_program import (
    _key_rank,
    _key_slot,
    _lp2_dense,
    _min_key,
    _next_key,
    _none_key,
    _pack,
)
from tgrf_jax.env.orca.numerics import (
    RVO_EPSILON,
    _columns,
    _componentwise,
    _computed_once,
    _det,
    _safe_inv,
    _safe_sqrt,
)
from tgrf_jax.env.orca.obstacle_lp import _lp3_obstacle_part, _obstacle_bounds, _obstacle_walk


def _pick(x, b):
    """x[b[p], p] for an (L, P) table, as a gather (a fusion boundary: what produced b is not recomputed)."""
    return jnp.take_along_axis(x, b[None, :], axis=0, mode="clip")[0]


def _projected_lines(pix, piy, dix, diy, px, py, dx, dy):
    """linearProgram3's projected lines (point, unit direction) for line i (pi, di; (P, 1)) and lines j (P, L):
    where line j's penetration equals line i's (the midline between them where they are parallel)."""
    determinant = _det(dix, diy, dx, dy)
    parallel = jnp.abs(determinant) <= RVO_EPSILON
    s = _det(dx, dy, pix - px, piy - py) / jnp.where(parallel, 1.0, determinant)
    qpx = jnp.where(parallel, 0.5 * (pix + px), pix + s * dix)
    qpy = jnp.where(parallel, 0.5 * (piy + py), piy + s * diy)
    ddx, ddy = dx - dix, dy - diy
    inv_len = _safe_inv(_safe_sqrt(ddx * ddx + ddy * ddy))  # RVO2 normalize(): v * (1 / abs(v))
    return qpx, qpy, ddx * inv_len, ddy * inv_len


def _lp3_round(lines, rank, valid, radius, state, obst=None):
    """One step of linearProgram3: the pending line is penetrated deeper than the current worst; minimise its
    penetration subject to the earlier lines not exceeding it (direction-mode LP2 on the projected lines),
    then look ahead to the next such line.  state = (r, distance, key): the result as complex(x, y), the
    current worst penetration and the packed key of the pending line (rank L: none).

    ``obst`` (:class:`obstacle_lp._ObstacleLP`): RVO2's projected lines start with the obstacle lines, unchanged (hard
    constraints), so the inner LP2 first walks them (:func:`obstacle_lp._obstacle_walk`), then goes on with the
    projected agent lines."""
    px, py, dx, dy = lines
    r, distance, key = state
    n = px.shape[0]
    b, i_rank = _key_slot(key, n), _key_rank(key, n)
    pix, piy, dix, diy = (p[None, :] for p in (_pick(x, b) for x in lines))

    projected = _componentwise(_projected_lines, (pix, piy, dix, diy) + tuple(lines), 4, px.shape)
    parallel = jnp.abs(_det(dix, diy, dx, dy)) <= RVO_EPSILON
    qvalid = valid & (rank < i_rank[None, :]) & ~(parallel & (dix * dx + diy * dy > 0.0))
    nx, ny = -diy[0], dix[0]  # optimise towards line i's valid side
    if obst is None:
        s, lp2_fail = _lp2_dense(projected, rank, qvalid, radius, nx, ny, True)
        ok = lp2_fail == n
    else:
        s0, fail_o = _obstacle_walk(obst, radius, nx, ny, True)
        walked = fail_o == obst.count
        s, lp2_fail = _lp2_dense(
            projected, rank, qvalid, radius, nx, ny, True, start=(s0, walked), bounds=_obstacle_bounds(obst, projected)
        )
        ok = walked & (lp2_fail == n)
    r = jnp.where(ok, s, r)  # a failed inner LP2 (rounding) keeps the result, as in RVO2
    distance = _det(dix[0], diy[0], pix[0] - jnp.real(r), piy[0] - jnp.imag(r))
    key = _computed_once(_next_key, radius, jnp.ones(r.shape, bool), key, r, *lines, valid, rank, distance)
    return r, distance, key


def _worklist(step, tables, state, pending, n_rounds, chunk):
    """Run ``step`` rounds on the pending problems only, gathered into chunks of ``chunk`` problems.

    tables: read-only (P,) or (L, P) arrays; state: (P,) arrays; step(table_columns, state_rows) returns the
    new state rows and their pending flags.  Each round compacts the pending problems and runs them in as many
    chunks as they fill; the loop ends when nothing is pending (or after n_rounds), so the cost follows the
    actual work.  Only ever traced outside vmap (the custom_vmap rule hands it the whole batch).
    """
    n_prob = pending.shape[0]
    size = max(1, min(chunk, n_prob))
    n_chunks = -(-n_prob // size)

    def run_round(carry):
        state, pending, rounds = carry
        count = jnp.sum(pending, dtype=jnp.int32)
        order = jnp.nonzero(pending, size=n_chunks * size, fill_value=n_prob)[0].astype(jnp.int32)

        def run_chunk(c, carry):
            state, pending = carry
            sel = lax.dynamic_slice_in_dim(order, c * size, size)
            rows = jnp.minimum(sel, n_prob - 1)
            new, pend = step(tuple(_columns(t, rows) for t in tables), tuple(x[rows] for x in state))
            state = tuple(x.at[sel].set(v, mode="drop") for x, v in zip(state, new))  # padding is dropped
            return state, pending.at[sel].set(pend, mode="drop")

        state, pending = lax.fori_loop(0, (count + size - 1) // size, run_chunk, (state, pending))
        return state, pending, rounds + 1

    def more(carry):
        return (carry[2] < n_rounds) & jnp.any(carry[1])

    return lax.while_loop(more, run_round, (state, pending, jnp.zeros((), jnp.int32)))[0]


def _linear_program3(lines, rank, radius, r, fail_at, chunk, obst=None, fail_o=None):
    """linearProgram3 from the failing line (violated by the current result), only for the problems whose
    linearProgram2 failed (fail_at < L), as a worklist.  Returns the new result (complex).

    With obstacles (``obst``, :class:`obstacle_lp._ObstacleLP`): where linearProgram2 failed on obstacle row
    fail_o (< count), the loop first runs over the obstacle lines from there
    (:func:`obstacle_lp._lp3_obstacle_part`), then goes on with the agent lines penetrated deeper; the agent
    lines' projected lines come after the obstacle lines (:func:`_lp3_round`)."""
    n = rank.shape[0]
    fail_key = _computed_once(
        lambda rank, fail_at: _min_key(lambda j: (rank[j] < n) & (rank[j] == fail_at), rank, n), rank, fail_at
    )
    distance = jnp.zeros(r.shape, jnp.float32)
    pending = fail_at < n
    if obst is not None:
        in_obst = fail_o < obst.count
        r, distance = _lp3_obstacle_part(obst, radius, r, fail_o)
        before_all = jnp.full(r.shape, _pack(-1, 0, n), jnp.int32)
        after = _computed_once(_next_key, radius, in_obst, before_all, r, *lines, rank < n, rank, distance)
        fail_key = jnp.where(in_obst, after, fail_key)
        pending = fail_key < _none_key(n)

    def lp3_step(t, s):
        new = _lp3_round(t[:4], t[4], t[4] < n, t[5], s, None if obst is None else obst._replace(count=t[6], cols=t[7]))
        return new, new[2] < _none_key(n)

    problems = jnp.arange(r.shape[0], dtype=jnp.int32)
    tables = tuple(lines) + (rank, radius) + (() if obst is None else (obst.count, problems))
    state = (r, distance, fail_key)
    return _worklist(lp3_step, tables, state, pending, n, chunk)[0]
