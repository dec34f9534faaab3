"""ORCA (optimal reciprocal collision avoidance) for all agents at once, with RVO2 semantics.

This reproduces one call of ``RVO::Agent::computeNewVelocity`` for every agent of a scene (agents only, no
obstacles): the ``max_neighbors`` nearest other agents within ``neighbor_dist`` give one ORCA half-plane each,
in ascending distance order; ``linearProgram2`` picks the velocity closest to the preferred one inside all
half-planes and the max-speed disk, and where that 2-D LP is infeasible ``linearProgram3`` minimises the
largest penetration, exactly as RVO2 does (same epsilon, same incremental order, same fallbacks).

How it is vectorised (RVO2's algorithm is sequential and branchy):

* One problem per agent of every scene (p = agent * B + scene), on the minor axis of every array: the lines
  are (L, P) tables with one slot per other agent (agent-index order), so every loop over the problems is
  full-width vector code (with the 20 line slots minor, LLVM vectorised 4-wide).  Each line carries its
  ``rank`` in RVO2's distance-sorted neighbour list; lines outside the ``max_neighbors`` nearest /
  ``neighbor_dist`` are inactive (rank = L).  The LPs follow ``rank``, so nothing is sorted (sorts and
  top_k are slow on XLA:CPU).
* ``linearProgram2`` is driven by events: RVO2 only does O(lines) work at lines that the running result
  violates (about 2.4 per agent in crossing crowds), so each round solves ``linearProgram1`` on a problem's
  pending violated line (a masked scan over the earlier-ranked lines) and then looks ahead to the next
  violated line; a problem is pending exactly while it has one.  The rounds run dense (every problem) over
  blocks of 128 consecutive problems until the block's slowest problem is done: compacting the pending
  problems costs more in gathers than the dense rounds waste.
* ``linearProgram3`` runs only for the agents whose LP2 failed, one round per line it re-solves (about 1.9 per
  failing agent), as a worklist: each round compacts the pending problems into chunks of 128; each round is a
  direction-mode LP2 over the projected lines, run in dense rounds over its chunk.
* XLA:CPU's fusion rules decide the speed, more than the arithmetic: a computation with several outputs gets
  one loop per output (recomputing what they share); a cheap chain is fused into every consumer (recomputed by
  each); a float or integer division is not fused into more than one consumer (the chain is cut there); a
  gather fusion is a scalar loop.  So every expensive chain ends in one output, computed once in one
  vectorised loop behind a conditional that is always true at run time (:func:`_computed_once`): the line
  components and ranks two at a time as complex64 pairs, linearProgram1's two bounds as one complex64 (the
  divisions last), the look-ahead's lowest violated line as one packed (rank, slot) key (packed by shifts,
  not division); masks are formed row by row inside those loops, and the LP1 line is picked by a select chain
  over the rows instead of a gather.
* The worklists and dense rounds are data-dependent loops (``while_loop``s that end when nothing is
  pending).  Under ``vmap`` they would become selects and every agent would pay for the worst one, so
  :func:`solve` carries a ``jax.custom_batching.custom_vmap`` rule: ``jax.vmap`` (nested too) hands the
  whole batch to one kernel, where the loops stay loops and the blocks draw from all scenes.
* Blocks and chunks of 128 problems suit a CPU, where a round costs what its problems cost.  On a GPU a round
  costs a few kernel launches whatever its width, so there one block (and one chunk) spans the whole batch:
  looping over 128-problem blocks would launch kernels for every block in turn, a time that grows with the
  batch.  The block size changes which problems share a loop, never a result (``block`` of
  :func:`solve_with_info`).

Every division and square root is guarded, so no NaN/inf appears even for coincident agents (where RVO2
itself divides 0 by 0), zero velocities or agents without neighbours.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax import lax

__all__ = ["CPU_BLOCK", "RVO_EPSILON", "WHOLE_BATCH", "default_block", "solve", "solve_with_info"]

RVO_EPSILON = 1e-5  # RVO2's RVO_EPSILON (Definitions.h): parallel-line threshold in the LPs.
_BIG = 1e30  # distance key of non-neighbours when ranking (finite, unlike inf)
# linearProgram2's blocks (each runs dense rounds until its slowest problem is done) and linearProgram3's chunks
# (each runs dense inner LP2 rounds until its slowest problem is done), in problems
CPU_BLOCK = 128
WHOLE_BATCH = 2**31 - 1  # one block: all problems (clamped to their number)


def default_block() -> int:
    """The block size for the backend that programs compile for: CPU_BLOCK on a CPU, WHOLE_BATCH elsewhere."""
    return CPU_BLOCK if jax.default_backend() == "cpu" else WHOLE_BATCH


# ---------------------------------------------------------------------------------------------------------
# small helpers (RVO2's Vector2 algebra on split x/y arrays)


def _det(ax, ay, bx, by):
    """RVO2 det(a, b) = a.x * b.y - a.y * b.x (cross product z)."""
    return ax * by - ay * bx


def _safe_inv(x):
    """1/x, with 1 where x == 0 (the caller masks those lanes out)."""
    return 1.0 / jnp.where(x == 0.0, 1.0, x)


def _safe_sqrt(x):
    """sqrt clamped at 0, with a gradient that stays finite at 0."""
    pos = x > 0.0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), 0.0)


# ---------------------------------------------------------------------------------------------------------
# ORCA half-planes


def _orca_lines(rpx, rpy, rvx, rvy, crad, vx, vy, inv_th, inv_dt, tie_sign):
    """One ORCA line per (agent, neighbour) pair, as in Agent::computeNewVelocity.

    rp = other.position - position, rv = velocity - other.velocity, crad = combined radius, v = own velocity.
    ``tie_sign`` (+1/-1, antisymmetric in the pair) picks an escape direction where RVO2 would produce NaN
    (coincident agents whose relative velocity is exactly zero in the collision case).
    Returns (point_x, point_y, dir_x, dir_y).
    """
    dist_sq = rpx * rpx + rpy * rpy
    crad_sq = crad * crad

    # -- no collision: velocity obstacle truncated at time_horizon (cut-off circle + two legs)
    wx = rvx - inv_th * rpx
    wy = rvy - inv_th * rpy
    w_len_sq = wx * wx + wy * wy
    dot1 = wx * rpx + wy * rpy
    on_circle = (dot1 < 0.0) & (dot1 * dot1 > crad_sq * w_len_sq)
    w_len = _safe_sqrt(w_len_sq)
    inv_w = _safe_inv(w_len)  # RVO2 divides a Vector2 by s as multiplication with 1/s
    uwx, uwy = wx * inv_w, wy * inv_w
    circ_dx, circ_dy = uwy, -uwx
    circ_s = crad * inv_th - w_len
    circ_ux, circ_uy = circ_s * uwx, circ_s * uwy

    leg = _safe_sqrt(dist_sq - crad_sq)
    inv_d2 = _safe_inv(dist_sq)
    left = _det(rpx, rpy, wx, wy) > 0.0
    leg_dx = jnp.where(left, (rpx * leg - rpy * crad) * inv_d2, -((rpx * leg + rpy * crad) * inv_d2))
    leg_dy = jnp.where(left, (rpx * crad + rpy * leg) * inv_d2, -((-rpx * crad + rpy * leg) * inv_d2))
    dot2 = rvx * leg_dx + rvy * leg_dy
    leg_ux, leg_uy = dot2 * leg_dx - rvx, dot2 * leg_dy - rvy

    # -- collision: project on the cut-off circle of time step dt
    cwx = rvx - inv_dt * rpx
    cwy = rvy - inv_dt * rpy
    cw_len = _safe_sqrt(cwx * cwx + cwy * cwy)
    degenerate = cw_len == 0.0
    inv_cw = _safe_inv(cw_len)
    cuwx = jnp.where(degenerate, tie_sign, cwx * inv_cw)
    cuwy = jnp.where(degenerate, 0.0, cwy * inv_cw)
    col_dx, col_dy = cuwy, -cuwx
    col_s = crad * inv_dt - cw_len
    col_ux, col_uy = col_s * cuwx, col_s * cuwy

    collide = dist_sq <= crad_sq
    dx = jnp.where(collide, col_dx, jnp.where(on_circle, circ_dx, leg_dx))
    dy = jnp.where(collide, col_dy, jnp.where(on_circle, circ_dy, leg_dy))
    ux = jnp.where(collide, col_ux, jnp.where(on_circle, circ_ux, leg_ux))
    uy = jnp.where(collide, col_uy, jnp.where(on_circle, circ_uy, leg_uy))
    return vx + 0.5 * ux, vy + 0.5 * uy, dx, dy


def _componentwise(fn, args, n_out, shape, extra=()):
    """fn(*args) -> n_out float32 arrays of ``shape``, computed two outputs at a time, plus one more output per
    function of ``extra`` (each fn(*args) -> one float32 array of ``shape``).

    XLA:CPU splits a multi-output elementwise computation into many materialised passes (measured ~20x
    slower than one output), while a single output is one fused loop; so each pair of outputs is its own
    :func:`_computed_once` (one loop, the shared intermediates computed once for both).  This also
    materialises every output once: a cheap elementwise chain with several consumers (the neighbour ranks)
    is otherwise fused into, and recomputed by, each of them.
    """
    outputs = [lambda *a, c=c: fn(*a)[c] for c in range(n_out)] + list(extra)
    values = []
    for c in range(0, len(outputs), 2):
        if c + 1 < len(outputs):
            values += _computed_once(lambda *a, c=c: (outputs[c](*a), outputs[c + 1](*a)), *args)
        else:
            values.append(_computed_once(outputs[c], *args))
    return tuple(values)


def _neighbour_lines(px, py, vx, vy, rad, mask, inv_th, inv_dt, range_sq, k):
    """ORCA lines of every agent towards every other agent, plus RVO2's neighbour order.

    Inputs are (N, B) (agent, scene); inv_th, inv_dt, range_sq are (B,).  Outputs are (N, N, B) with
    [b, a, s] = agent a's line towards agent b in scene s: the point/direction components and ``rank`` (b's
    position in a's distance-sorted neighbour list, i.e. the line's index in RVO2's orcaLines_; n where b is
    not one of a's ``k`` nearest neighbours within range).  The lines stay in agent-index order; the LPs
    follow ``rank``, so nothing is sorted.  Equal distances rank by agent index (RVO2: kd-tree visiting
    order).
    """
    n = px.shape[0]
    idx = jnp.arange(n)
    not_self = (idx[:, None] != idx[None, :])[:, :, None]
    other_idx = idx[:, None, None]
    tie_sign = jnp.where(idx[:, None] > idx[None, :], 1.0, -1.0)[:, :, None]

    # The pairwise differences are formed inside each output's computation: materialised, these (N, N, B)
    # inputs cost more memory traffic than all the arithmetic of the lines.
    def offsets(px, py):
        return px[:, None, :] - px[None, :, :], py[:, None, :] - py[None, :, :]  # other b minus self a

    def pair_lines(px, py, vx, vy, rad, mask, inv_th, inv_dt, range_sq):
        rpx, rpy = offsets(px, py)
        return _orca_lines(rpx, rpy, vx[None, :, :] - vx[:, None, :], vy[None, :, :] - vy[:, None, :],
                           rad[None, :, :] + rad[:, None, :], vx[None, :, :], vy[None, :, :],
                           inv_th[None, None, :], inv_dt[None, None, :], tie_sign)

    def line_rank(px, py, vx, vy, rad, mask, inv_th, inv_dt, range_sq):
        """b's place in a's neighbour order (ties: lower index first), or n where b is not an active
        neighbour: the count of the valid neighbours that are closer."""
        rpx, rpy = offsets(px, py)
        d2 = rpx * rpx + rpy * rpy
        valid = not_self & mask[:, None, :] & (d2 < range_sq[None, None, :])
        key = jnp.where(valid, d2, _BIG)
        rank = jnp.zeros(key.shape, jnp.int32)
        for c in range(n):
            kc = key[c:c + 1]
            rank = rank + ((kc < key) | ((kc == key) & (c < other_idx))).astype(jnp.int32)
        return jnp.where(valid & (rank < k), rank, n).astype(jnp.float32)

    args = (px, py, vx, vy, rad, mask, inv_th, inv_dt, range_sq)
    *lines, rank = _componentwise(pair_lines, args, 4, (n,) + px.shape, extra=(line_rank,))
    return tuple(lines) + (rank.astype(jnp.int32),)


# ---------------------------------------------------------------------------------------------------------
# linear programs, event driven
#
# Arrays are (L, P): L line slots in arbitrary order, P independent problems (agents) on the minor axis;
# ``rank`` (L, P) gives each line's position in RVO2's sequence and ``valid`` marks the lines that exist.
# RVO2 walks the lines in order and does O(L) work only at lines that the running result violates (about 2
# per agent in crowds), so instead of a dense O(L^2) precompute every "round" jumps each problem to its next
# violated line.


def _pick(x, b):
    """x[b[p], p] for an (L, P) table, as a gather (a fusion boundary: what produced b is not recomputed)."""
    return jnp.take_along_axis(x, b[None, :], axis=0, mode="clip")[0]


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


def _computed_once(fn, *args):
    """fn(*args) (one array, or a pair of float32 arrays of one shape), computed in one vectorised loop and
    materialised.

    XLA:CPU fuses a cheap elementwise chain into each of its consumers (recomputing it), and gives every output
    of a computation its own loop (recomputing the shared chain in each).  Here the chain is the branch of a
    conditional whose predicate is only known at run time (always true), so it is one fusion whose result is
    materialised; a pair leaves it as one complex64, which the simplifier cannot split into two chains again
    through the conditional.  (A gather with a run-time index would also be a boundary, but XLA fuses the
    chain into the gather, whose loop is not vectorised.)  Elsewhere fusion follows other rules, and a
    conditional waits for its predicate to reach the host: there this is plain fn(*args).
    """
    if jax.default_backend() != "cpu":
        return fn(*args)
    args = tuple(jnp.asarray(x) for x in args)
    pair = isinstance(jax.eval_shape(fn, *args), tuple)

    def run(args):
        out = fn(*args)
        return lax.complex(*out) if pair else out

    out_type = jax.eval_shape(run, args)
    probe = next((x for x in args if jnp.issubdtype(x.dtype, jnp.floating)), None)
    if probe is None:  # x == x folds to True for integers, not for floats (NaN)
        probe = lax.bitcast_convert_type(args[0].astype(jnp.int32), jnp.float32)
    probe = probe.reshape(-1)[0]
    always = probe == probe  # True (no NaN here), but not a constant
    out = lax.cond(always, run, lambda _: jnp.zeros(out_type.shape, out_type.dtype), args)
    return (jnp.real(out), jnp.imag(out)) if pair else out


def _pick_row(x, b):
    """x[b[p], p] for an (L, P) table, as a select chain over its rows: inside a loop fusion over the problems
    this is a few vector selects, where a gather would be a separate, scalar loop."""
    out = x[0]
    for j in range(1, x.shape[0]):
        out = jnp.where(b == j, x[j], out)
    return out


def _lp1_bounds(radius, key, px, py, dx, dy, valid, rank):
    """linearProgram1's feasible interval (t_left, t_right) on the line that ``key`` (packed (rank, slot), see
    :func:`_min_key`) points to, constrained by the valid lines ranked before it; t_left = inf where RVO2's
    linearProgram1 returns false, so that ``t_left <= t_right`` is its success.  Meant for one loop over the
    problems (:func:`_computed_once`): the divisions come last, because XLA:CPU does not fuse a division into
    more than one consumer and would split the chain into one loop per use.

    The running bounds are kept as fractions num/den with den > 0, compared by cross-multiplication, so the
    per-line chain has no division; RVO2's min/max of rounded quotients picks the same line up to rounding
    ties.
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


