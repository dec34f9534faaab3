"""ORCA (optimal reciprocal collision avoidance) for all agents at once, with RVO2 semantics.

This reproduces one call of ``RVO::Agent::computeNewVelocity`` for every agent of a scene: the
``max_neighbors`` nearest other agents within ``neighbor_dist`` give one ORCA half-plane each, in ascending
distance order; ``linearProgram2`` picks the velocity closest to the preferred one inside all half-planes and
the max-speed disk, and where that 2-D LP is infeasible ``linearProgram3`` minimises the largest penetration,
exactly as RVO2 does (same epsilon, same incremental order, same fallbacks).  Optional static obstacles
(polygons as RVO2's ``addObstacle`` takes them) add RVO2's obstacle half-planes first: they are hard
constraints, which linearProgram3 never relaxes.

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

Static obstacles (``obstacles=``; the obstacle-free program is unchanged when there are none):

* ``processObstacles`` runs per scene (:func:`_obstacle_table`): in every call, or once for obstacles that stay
  put (:func:`process_obstacles`, whose table :func:`solve` takes instead of the polygons): the polygons become directed
  edges (a wall of 2 vertices: a -> b and b -> a), and RVO2's kd-tree (a BSP) is built one level at a time
  for all lists and scenes at once, because it matters twice: it splits every edge that straddles a split
  line (inserting a convex vertex; packed layouts get several splits), and ties in an agent's obstacle
  neighbour list (two edges whose shared corner is the nearest point of both: common) keep the order of the
  tree query, which decides which of the two the "already covered" test keeps.  The splits take free edge
  slots (:func:`_edge_capacity`); beyond them an edge stays whole (RVO2 would split it).
* An agent's obstacle lines (:func:`_obstacle_lines`) follow its neighbours in RVO2's order, one round per
  uncovered neighbour for all problems together, with every case of RVO2 (collisions with a vertex or the
  segment, oblique views, convex and non-convex vertices, foreign legs, cut-off circles and line).
* The LPs take them first, as RVO2 does, without putting them into the (L, P) tables, whose loops are
  unrolled over L (compile time and run time grow with L, and an agent has a few obstacle lines among many
  edge slots): linearProgram1's interval on any line starts from what the obstacle lines allow, which does
  not depend on the LP's progress, so the obstacle lines are walked by small loops up to the largest count
  (:class:`_ObstacleLP`).  linearProgram3 keeps them unchanged among its projected lines.

Every division and square root is guarded, so no NaN/inf appears even for coincident agents (where RVO2
itself divides 0 by 0), zero velocities, agents without neighbours, agents on a wall or zero-length edges.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

__all__ = [
    "CPU_BLOCK",
    "RVO_EPSILON",
    "WHOLE_BATCH",
    "ObstacleTable",
    "default_block",
    "process_obstacles",
    "solve",
    "solve_with_info",
]

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
        return _orca_lines(
            rpx,
            rpy,
            vx[None, :, :] - vx[:, None, :],
            vy[None, :, :] - vy[:, None, :],
            rad[None, :, :] + rad[:, None, :],
            vx[None, :, :],
            vy[None, :, :],
            inv_th[None, None, :],
            inv_dt[None, None, :],
            tie_sign,
        )

    def line_rank(px, py, vx, vy, rad, mask, inv_th, inv_dt, range_sq):
        """b's place in a's neighbour order (ties: lower index first), or n where b is not an active
        neighbour: the count of the valid neighbours that are closer."""
        rpx, rpy = offsets(px, py)
        d2 = rpx * rpx + rpy * rpy
        valid = not_self & mask[:, None, :] & (d2 < range_sq[None, None, :])
        key = jnp.where(valid, d2, _BIG)
        rank = jnp.zeros(key.shape, jnp.int32)
        for c in range(n):
            kc = key[c : c + 1]
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


def _lp1_bounds(radius, key, px, py, dx, dy, valid, rank, *start):
    """linearProgram1's feasible interval (t_left, t_right) on the line that ``key`` (packed (rank, slot), see
    :func:`_min_key`) points to, constrained by the valid lines ranked before it; t_left = inf where RVO2's
    linearProgram1 returns false, so that ``t_left <= t_right`` is its success.  Meant for one loop over the
    problems (:func:`_computed_once`): the divisions come last, because XLA:CPU does not fuse a division into
    more than one consumer and would split the chain into one loop per use.

    The running bounds are kept as fractions num/den with den > 0, compared by cross-multiplication, so the
    per-line chain has no division; RVO2's min/max of rounded quotients picks the same line up to rounding
    ties.  ``start``: none, or (t_left, t_right, bad) (L, P) tables of every line's interval from the obstacle
    lines (:func:`_obstacle_bounds`), which RVO2 ranks before all of these lines.
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
    result after the obstacle lines and whether to go on (:func:`_obstacle_walk`)."""
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

    ``obst`` (:class:`_ObstacleLP`): RVO2's projected lines start with the obstacle lines, unchanged (hard
    constraints), so the inner LP2 first walks them (:func:`_obstacle_walk`), then goes on with the
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
# static obstacles
#
# RVO2 keeps an obstacle as a ring of vertices (Obstacle: point_, unitDir_ to the next vertex, isConvex_);
# each vertex stands for the directed edge to its next vertex.  processObstacles builds a BSP tree over the
# edges (KdTree::buildObstacleTree) that splits every edge straddling a split line, inserting a convex vertex;
# an agent's obstacle neighbours are the edges it sees from their right side within range, in ascending
# distance, exact ties in the order of the tree query.  Both the splits and that order change results (the
# "already covered" test keeps the first of two edges that share a corner), so the tree is rebuilt here.
# Edge tables are (E, B): edge slot, scene; an agent's view of them is (E, N, B), broadcast inside the loops.


class _Edges(NamedTuple):
    """Directed obstacle edges (RVO2: one Obstacle each, the edge from its point_ to its nextObstacle_'s),
    every field (E, B)."""

    ax: jax.Array  # point_
    ay: jax.Array
    bx: jax.Array  # nextObstacle_->point_
    by: jax.Array
    conv_a: jax.Array  # isConvex_ of the two vertices
    conv_b: jax.Array
    dpx: jax.Array  # prevObstacle_->unitDir_ (the previous edge's direction)
    dpy: jax.Array
    dx: jax.Array  # unitDir_ (this edge's direction; a split piece keeps its edge's)
    dy: jax.Array
    dnx: jax.Array  # nextObstacle_->unitDir_ (the next edge's direction)
    dny: jax.Array
    nxt: jax.Array  # int32: slot of the next edge (the one starting at b)
    alive: jax.Array  # bool: the slot holds an edge


class _ObstacleTable(NamedTuple):
    """The processed obstacles of each scene, every field (E, B): the edges after the tree's splits, and for
    each edge e the order of e and its next edge in the tree query (they share a vertex, so their distances
    tie whenever that vertex is the nearest point of both): e comes first iff leftOf(tie_a, tie_b, agent) >= 0
    equals tie_flag; the same for the pair (previous edge, e) in the tie_p* fields."""

    edges: _Edges
    prv: jax.Array  # int32: slot of the previous edge
    tie_ax: jax.Array
    tie_ay: jax.Array
    tie_bx: jax.Array
    tie_by: jax.Array
    tie_flag: jax.Array
    tie_pax: jax.Array
    tie_pay: jax.Array
    tie_pbx: jax.Array
    tie_pby: jax.Array
    tie_pflag: jax.Array


def _left_of(ax, ay, bx, by, cx, cy):
    """RVO2 leftOf(a, b, c) = det(a - c, b - a): positive where c lies left of the line a -> b."""
    return _det(ax - cx, ay - cy, bx - ax, by - ay)


def _normalized(x, y):
    """RVO2 normalize(v) = v * (1 / abs(v)); (0, 0) for a zero vector (RVO2: NaN)."""
    inv = _safe_inv(_safe_sqrt(x * x + y * y))
    return x * inv, y * inv


def _edge_capacity(n_slots: int) -> int:
    """Edge slots for M * V polygon vertex slots: those, plus room for the kd-tree's splits, max(8, half of
    them).  RVO2 splits an edge wherever a split line crosses it: in 3000 layouts of 8 boxes like the
    environment's (32 edges, 0.6 m apart) at most 6 splits; 8 boxes packed in a 10 m square, 4.7 on average
    and up to 28; walls crossing each other up to 1.2 per edge.  The splits beyond this room are not made
    (such an edge stays whole, see :func:`_tree_level`): then agents near it may differ from RVO2."""
    return n_slots + max(8, n_slots // 2)


def _polygon_edges(vx, vy, nv, capacity):
    """RVOSimulator::addObstacle for every polygon slot: vx, vy (M, V, B), nv (M, B) -> :class:`_Edges` with
    ``capacity`` slots, slot m * V + v for vertex v of polygon m (RVO2's vertex order), the rest free."""
    m, v, b = vx.shape
    n = jnp.minimum(nv, v)[:, None, :]
    i = jnp.arange(v, dtype=jnp.int32)[None, :, None]
    alive = (i < n) & (n >= 2)  # addObstacle rejects fewer than 2 vertices
    nxt = jnp.where(i + 1 < n, i + 1, 0)
    prv = jnp.where(i > 0, i - 1, jnp.maximum(n - 1, 0))

    def at(x, j):
        return jnp.take_along_axis(x, jnp.broadcast_to(j, x.shape), axis=1)

    nx, ny = at(vx, nxt), at(vy, nxt)
    ux, uy = _normalized(nx - vx, ny - vy)  # unitDir_ = normalize(next point - point)
    px, py = at(vx, prv), at(vy, prv)
    # isConvex_: leftOf(previous, point, next) >= 0, and true for both ends of a wall (2 vertices)
    conv = (n == 2) | (_left_of(px, py, vx, vy, nx, ny) >= 0.0)
    base = jnp.arange(m, dtype=jnp.int32)[:, None, None] * v
    fields = dict(
        ax=vx,
        ay=vy,
        bx=nx,
        by=ny,
        conv_a=conv,
        conv_b=at(conv, nxt),
        dpx=at(ux, prv),
        dpy=at(uy, prv),
        dx=ux,
        dy=uy,
        dnx=at(ux, nxt),
        dny=at(uy, nxt),
        nxt=jnp.broadcast_to(base + nxt, vx.shape),
        alive=alive,
    )
    pad = capacity - m * v
    out = {}
    for name, x in fields.items():
        x = jnp.where(alive, x, jnp.zeros((), x.dtype)).reshape(m * v, b)
        out[name] = jnp.pad(x, ((0, pad), (0, 0)))
    out["nxt"] = jnp.where(out["alive"], out["nxt"], jnp.arange(capacity, dtype=jnp.int32)[:, None])
    return _Edges(**out)


class _TreeState(NamedTuple):
    """The kd-tree build, one level at a time (all scenes at once)."""

    edges: _Edges
    key: jax.Array  # int32 (E, B): position in its list (the original slot: a split piece keeps its edge's)
    lst: jax.Array  # int32 (E, B): the list (future subtree) an edge waits in; -1 once it is a node (or dead)
    used: jax.Array  # int32 (B,): slots in use
    pair_open: jax.Array  # bool (E, B): edge e and its next edge still wait in one list
    pair_node: jax.Array  # int32 (E, B): the node that separated them
    pair_flag: jax.Array  # bool (E, B): see _ObstacleTable


def _tree_level(state: _TreeState) -> _TreeState:
    """One level of KdTree::buildObstacleTreeRecursive for every waiting list at once.

    Each list picks its split edge i: the first (in list order) minimising (max, min) of the sizes of the
    two sides, where an edge j counts on the left of i if both its ends have leftOf >= -eps, on the right if
    both <= eps, else on both (it will be split).  The others go to the child lists; a straddling edge j is
    cut where it crosses i's line, j keeping the piece from its first vertex (on j's first vertex's side,
    left if its leftOf > 0) and a new convex vertex starting the other piece (RVO2 appends it; here it takes
    the next free slot; without one the edge stays whole on its first vertex's side, unlike RVO2).

    A list in which every edge has all the others on its left (a convex polygon, a wall) gives every
    candidate the same sides (all left), so RVO2 makes it a chain in list order, each node the left child of
    the one before: such a list is placed at once.
    """
    e, lst, key = state.edges, state.lst, state.key
    n_slots = e.ax.shape[0]
    slot = jnp.arange(n_slots, dtype=jnp.int32)[:, None]
    cols = jnp.broadcast_to(jnp.arange(lst.shape[1], dtype=jnp.int32)[None, :], lst.shape)
    waiting = lst >= 0
    n_lists = 2 * n_slots + 1  # list ids: 0 (the root) and 2c + 1, 2c + 2 (the children of node c)

    def per_list(reduce, values, empty):
        """reduce(values) over the edges of each edge's list (a scatter into one entry per list id)."""
        table = jnp.full((n_lists,) + lst.shape[1:], empty, values.dtype)
        table = getattr(table.at[jnp.where(waiting, lst, n_lists), cols], reduce)(values, mode="drop")
        return jnp.take_along_axis(table, jnp.where(waiting, lst, 0), axis=0)

    def classify(ax, ay, ex, ey, jax_, jay, jbx, jby):
        # leftOf(a, b, c) = det(a - c, b - a), with e = b - a computed once per edge (the same rounding)
        l1 = _det(ax - jax_, ay - jay, ex, ey)
        l2 = _det(ax - jbx, ay - jby, ex, ey)
        left = (l1 >= -RVO_EPSILON) & (l2 >= -RVO_EPSILON)
        right = ~left & (l1 <= RVO_EPSILON) & (l2 <= RVO_EPSILON)
        return l1, left, right

    # all pairs (candidate i, edge j, scene): the side counts of every candidate split edge; placed and dead
    # edges get a list id of their own (below -1), so that one comparison finds the pairs of a list
    own = jnp.where(waiting, lst, -2 - slot)
    pairs = (own[:, None] == own[None]) & (slot[:, None] != slot[None])
    ex, ey = e.bx - e.ax, e.by - e.ay
    _, left, right = classify(*(x[:, None] for x in (e.ax, e.ay, ex, ey)), *(x[None] for x in (e.ax, e.ay, e.bx, e.by)))
    # both counts in one reduction (one pass over the pairs): n_left in the low 16 bits, n_right above
    packed = jnp.where(pairs, (~right).astype(jnp.int32) + ((~left).astype(jnp.int32) << 16), 0)
    counts = jnp.sum(packed, axis=1, dtype=jnp.int32)
    n_left, n_right = counts & 0xFFFF, counts >> 16
    chain = waiting & (per_list("max", (n_right > 0).astype(jnp.int32), 0) == 0)
    # the first edge (by key) of the least (max, min) side sizes
    order = (jnp.maximum(n_left, n_right) * (n_slots + 1) + jnp.minimum(n_left, n_right)) * n_slots + key
    chosen = waiting & ~chain & (order == per_list("min", order, jnp.iinfo(jnp.int32).max))
    # each waiting edge's node: the chosen edge of its list (itself if chosen or in a chain)
    node = per_list("max", jnp.where(chosen, slot, -1), -1)
    node = jnp.where(waiting & ~chain, node, slot)

    def at(x, j):
        return jnp.take_along_axis(x, j, axis=0)

    cax, cay, cbx, cby = (at(x, node) for x in (e.ax, e.ay, e.bx, e.by))
    l1, go_left, go_right = classify(cax, cay, cbx - cax, cby - cay, e.ax, e.ay, e.bx, e.by)
    other = waiting & ~chosen & ~chain
    straddle = other & ~go_left & ~go_right
    new_slot = state.used[None] + jnp.cumsum(straddle, axis=0, dtype=jnp.int32) - 1
    split = straddle & (new_slot < n_slots)
    left = go_left | (straddle & (l1 > 0.0))  # the side of edge j (of its first piece, if split)
    # where j crosses the node's line: t = det(c_b - c_a, j_a - c_a) / det(c_b - c_a, j_a - j_b)
    ex, ey = cbx - cax, cby - cay
    den = _det(ex, ey, e.ax - e.bx, e.ay - e.by)
    t = _det(ex, ey, e.ax - cax, e.ay - cay) / jnp.where(den == 0.0, 1.0, den)
    sx, sy = e.ax + t * (e.bx - e.ax), e.ay + t * (e.by - e.ay)

    child = 2 * node + 1  # the left child list of node c is 2c + 1, the right one 2c + 2
    new_lst = jnp.where(chosen | chain | ~waiting, -1, child + (~left).astype(jnp.int32))

    def insert_pieces(_):
        """The new pieces (s -> old b) in their slots, each edge j split shortened to (a -> s).  Scatters: on a
        CPU in a conditional, since most levels split nothing (elsewhere a conditional waits for its
        predicate to reach the host, and scatters are cheap)."""
        tgt = jnp.where(split, new_slot, n_slots)  # out of range: dropped

        def put(x, v):
            return x.at[tgt, cols].set(v, mode="drop")

        true = jnp.ones_like(split)
        edges = _Edges(
            ax=put(e.ax, sx),
            ay=put(e.ay, sy),
            bx=put(jnp.where(split, sx, e.bx), e.bx),
            by=put(jnp.where(split, sy, e.by), e.by),
            conv_a=put(e.conv_a, true),
            conv_b=put(e.conv_b | split, e.conv_b),
            dpx=put(e.dpx, e.dx),
            dpy=put(e.dpy, e.dy),
            dx=put(e.dx, e.dx),
            dy=put(e.dy, e.dy),
            dnx=put(jnp.where(split, e.dx, e.dnx), e.dnx),
            dny=put(jnp.where(split, e.dy, e.dny), e.dny),
            nxt=put(jnp.where(split, new_slot, e.nxt), e.nxt),
            alive=put(e.alive, true),
        )
        # this level's facts per slot, the new pieces included (they wait on the other side of j's node);
        # the new piece inherits j's pair (with j's old next edge), and j's pair is now (j, new piece)
        return (
            edges,
            put(key, key),
            put(new_lst, child + left.astype(jnp.int32)),
            put(chosen, ~true),
            put(chain, ~true),
            put(left, ~left),
            put(node, node),
            put(state.pair_open | split, state.pair_open),
            put(state.pair_node, state.pair_node),
            put(state.pair_flag, state.pair_flag),
        )

    unsplit = (e, key, new_lst, chosen, chain, left, node, state.pair_open, state.pair_node, state.pair_flag)
    if jax.default_backend() == "cpu":
        inserted = lax.cond(jnp.any(split), insert_pieces, lambda _: unsplit, None)
    else:
        inserted = insert_pieces(None)
    edges, key, lst, chosen, chain, left, node, pair_open, pair_node, pair_flag = inserted
    # an open pair (e, f) waited in one list; it is decided where its list's node is e or f, or where they
    # part: e first iff, at the deciding node, e is on the side that the query visits first
    # (in a chain, the earlier edge is the node and the other lies in its left subtree)
    f = edges.nxt
    chosen_f, left_f, f_first = at(chosen, f), at(left, f), at(key, f) < key
    decide_e = pair_open & (chosen | (chain & ~f_first))
    decide_f = pair_open & ~decide_e & (chosen_f | chain)
    part = pair_open & ~decide_e & ~decide_f & (left != left_f)
    pair_node = jnp.where(decide_e, slot, jnp.where(decide_f, f, jnp.where(part, node, pair_node)))
    pair_flag = jnp.where(
        decide_e, ~left_f & ~chain, jnp.where(decide_f, left | chain, jnp.where(part, left, pair_flag))
    )
    pair_open = pair_open & ~(decide_e | decide_f | part)
    used = state.used + jnp.sum(split, axis=0, dtype=jnp.int32)
    return _TreeState(edges, key, lst, used, pair_open, pair_node, pair_flag)


def _obstacle_table(vx, vy, nv, capacity) -> _ObstacleTable:
    """RVO2's addObstacle for every polygon, then processObstacles (the kd-tree, its splits, and the order in
    which the tree query visits adjacent edges).  vx, vy (M, V, B), nv (M, B)."""
    edges = _polygon_edges(vx, vy, nv, capacity)
    n_slots, b = edges.ax.shape
    slot = jnp.broadcast_to(jnp.arange(n_slots, dtype=jnp.int32)[:, None], (n_slots, b))
    state = _TreeState(
        edges,
        slot,
        jnp.where(edges.alive, 0, -1),
        jnp.full((b,), vx.shape[0] * vx.shape[1], jnp.int32),
        edges.alive,
        slot,
        jnp.zeros((n_slots, b), bool),
    )
    state = lax.while_loop(lambda s: jnp.any(s.lst >= 0), _tree_level, state)
    e = state.edges

    def at(x, j):
        return jnp.take_along_axis(x, j, axis=0)

    node = state.pair_node
    tie = (at(e.ax, node), at(e.ay, node), at(e.bx, node), at(e.by, node), state.pair_flag)
    cols = jnp.broadcast_to(jnp.arange(b, dtype=jnp.int32)[None, :], (n_slots, b))
    prv = slot.at[jnp.where(e.alive, e.nxt, n_slots), cols].set(slot, mode="drop")
    return _ObstacleTable(e, prv, *tie, *(at(x, prv) for x in tie))


ObstacleTable = _ObstacleTable  # the public name of a processed obstacle set (see process_obstacles)
_TABLE_LEAVES = len(
    jax.tree.leaves(_ObstacleTable(_Edges(*(0,) * len(_Edges._fields)), *(0,) * (len(_ObstacleTable._fields) - 1)))
)


def _process_scenes(vertices, num_vertices):
    """vertices (B, M, V, 2), num_vertices (B, M) -> the tables' leaves, each (B, E)."""
    vertices = vertices.astype(jnp.float32)
    table = _obstacle_table(
        vertices[..., 0].transpose(1, 2, 0),
        vertices[..., 1].transpose(1, 2, 0),
        num_vertices.astype(jnp.int32).T,
        _edge_capacity(vertices.shape[1] * vertices.shape[2]),
    )
    return tuple(x.T for x in jax.tree.leaves(table))


@jax.custom_batching.custom_vmap
def _process_batch(vertices, num_vertices):
    return _process_scenes(vertices, num_vertices)


@_process_batch.def_vmap
def _process_batch_rule(axis_size, in_batched, vertices, num_vertices):
    args = [
        x if bt else jnp.broadcast_to(x, (axis_size,) + x.shape) for x, bt in zip((vertices, num_vertices), in_batched)
    ]
    inner = args[0].shape[1]
    out = _process_batch(*(x.reshape((axis_size * inner,) + x.shape[2:]) for x in args))
    return tuple(x.reshape((axis_size, inner) + x.shape[1:]) for x in out), (True,) * len(out)


@jax.custom_batching.custom_vmap
def _process_scene(vertices, num_vertices):
    return tuple(x[0] for x in _process_scenes(vertices[None], num_vertices[None]))


@_process_scene.def_vmap
def _process_scene_rule(axis_size, in_batched, vertices, num_vertices):
    args = [
        x if bt else jnp.broadcast_to(x, (axis_size,) + x.shape) for x, bt in zip((vertices, num_vertices), in_batched)
    ]
    out = _process_batch(*args)
    return out, (True,) * len(out)


def process_obstacles(vertices, num_vertices) -> ObstacleTable:
    """RVO2's ``processObstacles`` for one scene's obstacles (vertices (M, V, 2), num_vertices (M,), as
    :func:`solve` takes them): the kd-tree's split edges and the tree query's tie order, every field (E,) with
    E = :func:`_edge_capacity` (M * V).  :func:`solve` takes the result in place of the (vertices,
    num_vertices) tuple, with the same results; obstacles that stay put for many solves (an episode) are so
    processed once instead of in every solve.  Jittable and vmappable (one batched kernel under ``jax.vmap``);
    M * V must be > 0."""
    vertices = jnp.asarray(vertices, jnp.float32)
    num_vertices = jnp.asarray(num_vertices, jnp.int32)
    if vertices.ndim != 3 or vertices.shape[2] != 2 or num_vertices.shape != vertices.shape[:1]:
        raise ValueError(
            f"obstacles: vertices {vertices.shape} must be (M, V, 2) and num_vertices {num_vertices.shape} (M,)"
        )
    if vertices.shape[0] * vertices.shape[1] == 0:
        raise ValueError("process_obstacles needs at least one vertex slot (M * V > 0)")
    return _table_from_leaves(_process_scene(vertices, num_vertices))


def _table_from_leaves(leaves) -> ObstacleTable:
    edges = _Edges(*leaves[: len(_Edges._fields)])
    return _ObstacleTable(edges, *leaves[len(_Edges._fields) :])


# -- per agent (problem p = agent * B + scene): obstacle neighbours and their ORCA lines


def _edge_dist_sq(ax, ay, bx, by, px, py):
    """RVO2 distSqPointLineSegment(a, b, p) (a zero-length edge: the distance to a)."""
    ex, ey = bx - ax, by - ay
    len_sq = ex * ex + ey * ey
    r = ((px - ax) * ex + (py - ay) * ey) / jnp.where(len_sq == 0.0, 1.0, len_sq)
    qx, qy = px - (ax + r * ex), py - (ay + r * ey)
    return jnp.where(r < 0.0, _sq(px - ax, py - ay), jnp.where(r > 1.0, _sq(px - bx, py - by), _sq(qx, qy)))


def _sq(x, y):
    return x * x + y * y


def _neighbour_key(ax, ay, bx, by, alive, px, py, range_sq):
    """An edge's squared distance where it is one of the agent's obstacle neighbours, else _BIG: RVO2's tree
    query inserts the edges seen from their right side (leftOf < 0) whose distance is below range_sq.  (The
    query also prunes subtrees whose split line is out of range, which can only drop edges that are out of
    range up to the split tolerance.)"""
    d = _edge_dist_sq(ax, ay, bx, by, px, py)
    ok = alive & (_left_of(ax, ay, bx, by, px, py) < 0.0) & (d < range_sq)
    return jnp.where(ok, d, _BIG)


def _tie_order(
    key, nxt, prv, tie_ax, tie_ay, tie_bx, tie_by, tie_flag, tie_pax, tie_pay, tie_pbx, tie_pby, tie_pflag, px, py
):
    """Each edge's tie-breaker among neighbours at the same distance (``key``'s shape, edges first): the tree
    query's order for two adjacent edges whose distances tie (the shared vertex is the nearest point of both),
    else the slot: 2 * slot, or 2 * min(slot of e, slot of its partner) + (0 for the one visited first, 1 for
    the other).  (An edge tied with both its neighbours, possible only where it has no length, takes its
    next one's order.)"""
    idx = jnp.arange(key.shape[0], dtype=jnp.int32).reshape((-1,) + (1,) * (key.ndim - 1))
    nxt, prv = jnp.broadcast_to(nxt, key.shape), jnp.broadcast_to(prv, key.shape)

    def at(x, j):
        return jnp.take_along_axis(x, j, axis=0)

    first = (_left_of(tie_ax, tie_ay, tie_bx, tie_by, px, py) >= 0.0) == tie_flag  # e before its next edge
    first_p = (_left_of(tie_pax, tie_pay, tie_pbx, tie_pby, px, py) >= 0.0) == tie_pflag  # previous edge first
    tie_n = (key < _BIG) & (at(key, nxt) == key) & (nxt != idx)
    tie_p = (key < _BIG) & (at(key, prv) == key) & (prv != idx) & ~tie_n
    return jnp.where(
        tie_n,
        2 * jnp.minimum(idx, nxt) + (~first).astype(jnp.int32),
        jnp.where(tie_p, 2 * jnp.minimum(idx, prv) + first_p.astype(jnp.int32), 2 * idx),
    )


def _obstacle_neighbours(t: _ObstacleTable, px, py, range_sq):
    """Agent::computeNeighbors' obstacle part: (key, tie), the neighbours in ascending (key, tie), key = _BIG
    for the edges that are none; edges on the first axis, t's fields broadcast against px, py, range_sq.

    Neighbours (:func:`_neighbour_key`) come in ascending distance; equal distances in the tree query's order
    for edges that share a vertex (:class:`_ObstacleTable`; their distances tie exactly wherever that vertex
    is the nearest point of both), otherwise (a coincidence) by slot.
    """
    e = t.edges
    key = _computed_once(_neighbour_key, e.ax, e.ay, e.bx, e.by, e.alive, px, py, range_sq)
    return key, _computed_once(_tie_order, key, e.nxt, *t[1:], px, py)


def _tangent_legs(rx, ry, dist_sq, radius):
    """The left and right tangent directions from the agent to the disk of ``radius`` around a vertex at
    relative position r (RVO2: Vector2(...) / distSq, i.e. times 1 / distSq)."""
    leg = _safe_sqrt(dist_sq - radius * radius)
    inv = _safe_inv(dist_sq)
    left = ((rx * leg - ry * radius) * inv, (rx * radius + ry * leg) * inv)
    right = ((rx * leg + ry * radius) * inv, (-rx * radius + ry * leg) * inv)
    return left, right


def _obstacle_line(ax, ay, bx, by, conv_a, conv_b, dpx, dpy, dx, dy, dnx, dny, px, py, vx, vy, radius, inv_th):
    """The ORCA line of Agent::computeNewVelocity for one obstacle neighbour (edge a -> b), every case of
    RVO2 but the 'already covered' test (which needs the lines before it, :func:`_obstacle_lines`).

    p, v: the agent's position and velocity; inv_th = 1 / timeHorizonObst.  Returns (point_x, point_y,
    dir_x, dir_y, made), made False where RVO2 adds no line for this edge.  Elementwise.
    """
    r1x, r1y = ax - px, ay - py
    r2x, r2y = bx - px, by - py
    dist1, dist2 = _sq(r1x, r1y), _sq(r2x, r2y)
    rad_sq = radius * radius
    ox, oy = bx - ax, by - ay
    o_sq = _sq(ox, oy)
    s = (-r1x * ox + -r1y * oy) / jnp.where(o_sq == 0.0, 1.0, o_sq)
    dist_line = _sq(-r1x - s * ox, -r1y - s * oy)

    # -- collision with the left vertex, the right vertex or the segment: a line through the origin
    col_left = (s < 0.0) & (dist1 <= rad_sq)
    col_right = ~col_left & (s > 1.0) & (dist2 <= rad_sq)
    col_seg = ~col_left & ~col_right & (s >= 0.0) & (s < 1.0) & (dist_line <= rad_sq)
    collide = col_left | col_right | col_seg
    # ignored at a non-convex vertex, and at the right vertex where the next edge takes care of it
    col_made = jnp.where(col_left, conv_a, jnp.where(col_right, conv_b & (_det(r2x, r2y, dnx, dny) >= 0.0), True))
    cdx, cdy = _normalized(jnp.where(col_left, -r1y, -r2y), jnp.where(col_left, r1x, r2x))
    col_dx, col_dy = jnp.where(col_seg, -dx, cdx), jnp.where(col_seg, -dy, cdy)

    # -- no collision: legs; viewed obliquely, both legs come from one vertex (obstacle1 = obstacle2)
    obl_left = (s < 0.0) & (dist_line <= rad_sq)
    obl_right = ~obl_left & (s > 1.0) & (dist_line <= rad_sq)
    same = obl_left | obl_right
    ignored = (obl_left & ~conv_a) | (obl_right & ~conv_b)
    o1x, o1y = jnp.where(obl_right, bx, ax), jnp.where(obl_right, by, ay)  # obstacle1 after RVO2's reassignment
    o2x, o2y = jnp.where(obl_left, ax, bx), jnp.where(obl_left, ay, by)  # obstacle2
    o1_conv = jnp.where(obl_right, conv_b, conv_a)
    o2_conv = jnp.where(obl_left, conv_a, conv_b)
    o2dx, o2dy = jnp.where(obl_left, dx, dnx), jnp.where(obl_left, dy, dny)  # obstacle2->unitDir_
    nbx, nby = jnp.where(obl_right, dx, dpx), jnp.where(obl_right, dy, dpy)  # obstacle1->prevObstacle_->unitDir_
    (llx, lly), _ = _tangent_legs(
        jnp.where(obl_right, r2x, r1x), jnp.where(obl_right, r2y, r1y), jnp.where(obl_right, dist2, dist1), radius
    )
    _, (rlx, rly) = _tangent_legs(
        jnp.where(obl_left, r1x, r2x), jnp.where(obl_left, r1y, r2y), jnp.where(obl_left, dist1, dist2), radius
    )
    # a non-convex vertex (usual view only: obliquely it is ignored) extends the cut-off line
    llx, lly = jnp.where(~same & ~conv_a, -dx, llx), jnp.where(~same & ~conv_a, -dy, lly)
    rlx, rly = jnp.where(~same & ~conv_b, dx, rlx), jnp.where(~same & ~conv_b, dy, rly)
    # legs never point into the neighbouring edge at a convex vertex: take its direction ("foreign" leg)
    foreign_left = o1_conv & (_det(llx, lly, -nbx, -nby) >= 0.0)
    llx, lly = jnp.where(foreign_left, -nbx, llx), jnp.where(foreign_left, -nby, lly)
    foreign_right = o2_conv & (_det(rlx, rly, o2dx, o2dy) <= 0.0)
    rlx, rly = jnp.where(foreign_right, o2dx, rlx), jnp.where(foreign_right, o2dy, rly)

    # -- project the velocity on the velocity obstacle: cut-off circles, cut-off line or legs
    lcx, lcy = inv_th * (o1x - px), inv_th * (o1y - py)
    rcx, rcy = inv_th * (o2x - px), inv_th * (o2y - py)
    cvx, cvy = rcx - lcx, rcy - lcy
    cv_sq = _sq(cvx, cvy)
    t = jnp.where(same, 0.5, ((vx - lcx) * cvx + (vy - lcy) * cvy) / jnp.where(cv_sq == 0.0, 1.0, cv_sq))
    t_left = (vx - lcx) * llx + (vy - lcy) * lly
    t_right = (vx - rcx) * rlx + (vy - rcy) * rly
    on_left = ((t < 0.0) & (t_left < 0.0)) | (same & (t_left < 0.0) & (t_right < 0.0))
    on_right = ~on_left & (t > 1.0) & (t_right < 0.0)
    ccx, ccy = jnp.where(on_left, lcx, rcx), jnp.where(on_left, lcy, rcy)
    ux, uy = _normalized(vx - ccx, vy - ccy)
    cut_r = radius * inv_th

    inf = jnp.float32(jnp.inf)
    d_cut = jnp.where((t < 0.0) | (t > 1.0) | same, inf, _sq(vx - (lcx + t * cvx), vy - (lcy + t * cvy)))
    d_left = jnp.where(t_left < 0.0, inf, _sq(vx - (lcx + t_left * llx), vy - (lcy + t_left * lly)))
    d_right = jnp.where(t_right < 0.0, inf, _sq(vx - (rcx + t_right * rlx), vy - (rcy + t_right * rly)))
    use_cut = (d_cut <= d_left) & (d_cut <= d_right)
    use_left = ~use_cut & (d_left <= d_right)
    use_right = ~use_cut & ~use_left
    ldx = jnp.where(use_cut, -dx, jnp.where(use_left, llx, -rlx))  # cut-off line: -obstacle1->unitDir_
    ldy = jnp.where(use_cut, -dy, jnp.where(use_left, lly, -rly))
    lpx = jnp.where(use_right, rcx, lcx) + cut_r * -ldy
    lpy = jnp.where(use_right, rcy, lcy) + cut_r * ldx
    leg_made = ~(use_left & foreign_left) & ~(use_right & foreign_right)

    circle = on_left | on_right
    zero = jnp.zeros_like(px)
    point_x = jnp.where(collide, zero, jnp.where(circle, ccx + cut_r * ux, lpx))
    point_y = jnp.where(collide, zero, jnp.where(circle, ccy + cut_r * uy, lpy))
    dir_x = jnp.where(collide, col_dx, jnp.where(circle, uy, ldx))
    dir_y = jnp.where(collide, col_dy, jnp.where(circle, -ux, ldy))
    made = jnp.where(collide, col_made, ~ignored & (circle | leg_made))
    return point_x, point_y, dir_x, dir_y, made


def _line_point_or_inf(*args):
    """:func:`_obstacle_line`'s point, x = inf where it makes no line."""
    px, py, _, _, made = _obstacle_line(*args)
    return jnp.where(made, px, jnp.inf), py


def _obstacle_lines(t: _ObstacleTable, px, py, vx, vy, radius, max_speed, inv_th, th_obst):
    """The obstacle ORCA lines of every problem (agent, scene), in RVO2's order: 4 (E, N * B) tables whose
    first ``count`` (N * B,) rows hold them (problem p = agent * B + scene).  t's fields are (E, B) (each
    scene's edges, broadcast to its agents inside the loops, never materialised per agent), the rest (N, B);
    inv_th = 1 / timeHorizonObst.

    RVO2 walks the neighbours in order and skips those 'already covered' (both vertices, scaled by inv_th,
    at least the radius behind a line built before).  Lines only accumulate, so an edge once covered stays
    covered: each round takes every problem's first neighbour neither covered nor done, computes its line
    (:func:`_obstacle_line`) and, if RVO2 makes one, keeps it and marks every edge it covers.  So the rounds
    follow the uncovered neighbours (a few), not all of them, and no edge slot's line is computed in vain.

    Most agents are done after two or three rounds while a few near many edges need up to ten, so the rounds
    run over all problems only while more than a quarter of them still find a neighbour; the rest are then
    gathered into chunks that run their own rounds to the end.
    """
    e = t.edges
    n_slots, n, b = e.ax.shape[0], px.shape[0], px.shape[1]
    n_prob = n * b
    per_agent = jax.tree.map(lambda x: x[:, None, :], t)  # (E, 1, B)
    reach = th_obst * max_speed + radius
    key, tie = _obstacle_neighbours(per_agent, px[None], py[None], (reach * reach)[None])
    margin = inv_th * radius  # invTimeHorizonObst * radius_

    def next_slot(key, tie, done):
        """The slot of the least (key, tie) among the neighbours not done (n_slots: none).  One loop."""
        best_key = jnp.full(key.shape[1:], _BIG, jnp.float32)
        best_tie = jnp.zeros(key.shape[1:], jnp.int32)
        s = jnp.full(key.shape[1:], n_slots, jnp.int32)
        for j in range(n_slots):
            kj, tj = key[j], tie[j]
            better = ~done[j] & ((kj < best_key) | ((kj == best_key) & (tj < best_tie)))
            best_key, best_tie, s = (
                jnp.where(better, kj, best_key),
                jnp.where(better, tj, best_tie),
                jnp.where(better, j, s),
            )
        return s

    def covers(done, ax, ay, bx, by, px, py, inv_th, margin, keep, lx, ly, ldx, ldy):
        """done | the edges that the new line (where kept) covers.  One loop."""
        c1x, c1y, c2x, c2y = inv_th * (ax - px), inv_th * (ay - py), inv_th * (bx - px), inv_th * (by - py)
        return done | (
            keep
            & (_det(c1x - lx, c1y - ly, ldx, ldy) - margin >= -RVO_EPSILON)
            & (_det(c2x - lx, c2y - ly, ldx, ldy) - margin >= -RVO_EPSILON)
        )

    def round_of(key, tie, corners, scene, agent):
        """One round for problems of some shape S (the whole (N, B) batch, or a (C,) chunk): key, tie (E,) + S;
        corners: the 4 edge end-point tables, (E,) + S or broadcastable; scene: S, the problems' scenes;
        agent = (px, py, vx, vy, radius, inv_th, margin), each S.  The lines are (E, prod S), problems flat."""
        shape = scene.shape
        size = scene.size
        cols = jnp.arange(size, dtype=jnp.int32)
        flat = lambda x: x.reshape(size)  # noqa: E731
        apx, apy, avx, avy, arad, ainv, amargin = agent

        def step(state):
            lines, count, done, _ = state
            s = _computed_once(next_slot, key, tie, done)
            found = s < n_slots
            index = jnp.minimum(s, n_slots - 1) * b + scene
            edge = [jnp.take(x.reshape(-1), index) for x in e[:12]]  # gathers from the scene's edges
            args = (*edge, apx, apy, avx, avy, arad, ainv)
            # two loops of the line's chain (a pair each); no line: point x = inf, so no third loop for the flag
            qx, qy = _computed_once(_line_point_or_inf, *args)
            qdx, qdy = _computed_once(lambda *a: _obstacle_line(*a)[2:4], *args)
            keep = found & (qx < jnp.inf)
            row = jnp.where(keep, count, n_slots)  # out of range: dropped
            lines = tuple(x.at[flat(row), cols].set(flat(v), mode="drop") for x, v in zip(lines, (qx, qy, qdx, qdy)))
            slot = jnp.arange(n_slots, dtype=jnp.int32).reshape((n_slots,) + (1,) * len(shape))
            kept = tuple(jnp.where(keep, v, 0.0)[None] for v in (qx, qy, qdx, qdy))  # no inf in the test below
            done = _computed_once(
                covers,
                done | (slot == s[None]),
                *corners,
                apx[None],
                apy[None],
                ainv[None],
                amargin[None],
                keep[None],
                *kept,
            )
            return lines, count + keep.astype(jnp.int32), done, jnp.sum(found, dtype=jnp.int32)

        return step

    # all problems together while many find a neighbour
    scene = jnp.broadcast_to(jnp.arange(b, dtype=jnp.int32)[None], (n, b))
    agent = (px, py, vx, vy, radius, inv_th, margin)
    dense = round_of(key, tie, per_agent.edges[:4], scene, agent)
    zeros = jnp.zeros((n_slots, n_prob), jnp.float32)
    state = ((zeros,) * 4, jnp.zeros((n, b), jnp.int32), key >= _BIG, jnp.int32(n_prob))
    lines, count, done, _ = lax.while_loop(lambda s: s[3] * 4 > n_prob, dense, state)

    # the rest in chunks of the problems with neighbours left
    to_p = lambda x: x.reshape(x.shape[:-2] + (n_prob,))  # noqa: E731  (..., N, B) -> (..., P)
    pending = jnp.any(~done, axis=0).reshape(n_prob)
    size = max(1, -(-n_prob // 8))
    n_chunks = -(-n_prob // size)
    order = jnp.nonzero(pending, size=n_chunks * size, fill_value=n_prob)[0].astype(jnp.int32)
    key_p, tie_p, done_p = to_p(key), to_p(tie), to_p(done)
    agent_p = tuple(to_p(x) for x in agent)
    scene_p = to_p(scene)

    def run_chunk(c, carry):
        lines, count = carry
        sel = lax.dynamic_slice_in_dim(order, c * size, size)
        rows = jnp.minimum(sel, n_prob - 1)
        sc = scene_p[rows]
        corners = tuple(jnp.take(x, sc, axis=1) for x in e[:4])  # (E, C): each problem's scene's edges
        step = round_of(_columns(key_p, rows), _columns(tie_p, rows), corners, sc, tuple(x[rows] for x in agent_p))
        part = (tuple(_columns(x, rows) for x in lines), count[rows], _columns(done_p, rows), jnp.int32(1))
        part_lines, part_count = lax.while_loop(lambda s: s[3] > 0, step, part)[:2]
        lines = tuple(x.at[:, sel].set(v, mode="drop") for x, v in zip(lines, part_lines))  # padding dropped
        return lines, count.at[sel].set(part_count, mode="drop")

    n_pending = jnp.sum(pending, dtype=jnp.int32)
    return lax.fori_loop(0, (n_pending + size - 1) // size, run_chunk, (lines, to_p(count)))


# -- the obstacle lines in the LPs
#
# RVO2 puts the obstacle lines first.  linearProgram1's interval on a line depends only on the lines before
# it, so an obstacle line's interval needs only the obstacle lines, and every later line's interval starts
# from what the obstacle lines allow.  So the obstacle lines never enter the (L, P) line tables, whose loops
# are unrolled over L: they are walked by small loops up to the largest obstacle line count (a few lines,
# however many edge slots there are): their intervals once, then linearProgram2's walk over them, then each
# agent line's interval from them (:func:`_obstacle_bounds`) to start its linearProgram1 with.


class _ObstacleLP(NamedTuple):
    """The obstacle lines of every problem: (K, P) tables whose first ``count`` (P,) rows hold them in
    RVO2's order, and linearProgram1's interval on each (from the velocity disk and the obstacle lines
    before it; ok: linearProgram1 succeeds).

    ``cols``: None, or the problems (C,) of a linearProgram3 chunk, whose ``count`` (C,) this then holds:
    the tables stay every problem's and each row is read for the chunk's problems only when a loop reaches
    it.  Gathering whole (K, C) tables instead, every round, would cost more than the rounds themselves (K is
    the edge capacity; the loops stop at the chunk's largest count, a few lines)."""

    px: jax.Array
    py: jax.Array
    dx: jax.Array
    dy: jax.Array
    count: jax.Array
    t_left: jax.Array
    t_right: jax.Array
    ok: jax.Array
    cols: jax.Array | None = None

    def line(self, i):
        """(px, py, dx, dy) of row i."""
        return self._read((self.px, self.py, self.dx, self.dy), i)

    def interval(self, i):
        """(t_left, t_right, ok) of row i."""
        return self._read((self.t_left, self.t_right, self.ok), i)

    def _read(self, tables, i):
        rows = _row(tables, i)
        return rows if self.cols is None else tuple(x[self.cols] for x in rows)


def _row(tables, i):
    return tuple(lax.dynamic_index_in_dim(x, i, 0, keepdims=False) for x in tables)


def _interval_update(bounds, pix, piy, dix, diy, pjx, pjy, djx, djy, use):
    """linearProgram1's step on line i for an earlier line j (where ``use``): bounds = (t_left, t_right,
    bad), bad where RVO2 returns false for a parallel line on the wrong side."""
    t_left, t_right, bad = bounds
    den = _det(dix, diy, djx, djy)
    num = _det(djx, djy, pix - pjx, piy - pjy)
    parallel = jnp.abs(den) <= RVO_EPSILON
    t = num / jnp.where(parallel, 1.0, den)
    t_right = jnp.where(use & ~parallel & (den >= 0.0), jnp.minimum(t_right, t), t_right)
    t_left = jnp.where(use & ~parallel & (den < 0.0), jnp.maximum(t_left, t), t_left)
    return t_left, t_right, bad | (use & parallel & (num < 0.0))


def _obstacle_lp(lines, count, radius) -> _ObstacleLP:
    """:class:`_ObstacleLP` of the obstacle lines (4 x (K, P), count (P,)); radius (P,): the disk."""

    def interval(i, tables):
        pix, piy, dix, diy = _row(lines, i)
        dot = pix * dix + piy * diy
        disc = dot * dot + radius * radius - (pix * pix + piy * piy)
        sq = _safe_sqrt(disc)
        t_left, t_right, bad = lax.fori_loop(
            0,
            i,
            lambda j, b: _interval_update(b, pix, piy, dix, diy, *_row(lines, j), True),
            (-dot - sq, -dot + sq, disc < 0.0),
        )
        return tuple(x.at[i].set(v) for x, v in zip(tables, (t_left, t_right, ~bad & (t_left <= t_right))))

    zeros = jnp.zeros(lines[0].shape, jnp.float32)
    tables = lax.fori_loop(0, jnp.max(count), interval, (zeros, zeros, jnp.zeros(zeros.shape, bool)))
    return _ObstacleLP(*lines, count, *tables)


def _obstacle_walk(obst: _ObstacleLP, radius, optx, opty, direction_opt):
    """linearProgram2 over the obstacle lines alone (they come first): the result after them (complex) and
    the row where linearProgram1 failed (count: none; the result then stays, as in RVO2)."""
    rx, ry = _lp2_start(radius, optx, opty, direction_opt)

    def step(i, state):
        rx, ry, fail = state
        (pix, piy, dix, diy), (t_left, t_right, ok) = obst.line(i), obst.interval(i)
        hit = (i < obst.count) & (fail == obst.count) & (_det(dix, diy, pix - rx, piy - ry) > 0.0)
        t = _lp1_optimum(optx, opty, pix, piy, dix, diy, t_left, t_right, direction_opt)
        take = hit & ok
        rx, ry = jnp.where(take, pix + t * dix, rx), jnp.where(take, piy + t * diy, ry)
        return rx, ry, jnp.where(hit & ~ok, i, fail)

    rx, ry, fail = lax.fori_loop(0, jnp.max(obst.count), step, (rx, ry, obst.count))
    return lax.complex(rx, ry), fail


def _obstacle_bounds(obst: _ObstacleLP, lines):
    """The interval (t_left, t_right, bad), each (L, P), that the obstacle lines leave on every line of
    ``lines`` (4 x (L, P)), for :func:`_lp1_bounds`."""
    px = lines[0]
    init = (
        jnp.full(px.shape, -jnp.inf, jnp.float32),
        jnp.full(px.shape, jnp.inf, jnp.float32),
        jnp.zeros(px.shape, bool),
    )

    def step(j, bounds):
        pj = (x[None] for x in obst.line(j))
        return _interval_update(bounds, *lines, *pj, (j < obst.count)[None])

    return lax.fori_loop(0, jnp.max(obst.count), step, init)


def _lp3_obstacle_part(obst: _ObstacleLP, radius, r, fail_o):
    """linearProgram3's loop over the obstacle lines where linearProgram2 failed on one (row fail_o < count):
    from that line on, each obstacle line penetrated deeper than the current worst is minimised subject to
    the obstacle lines (the projected lines are just those).  Returns the result and the worst penetration
    (0 elsewhere), from which the loop goes on over the agent lines."""

    def step(i, state):
        r, distance = state
        pix, piy, dix, diy = obst.line(i)
        hit = (i >= fail_o) & (i < obst.count) & (_det(dix, diy, pix - jnp.real(r), piy - jnp.imag(r)) > distance)
        s, fail = _obstacle_walk(obst, radius, -diy, dix, True)
        r = jnp.where(hit & (fail == obst.count), s, r)
        return r, jnp.where(hit, _det(dix, diy, pix - jnp.real(r), piy - jnp.imag(r)), distance)

    n_rounds = jnp.max(jnp.where(fail_o < obst.count, obst.count, 0))
    return lax.fori_loop(0, n_rounds, step, (r, jnp.zeros(r.shape, jnp.float32)))


# ---------------------------------------------------------------------------------------------------------
# the batched kernel


def _linear_program2(lines, rank, radius, optx, opty, block, start=None, bounds=()):
    """linearProgram2 for every problem (lines (L, P), rank (L, P), the rest (P,)): dense rounds over blocks of
    consecutive problems.  Returns the result as complex(x, y) and the rank of the line where it failed (L:
    none).  With obstacles, ``start`` = (result after the obstacle lines, go on) and ``bounds`` (their
    intervals on these lines, :func:`_obstacle_bounds`)."""
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


def _linear_program3(lines, rank, radius, r, fail_at, chunk, obst=None, fail_o=None):
    """linearProgram3 from the failing line (violated by the current result), only for the problems whose
    linearProgram2 failed (fail_at < L), as a worklist.  Returns the new result (complex).

    With obstacles (``obst``, :class:`_ObstacleLP`): where linearProgram2 failed on obstacle row fail_o (<
    count), the loop first runs over the obstacle lines from there (:func:`_lp3_obstacle_part`), then goes on
    with the agent lines penetrated deeper; the agent lines' projected lines come after the obstacle lines
    (:func:`_lp3_round`)."""
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


def _solve_scenes(pos, vel, rad, pref, vmax, mask, time_horizon, dt, neighbor_dist, *obstacles, k, block):
    """Batched core: pos/vel/pref (B, N, 2), rad/vmax/mask (B, N), scalars (B,); ``obstacles``: none, or
    vertices (B, M, V, 2), num_vertices (B, M) (or the leaves of their :class:`ObstacleTable`, each (B, E)) and
    time_horizon_obst (B,).  Returns (B, N, 2) and the
    per-agent LP2 failure flag (B, N)."""
    b, n = rad.shape
    f32 = jnp.float32
    pos, vel, pref = pos.astype(f32), vel.astype(f32), pref.astype(f32)
    a = b * n
    agent_major = lambda x: x.T.reshape(a)  # noqa: E731  (B, N) -> problem p = agent * B + scene
    scene_major = lambda x: x.reshape(n, b).T  # noqa: E731
    radius = agent_major(vmax.astype(f32))
    ox, oy = agent_major(pref[..., 0]), agent_major(pref[..., 1])
    if k == 0 and not obstacles:
        rx, ry = _lp2_start(radius, ox, oy, direction_opt=False)
        return jnp.stack([scene_major(rx), scene_major(ry)], -1), jnp.zeros((b, n), bool)

    if k > 0:
        inv_th = 1.0 / time_horizon.astype(f32)  # RVO2: invTimeHorizon = 1.0f / timeHorizon_
        inv_dt = 1.0 / dt.astype(f32)
        nd = neighbor_dist.astype(f32)
        out = _neighbour_lines(
            pos[..., 0].T,
            pos[..., 1].T,
            vel[..., 0].T,
            vel[..., 1].T,
            rad.astype(f32).T,
            mask.astype(bool).T,
            inv_th,
            inv_dt,
            nd * nd,
            k,
        )
        lines = tuple(x.reshape(n, a) for x in out[:4])
        rank = out[4].reshape(n, a)
    if not obstacles:
        r, fail_at = _linear_program2(lines, rank, radius, ox, oy, block)
        r = _linear_program3(lines, rank, radius, r, fail_at, block)
        rx, ry, failed = jnp.real(r), jnp.imag(r), fail_at < n
        return jnp.stack([scene_major(rx), scene_major(ry)], -1), scene_major(failed)

    # obstacles: their lines first (RVO2's orcaLines_ order), then the agent lines
    *obstacles, th_obst = obstacles
    if len(obstacles) == 2:  # (vertices (B, M, V, 2), num_vertices (B, M)): processed here
        obstacles = _process_scenes(*obstacles)
    table = _table_from_leaves(tuple(x.T for x in obstacles))  # processed (process_obstacles): (B, E) -> (E, B)
    th_obst = jnp.broadcast_to(th_obst.astype(f32)[None], (n, b))  # (agent, scene), as the edge walk takes them
    inv_th_obst = 1.0 / th_obst  # RVO2: invTimeHorizonObst = 1.0f / timeHorizonObst_
    obst_lines, n_obst = _obstacle_lines(
        table,
        pos[..., 0].T,
        pos[..., 1].T,
        vel[..., 0].T,
        vel[..., 1].T,
        rad.astype(f32).T,
        vmax.astype(f32).T,
        inv_th_obst,
        th_obst,
    )
    obst = _obstacle_lp(obst_lines, n_obst, radius)
    r, fail_o = _obstacle_walk(obst, radius, ox, oy, False)
    walked = fail_o == n_obst
    if k == 0:  # obstacle lines only
        r, _ = _lp3_obstacle_part(obst, radius, r, fail_o)
        return jnp.stack([scene_major(jnp.real(r)), scene_major(jnp.imag(r))], -1), scene_major(~walked)
    r, fail_at = _linear_program2(
        lines, rank, radius, ox, oy, block, start=(r, walked), bounds=_obstacle_bounds(obst, lines)
    )
    r = _linear_program3(lines, rank, radius, r, fail_at, block, obst, fail_o)
    rx, ry, failed = jnp.real(r), jnp.imag(r), ~walked | (fail_at < n)
    return jnp.stack([scene_major(rx), scene_major(ry)], -1), scene_major(failed)


@functools.cache
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
        return (
            out.reshape((axis_size, inner) + out.shape[1:]),
            failed.reshape((axis_size, inner) + failed.shape[1:]),
        ), (True, True)

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
def solve_with_info(
    positions,
    velocities,
    radii,
    pref_velocities,
    max_speeds,
    *,
    time_horizon,
    dt,
    neighbor_dist,
    max_neighbors,
    neighbor_mask=None,
    obstacles=None,
    time_horizon_obst=None,
    block=None,
):
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
    extra = ()
    if isinstance(obstacles, _ObstacleTable):  # processed by process_obstacles
        if time_horizon_obst is None:
            raise ValueError("obstacles need time_horizon_obst (RVO2's timeHorizonObst)")
        leaves = tuple(jnp.asarray(x) for x in jax.tree.leaves(obstacles))
        if len(leaves) != _TABLE_LEAVES or any(x.ndim != 1 or x.shape != leaves[0].shape for x in leaves):
            raise ValueError("obstacles: an ObstacleTable of one scene (every field (E,), from process_obstacles)")
        extra = leaves + (f32(time_horizon_obst),)
    elif obstacles is not None:
        vertices, num_vertices = obstacles
        vertices, num_vertices = f32(vertices), jnp.asarray(num_vertices, jnp.int32)
        if vertices.ndim != 3 or vertices.shape[2] != 2 or num_vertices.shape != vertices.shape[:1]:
            raise ValueError(
                f"obstacles: vertices {vertices.shape} must be (M, V, 2) and num_vertices {num_vertices.shape} (M,)"
            )
        if time_horizon_obst is None:
            raise ValueError("obstacles need time_horizon_obst (RVO2's timeHorizonObst)")
        if vertices.shape[0] * vertices.shape[1] > 0:  # no slots: the obstacle-free program
            extra = (vertices, num_vertices, f32(time_horizon_obst))
    return _kernels(k, block)(
        positions,
        f32(velocities),
        f32(radii),
        f32(pref_velocities),
        f32(max_speeds),
        mask,
        f32(time_horizon),
        f32(dt),
        f32(neighbor_dist),
        *extra,
    )


def solve(
    positions,
    velocities,
    radii,
    pref_velocities,
    max_speeds,
    *,
    time_horizon,
    dt,
    neighbor_dist,
    max_neighbors,
    neighbor_mask=None,
    obstacles=None,
    time_horizon_obst=None,
):
    """New velocities of all agents of one scene after one ORCA step, as RVO2's ``doStep`` sets them.

    Equivalent to an ``RVO::RVOSimulator`` holding these agents (and, if given, these obstacles, processed)
    calling ``Agent::computeNeighbors`` and ``Agent::computeNewVelocity`` for each; the position update is
    left to the caller.  Jittable and vmappable (``jax.vmap(solve)`` runs one batched kernel, see the module
    docstring).  float32 throughout.

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
      obstacles: None, or static obstacles shared by all agents: a tuple (vertices (M, V, 2) float,
        num_vertices (M,) int), polygon m being vertices[m, :num_vertices[m]], counter-clockwise as RVO2's
        ``addObstacle`` takes them (interior on the left of each edge; 2 vertices: a wall segment, both of
        its directed edges convex); slots with fewer than 2 vertices are unused.  Or the same obstacles
        processed once by :func:`process_obstacles` (an :class:`ObstacleTable`): the same results, without
        rebuilding RVO2's obstacle tree in every call.  Under ``jax.vmap`` each
        scene may have its own (or all share unbatched ones).  None, or M * V == 0: the obstacle-free
        program.  RVO2's kd-tree splits edges; here at most :func:`_edge_capacity` (M * V) - M * V of them
        (the env's layouts need far fewer), an edge beyond that staying whole.
      time_horizon_obst: ``timeHorizonObst_`` (required with obstacles): velocities are safe with respect to
        the obstacles for this long; it also sets each agent's obstacle range, ``time_horizon_obst *
        max_speed + radius``.  Python float or traced scalar.

    Returns:
      (N, 2) float32 new velocities (``newVelocity_``), each within its agent's max speed (up to rounding).
    """
    return solve_with_info(
        positions,
        velocities,
        radii,
        pref_velocities,
        max_speeds,
        time_horizon=time_horizon,
        dt=dt,
        neighbor_dist=neighbor_dist,
        max_neighbors=max_neighbors,
        neighbor_mask=neighbor_mask,
        obstacles=obstacles,
        time_horizon_obst=time_horizon_obst,
    )[0]
