"""Each agent's obstacle neighbours (Agent::computeNeighbors' obstacle part, in the tree query's order) and
their ORCA lines (Agent::computeNewVelocity's obstacle part), for every problem p = agent * B + scene."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax

from tgrf_jax.env.orca.numerics import (
    _BIG,
    RVO_EPSILON,
    _columns,
    _computed_once,
    _det,
    _left_of,
    _normalized,
    _safe_inv,
    _safe_sqrt,
)
from tgrf_jax.env.orca.obstacle_tree import _ObstacleTable


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
    for edges that share a vertex (:class:`obstacle_tree._ObstacleTable`; their distances tie exactly wherever
    that vertex is the nearest point of both), otherwise (a coincidence) by slot.
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
        flat = lambda x: x.reshape(size)
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
    to_p = lambda x: x.reshape(x.shape[:-2] + (n_prob,))  # (..., N, B) -> (..., P)
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