def _next_key(radius, take, key, r, px, py, dx, dy, valid, rank, depth):
    """Packed key of the lowest-ranked valid line ranked after ``key`` whose penetration det(d, p - r) exceeds
    depth, where ``take`` holds (none elsewhere): where RVO2's loop does work next.  One loop."""
    n = rank.shape[0]
    rx, ry, after = jnp.real(r), jnp.imag(r), _key_rank(key, n)

    def hit_row(j):
        return valid[j] & (rank[j] > after) & (_det(dx[j], dy[j], px[j] - rx, py[j] - ry) > depth)

    return jnp.where(take, _min_key(hit_row, rank, n), _none_key(n))


def _lp2_init(lines, rank, valid, radius, optx, opty, direction_opt):
    """linearProgram2's initial state (r, key, fail_at) for :func:`_lp2_round`."""
    n = rank.shape[0]
    rx, ry = _lp2_start(radius, optx, opty, direction_opt)
    before_all = jnp.full(rx.shape, _pack(-1, 0, n), jnp.int32)  # rank -1: every line is after it
    r = lax.complex(rx, ry)
    key = _computed_once(_next_key, radius, jnp.ones(rx.shape, bool), before_all, r, *lines, valid, rank, 0.0)
    return r, key, jnp.full(rx.shape, n, jnp.int32)


