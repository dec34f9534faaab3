"""linearProgram1 and linearProgram2 for every problem, event driven: each round solves LP1 on a problem's
pending violated line, then looks ahead to the next one; the rounds run dense over blocks of problems.

Tables are (L, P): L line slots in any order, P problems (agents) on the minor axis; ``rank`` (L, P) is each
line's place in RVO2's sequence and ``valid`` marks the lines that exist."""

from __future__ import annotations

import jax.numpy as jnp
from jax import lax

from tgrf_jax.env.orca.numerics import RVO_EPSILON, _computed_once, _det, _safe_inv, _safe_sqrt


def _slot_bits(n):
    """Bits of a packed key that hold the slot (a power-of-two packing: shifts and masks fuse freely into
    XLA:CPU loops, while integer division and remainder are materialised like any division)."""
    return max(1, (n - 1).bit_length())


def _pack(rank, slot, n):
    return (rank << _slot_bits(n)) | slot


def _key_slot(key, n):
    return key & ((1 << _slot_bits(n)) - 1)


def _key_rank(key, n):
    return key >> _slot_bits(n)  # arithmetic shift: rank -1 stays -1


def _none_key(n):
    """The key of 'no line' (rank n): larger than every real key."""
    return _pack(n, 0, n)


def _min_key(hit_row, rank, n_slots):
    """Packed (rank, slot) key (:func:`_pack`) of the lowest-ranked line j where hit_row(j) (P,) holds (rank
    n_slots if none): an elementwise min over the L rows, so that the problems stay on the vectorised axis.
    (Row by row: a whole (L, P) mask, sliced per row, would be materialised instead of fused.)"""
    n = rank.shape[0]
    none = _pack(n_slots, 0, n)
    key = jnp.where(hit_row(0), _pack(rank[0], 0, n), none)
    for j in range(1, n):
        key = jnp.minimum(key, jnp.where(hit_row(j), _pack(rank[j], j, n), none))
    return key


def _pick_row(x, b):
    """x[b[p], p] for an (L, P) table, as a select chain over its rows: inside a loop fusion over the problems
    this is a few vector selects, where a gather would be a separate, scalar loop."""
    out = x[0]
    for j in range(1, x.shape[0]):
        out = jnp.where(b == j, x[j], out)
    return out


def _lp1_bounds(radius, key, px, py, dx, dy, valid, rank, *start):
    """linearProgram1's feasible interval (t_left, t_right) on the line that ``key`` (packed (rank, slot), see
    :func:`_min_key`) points to, constrained by the valid lines ranked before it; t_left = inf where RVO2's
    linearProgram1 returns false, so that ``t_left <= t_right`` is its success.  Meant for one loop over the
    problems (:func:`numerics._computed_once`): the divisions come last, because XLA:CPU does not fuse a division into
    more than one consumer and would split the chain into one loop per use.

    The running bounds are kept as fractions num/den with den > 0, compared by cross-multiplication, so the
    per-line chain has no division; RVO2's min/max of rounded quotients picks the same line up to rounding
    ties.  ``start``: none, or (t_left, t_right, bad) (L, P) tables of every line's interval from the obstacle
    lines (:func:`obstacle_lp._obstacle_bounds`), which RVO2 ranks before all of these lines.
    """
    n = rank.shape[0]
    b, before = _key_slot(key, n), _key_rank(key, n)
    pix, piy, dix, diy = (_pick_row(x, b) for x in (px, py, dx, dy))
    dot = pix * dix + piy * diy
    disc = dot * dot + radius * radius - (pix * pix + piy * piy)
    sq = _safe_sqrt(disc)
    n_left, n_right = -dot - sq, -dot + sq
    d_left = d_right = jnp.ones_like(dot)
    bad = disc < 0.0
    if start:
        o_left, o_right, o_bad = (_pick_row(x, b) for x in start)
        n_left, n_right, bad = jnp.maximum(n_left, o_left), jnp.minimum(n_right, o_right), bad | o_bad
    for j in range(n):
        prev = valid[j] & (rank[j] < before)
        den = _det(dix, diy, dx[j], dy[j])
        num = _det(dx[j], dy[j], pix - px[j], piy - py[j])
        parallel = jnp.abs(den) <= RVO_EPSILON
        use = prev & ~parallel
        bad = bad | (prev & parallel & (num < 0.0))
        right = use & (den >= 0.0) & (num * d_right < n_right * den)  # num/den < tRight
        n_right = jnp.where(right, num, n_right)
        d_right = jnp.where(right, den, d_right)
        left = use & (den < 0.0) & (num * d_left < n_left * den)  # num/den > tLeft (den < 0)
        n_left = jnp.where(left, -num, n_left)
        d_left = jnp.where(left, -den, d_left)
    return jnp.where(bad, jnp.inf, n_left / d_left), n_right / d_right


