"""The ORCA half-planes of every agent towards every other agent (Agent::computeNewVelocity's agent part), and
each line's rank in RVO2's distance-sorted neighbour list."""

from __future__ import annotations

import jax.numpy as jnp

from tgrf_jax.env.orca.numerics import _BIG, _componentwise, _det, _safe_inv, _safe_sqrt


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