def _lp2_round(lines, rank, valid, radius, optx, opty, direction_opt, state):
    """One step of linearProgram2 for every problem: solve LP1 on the pending violated line, then look ahead
    to the next violated line, so that a problem is pending exactly while RVO2 still has work to do.

    state = (r, key, fail_at): the result as complex(x, y); the packed key of the pending line (rank n: none,
    finished); the rank of the line where LP1 failed (n: none).  On failure the result stays and the walk
    stops, as in RVO2.  Each step is a handful of loops: LP1 and the look-ahead each run as one.
    """
    r, key, fail_at = state
    n = rank.shape[0]
    found = key < _none_key(n)
    t_left, t_right = _computed_once(_lp1_bounds, radius, key, *lines, valid, rank)
    ok = t_left <= t_right
    pix, piy, dix, diy = (_pick_row(x, _key_slot(key, n)) for x in lines)
    if direction_opt:
        t = jnp.where(optx * dix + opty * diy > 0.0, t_right, t_left)
    else:
        t = dix * (optx - pix) + diy * (opty - piy)
        t = jnp.where(t < t_left, t_left, jnp.where(t > t_right, t_right, t))
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


def _lp2_dense(lines, rank, valid, radius, optx, opty, direction_opt):
    """linearProgram2 for P problems in dense rounds (every problem every round) until none is pending.

    Used on blocks of problems (linearProgram2 itself, and the projected lines of a linearProgram3 chunk):
    there compacting the pending problems costs more in gathers and scatters than the rounds it saves (2.4
    violated lines per LP2 on average, 3.2 inside LP3, rarely over 8)."""
    n = rank.shape[0]
    state = _lp2_init(lines, rank, valid, radius, optx, opty, direction_opt)
    r, _, fail_at = lax.while_loop(
        lambda s: jnp.min(s[1]) < _none_key(n),
        lambda s: _lp2_round(lines, rank, valid, radius, optx, opty, direction_opt, s), state)
    return r, fail_at


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