def _lp2_start(radius, optx, opty, direction_opt):
    """linearProgram2's initial result."""
    if direction_opt:  # optVelocity is a unit direction
        return optx * radius, opty * radius
    # RVO2: normalize(optVelocity) * radius, i.e. (opt * (1 / |opt|)) * radius, if outside the disk
    opt_sq = optx * optx + opty * opty
    clamp = opt_sq > radius * radius
    inv = _safe_inv(_safe_sqrt(opt_sq))
    return jnp.where(clamp, (optx * inv) * radius, optx), jnp.where(clamp, (opty * inv) * radius, opty)


def _lp1_optimum(optx, opty, pix, piy, dix, diy, t_left, t_right, direction_opt):
    """linearProgram1's optimum on its line p + t d within [t_left, t_right]: the end pointing along the
    direction ``opt`` (direction_opt), else the point nearest to ``opt``, clamped."""
    if direction_opt:
        return jnp.where(optx * dix + opty * diy > 0.0, t_right, t_left)
    t = dix * (optx - pix) + diy * (opty - piy)
    return jnp.where(t < t_left, t_left, jnp.where(t > t_right, t_right, t))


def _next_key(radius, take, key, r, px, py, dx, dy, valid, rank, depth):
    """Packed key of the lowest-ranked valid line ranked after ``key`` whose penetration det(d, p - r) exceeds
    depth, where ``take`` holds (none elsewhere): where RVO2's loop does work next.  One loop."""
    n = rank.shape[0]
    rx, ry, after = jnp.real(r), jnp.imag(r), _key_rank(key, n)

    def hit_row(j):
        return valid[j] & (rank[j] > after) & (_det(dx[j], dy[j], px[j] - rx, py[j] - ry) > depth)

    return jnp.where(take, _min_key(hit_row, rank, n), _none_key(n))


def _lp2_init(lines, rank, valid, radius, optx, opty, direction_opt, start=None):
    """linearProgram2's initial state (r, key, fail_at) for :func:`_lp2_round`.  ``start``: None, or the
    result after the obstacle lines and whether to go on (:func:`obstacle_lp._obstacle_walk`)."""
    n = rank.shape[0]
    if start is None:
        rx, ry = _lp2_start(radius, optx, opty, direction_opt)
        before_all = jnp.full(rx.shape, _pack(-1, 0, n), jnp.int32)  # rank -1: every line is after it
        r, go = lax.complex(rx, ry), jnp.ones(rx.shape, bool)
    else:
        (r, go), before_all = start, jnp.full(start[1].shape, _pack(-1, 0, n), jnp.int32)
    key = _computed_once(_next_key, radius, go, before_all, r, *lines, valid, rank, 0.0)
    return r, key, jnp.full(r.shape, n, jnp.int32)