def _lp3_round(lines, rank, valid, radius, state):
    """One step of linearProgram3: the pending line is penetrated deeper than the current worst; minimise its
    penetration subject to the earlier lines not exceeding it (direction-mode LP2 on the projected lines),
    then look ahead to the next such line.  state = (r, distance, key): the result as complex(x, y), the
    current worst penetration and the packed key of the pending line (rank L: none)."""
    px, py, dx, dy = lines
    r, distance, key = state
    n = px.shape[0]
    b, i_rank = _key_slot(key, n), _key_rank(key, n)
    pix, piy, dix, diy = (p[None, :] for p in (_pick(x, b) for x in lines))

    projected = _componentwise(_projected_lines, (pix, piy, dix, diy) + tuple(lines), 4, px.shape)
    parallel = jnp.abs(_det(dix, diy, dx, dy)) <= RVO_EPSILON
    qvalid = valid & (rank < i_rank[None, :]) & ~(parallel & (dix * dx + diy * dy > 0.0))
    nx, ny = -diy[0], dix[0]  # optimise towards line i's valid side
    s, lp2_fail = _lp2_dense(projected, rank, qvalid, radius, nx, ny, True)
    r = jnp.where(lp2_fail == n, s, r)  # a failed inner LP2 (rounding) keeps the result, as in RVO2
    distance = _det(dix[0], diy[0], pix[0] - jnp.real(r), piy[0] - jnp.imag(r))
    key = _computed_once(_next_key, radius, jnp.ones(r.shape, bool), key, r, *lines, valid, rank, distance)
    return r, distance, key


def _columns(table, cols):
    """table[..., cols] for a (P,) or (L, P) table, gathered element by element so that the result keeps the
    problems as its minor (vectorised) axis: a gather of whole columns is laid out (cols, L) and transposed."""
    if table.ndim == 1:
        return table[cols]
    idx = jnp.broadcast_to(cols[None, :], (table.shape[0], cols.shape[0]))
    return jnp.take_along_axis(table, idx, axis=1, mode="clip")


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


# ---------------------------------------------------------------------------------------------------------
# the batched kernel


def _linear_program2(lines, rank, radius, optx, opty, block):
    """linearProgram2 for every problem (lines (L, P), rank (L, P), the rest (P,)): dense rounds over blocks of
    consecutive problems.  Returns the result as complex(x, y) and the rank of the line where it failed (L:
    none)."""
    n = rank.shape[0]

    def solve_block(px, py, dx, dy, rank, radius, optx, opty):
        return _lp2_dense((px, py, dx, dy), rank, rank < n, radius, optx, opty, False)

    return _blocked(solve_block, tuple(lines) + (rank, radius, optx, opty), (jnp.complex64, jnp.int32), block)


def _linear_program3(lines, rank, radius, r, fail_at, chunk):
    """linearProgram3 from the failing line (violated by the current result), only for the problems whose
    linearProgram2 failed (fail_at < L), as a worklist.  Returns the new result (complex)."""
    n = rank.shape[0]
    fail_key = _computed_once(
        lambda rank, fail_at: _min_key(lambda j: (rank[j] < n) & (rank[j] == fail_at), rank, n), rank, fail_at)

    def lp3_step(t, s):
        new = _lp3_round(t[:4], t[4], t[4] < n, t[5], s)
        return new, new[2] < _none_key(n)

    tables = tuple(lines) + (rank, radius)
    state = (r, jnp.zeros(r.shape, jnp.float32), fail_key)
    return _worklist(lp3_step, tables, state, fail_at < n, n, chunk)[0]