def _lp2_round(lines, rank, valid, radius, optx, opty, direction_opt, state, bounds=()):
    """One step of linearProgram2 for every problem: solve LP1 on the pending violated line, then look ahead
    to the next violated line, so that a problem is pending exactly while RVO2 still has work to do.

    state = (r, key, fail_at): the result as complex(x, y); the packed key of the pending line (rank n: none,
    finished); the rank of the line where LP1 failed (n: none).  On failure the result stays and the walk
    stops, as in RVO2.  Each step is a handful of loops: LP1 and the look-ahead each run as one.
    """
    r, key, fail_at = state
    n = rank.shape[0]
    found = key < _none_key(n)
    t_left, t_right = _computed_once(_lp1_bounds, radius, key, *lines, valid, rank, *bounds)
    ok = t_left <= t_right
    pix, piy, dix, diy = (_pick_row(x, _key_slot(key, n)) for x in lines)
    t = _lp1_optimum(optx, opty, pix, piy, dix, diy, t_left, t_right, direction_opt)
    take = found & ok
    r = jnp.where(take, lax.complex(pix + t * dix, piy + t * diy), r)
    fail_at = jnp.where(found & ~ok, _key_rank(key, n), fail_at)
    key = _computed_once(_next_key, radius, take, key, r, *lines, valid, rank, 0.0)
    return r, key, fail_at


def _blocked(solve, tables, n_out, block):
    """solve(*block_tables) -> n_out (block,) arrays, run over consecutive blocks of the problems (the minor
    axis of every table) in a loop and stitched together.  The last block is shifted back to end at P (its
    overlap with the previous block is solved twice, identically), so nothing is padded."""
    n_prob = tables[0].shape[-1]
    block = min(block, n_prob)
    n_blocks = -(-n_prob // block)

    def body(i, outs):
        start = jnp.minimum(i * block, n_prob - block)
        part = solve(*(lax.dynamic_slice_in_dim(t, start, block, axis=t.ndim - 1) for t in tables))
        return tuple(lax.dynamic_update_slice_in_dim(o, v, start, 0) for o, v in zip(outs, part))

    outs = tuple(jnp.zeros((n_prob,), dt) for dt in n_out)
    return lax.fori_loop(0, n_blocks, body, outs)


def _lp2_dense(lines, rank, valid, radius, optx, opty, direction_opt, start=None, bounds=()):
    """linearProgram2 for P problems in dense rounds (every problem every round) until none is pending.

    Used on blocks of problems (linearProgram2 itself, and the projected lines of a linearProgram3 chunk):
    there compacting the pending problems costs more in gathers and scatters than the rounds it saves (2.4
    violated lines per LP2 on average, 3.2 inside LP3, rarely over 8).  With obstacles, ``start`` and
    ``bounds`` carry the obstacle lines' part (:func:`_lp2_init`, :func:`_lp1_bounds`)."""
    n = rank.shape[0]
    state = _lp2_init(lines, rank, valid, radius, optx, opty, direction_opt, start)
    r, _, fail_at = lax.while_loop(
        lambda s: jnp.min(s[1]) < _none_key(n),
        lambda s: _lp2_round(lines, rank, valid, radius, optx, opty, direction_opt, s, bounds),
        state,
    )
    return r, fail_at


def _linear_program2(lines, rank, radius, optx, opty, block, start=None, bounds=()):
    """linearProgram2 for every problem (lines (L, P), rank (L, P), the rest (P,)): dense rounds over blocks of
    consecutive problems.  Returns the result as complex(x, y) and the rank of the line where it failed (L:
    none).  With obstacles, ``start`` = (result after the obstacle lines, go on) and ``bounds`` (their
    intervals on these lines, :func:`obstacle_lp._obstacle_bounds`)."""
    n = rank.shape[0]

    def solve_block(px, py, dx, dy, rank, radius, optx, opty, *extra):
        return _lp2_dense(
            (px, py, dx, dy),
            rank,
            rank < n,
            radius,
            optx,
            opty,
            False,
            start=tuple(extra[:2]) or None,
            bounds=extra[2:],
        )

    tables = tuple(lines) + (rank, radius, optx, opty) + (() if start is None else tuple(start) + tuple(bounds))
    return _blocked(solve_block, tables, (jnp.complex64, jnp.int32), block)