def _solve_scenes(pos, vel, rad, pref, vmax, mask, time_horizon, dt, neighbor_dist, *, k, block):
    """Batched core: pos/vel/pref (B, N, 2), rad/vmax/mask (B, N), scalars (B,).  Returns (B, N, 2) and the
    per-agent LP2 failure flag (B, N)."""
    b, n = rad.shape
    f32 = jnp.float32
    pos, vel, pref = pos.astype(f32), vel.astype(f32), pref.astype(f32)
    a = b * n
    agent_major = lambda x: x.T.reshape(a)  # noqa: E731  (B, N) -> problem p = agent * B + scene
    scene_major = lambda x: x.reshape(n, b).T  # noqa: E731
    radius = agent_major(vmax.astype(f32))
    ox, oy = agent_major(pref[..., 0]), agent_major(pref[..., 1])
    if k == 0:
        rx, ry = _lp2_start(radius, ox, oy, direction_opt=False)
        return jnp.stack([scene_major(rx), scene_major(ry)], -1), jnp.zeros((b, n), bool)

    inv_th = 1.0 / time_horizon.astype(f32)  # RVO2: invTimeHorizon = 1.0f / timeHorizon_
    inv_dt = 1.0 / dt.astype(f32)
    nd = neighbor_dist.astype(f32)
    out = _neighbour_lines(pos[..., 0].T, pos[..., 1].T, vel[..., 0].T, vel[..., 1].T, rad.astype(f32).T,
                           mask.astype(bool).T, inv_th, inv_dt, nd * nd, k)
    lines = tuple(x.reshape(n, a) for x in out[:4])
    rank = out[4].reshape(n, a)

    r, fail_at = _linear_program2(lines, rank, radius, ox, oy, block)
    r = _linear_program3(lines, rank, radius, r, fail_at, block)
    rx, ry, failed = jnp.real(r), jnp.imag(r), fail_at < n
    return jnp.stack([scene_major(rx), scene_major(ry)], -1), scene_major(failed)


@functools.lru_cache(maxsize=None)
def _kernels(k: int, block: int):
    """custom_vmap wrappers for a given (static) neighbour count and block size.

    ``scene`` solves one scene; its vmap rule calls ``batch`` on the whole batch; ``batch``'s own vmap rule
    folds any further vmap axis into its batch axis, so nested vmaps also end in one flat kernel.
    """

    def core(*args):
        return _solve_scenes(*args, k=k, block=block)

    @jax.custom_batching.custom_vmap
    def batch(*args):
        return core(*args)

    @batch.def_vmap
    def _batch_rule(axis_size, in_batched, *args):
        args = [x if bt else jnp.broadcast_to(x, (axis_size,) + x.shape) for x, bt in zip(args, in_batched)]
        inner = args[0].shape[1]
        out, failed = batch(*(x.reshape((axis_size * inner,) + x.shape[2:]) for x in args))
        return (out.reshape((axis_size, inner) + out.shape[1:]),
                failed.reshape((axis_size, inner) + failed.shape[1:])), (True, True)

    @jax.custom_batching.custom_vmap
    def scene(*args):
        out, failed = core(*(x[None] for x in args))
        return out[0], failed[0]

    @scene.def_vmap
    def _scene_rule(axis_size, in_batched, *args):
        args = [x if bt else jnp.broadcast_to(x, (axis_size,) + x.shape) for x, bt in zip(args, in_batched)]
        return batch(*args), (True, True)

    return scene


@functools.partial(jax.jit, static_argnames=("max_neighbors", "block"))
def solve_with_info(positions, velocities, radii, pref_velocities, max_speeds, *, time_horizon, dt,
                    neighbor_dist, max_neighbors, neighbor_mask=None, block=None):
    """Like :func:`solve`, and also returns a (N,) bool: True where RVO2's linearProgram2 failed (the 2-D LP
    was infeasible) and linearProgram3 produced the velocity.  (jitted: eager calls compile once per shape.)
    `block`: problems per LP block (static; None: :func:`default_block`); results do not depend on it."""
    positions = jnp.asarray(positions, jnp.float32)
    n = positions.shape[0]
    if n == 0:
        return jnp.zeros((0, 2), jnp.float32), jnp.zeros((0,), bool)
    k = max(0, min(int(max_neighbors), n - 1))
    mask = jnp.ones((n,), bool) if neighbor_mask is None else jnp.asarray(neighbor_mask, bool)
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    block = default_block() if block is None else int(block)
    if block < 1:
        raise ValueError(f"block = {block}: must be >= 1 (problems per block)")
    return _kernels(k, block)(positions, f32(velocities), f32(radii), f32(pref_velocities), f32(max_speeds), mask,
                       f32(time_horizon), f32(dt), f32(neighbor_dist))


def solve(positions, velocities, radii, pref_velocities, max_speeds, *, time_horizon, dt, neighbor_dist,
          max_neighbors, neighbor_mask=None):
    """New velocities of all agents of one scene after one ORCA step, as RVO2's ``doStep`` sets them.

    Equivalent to an ``RVO::RVOSimulator`` holding these agents (no obstacles) calling
    ``Agent::computeNewVelocity`` for each; the position update is left to the caller.  Jittable and
    vmappable (``jax.vmap(solve)`` runs one batched kernel, see the module docstring).  float32 throughout.

    Args:
      positions: (N, 2) agent centres (RVO2 ``position_``).
      velocities: (N, 2) current velocities (``velocity_``): the ORCA lines are built around them and
        reciprocity assumes the neighbours keep theirs.
      radii: (N,) agent radii (``radius_``); a pair collides when the centre distance is <= the sum.
      pref_velocities: (N, 2) preferred velocities (``prefVelocity_``), the LP's target.
      max_speeds: (N,) speed limits (``maxSpeed_``), the radius of the velocity disk of the LPs.
      time_horizon: ``timeHorizon_``: velocities are safe with respect to other agents for this long.
        Python float or traced scalar.
      dt: simulation time step (``timeStep_``), used only for already-colliding pairs, which are pushed
        apart within one step.  Python float or traced scalar.
      neighbor_dist: ``neighborDist_``: only agents whose centre distance is strictly below it are neighbours.
        Python float or traced scalar.
      max_neighbors: ``maxNeighbors_``: at most this many nearest neighbours are considered (static int,
        clamped to N-1).
      neighbor_mask: optional (N,) bool; agents where it is False are nobody's neighbour (hidden agents).
        Their own result is still computed (finite) and is meaningless to RVO2-equivalence only if they
        should not exist at all.

    Returns:
      (N, 2) float32 new velocities (``newVelocity_``), each within its agent's max speed (up to rounding).
    """
    return solve_with_info(positions, velocities, radii, pref_velocities, max_speeds, time_horizon=time_horizon,
                           dt=dt, neighbor_dist=neighbor_dist, max_neighbors=max_neighbors,
                           neighbor_mask=neighbor_mask)[0]
