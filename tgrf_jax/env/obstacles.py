"""Static obstacles: polygon geometry, occlusion, a simulated 2-D LiDAR and the Social Force wall term.

An episode's obstacles are M polygon slots of up to V vertices (`Obstacles`), counter-clockwise like RVO2's
``addObstacle`` (the interior lies on the left of each edge); a polygon of 2 vertices is a wall segment with no
interior. Every function here is dense array code over all edges at once (E = M * V edge slots, the unused ones
masked), so that it vectorises under ``jax.vmap`` over many environments (the LiDAR loops over its edges and
discs, each pass over all rays with a running nearest hit). As in
`geometry`, x and y are handled as separate arrays because reductions over a trailing axis of size 2 vectorise
poorly on XLA:CPU. Degenerate input (points on an edge, zero-length edges or motions, parallel rays) gives
finite results: every division and square root is guarded.

Formulas (2-D cross product u x v = u_x v_y - u_y v_x):

* point-segment: t = clip((p - a).(b - a) / |b - a|^2, 0, 1), distance |p - (a + t (b - a))|.
* ray-segment: the ray o + t d (|d| = 1, t >= 0) meets the segment a + s e (e = b - a, 0 <= s <= 1) at
  t = ((a - o) x e) / (d x e), s = ((a - o) x d) / (d x e); parallel rays (d x e = 0) miss a wall of no
  thickness (a polygon's neighbouring edges still stop them).
* ray-circle: with m = c - o, b = d.m, q = |m|^2 - r^2 (> 0 outside) the ray enters the disc at the smaller
  root of t^2 - 2 b t + q = 0, t = b - sqrt(b^2 - q); it hits when b > 0 and b^2 >= q. (The cancellation-free
  q / (b + sqrt(b^2 - q)) costs a division per ray and disc and gains under 1e-6 m at 10 m in float32.)
* wall force (Helbing, Farkas & Vicsek, Nature 407, 2000, eq. 2's wall term without the body and friction
  forces): A exp((r_i - d_iW) / B) n_iW, with d_iW the distance from person i's centre to the nearest point
  of obstacle W and n_iW the unit vector from that point to the person.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
from flax import struct
from jax import lax

from tgrf_jax.fields import ConfigError
from tgrf_jax.polygons import check_polygons

# The exponent cap of `social_force.step`: tiny B or deep penetration give a huge, not an infinite, push.
_MAX_EXPONENT = 30.0
# Squared lengths and cross products below this count as zero in divisions (real edges are far longer).
_TINY = 1e-30


@struct.dataclass
class Obstacles:
    """Static obstacles of an episode: M polygon slots of up to V vertices, world frame.

    vertices     (M, V, 2) float32: counter-clockwise (interior on the left of each edge, as RVO2's
                 addObstacle); a polygon of 2 vertices is a wall segment (no interior).
    num_vertices (M,) int32: 0 = unused slot; vertices beyond a slot's count are ignored.
    """

    vertices: jnp.ndarray
    num_vertices: jnp.ndarray


def empty(num_slots=0, max_vertices=2) -> Obstacles:
    """Obstacles with `num_slots` unused slots (none at all by default)."""
    return Obstacles(
        vertices=jnp.zeros((num_slots, max_vertices, 2), jnp.float32),
        num_vertices=jnp.zeros((num_slots,), jnp.int32),
    )


# --------------------------------------------------------------------------------------------------
# Host side: validation and padding
# --------------------------------------------------------------------------------------------------


def from_polygons(polygons, num_slots=None, max_vertices=None, *, field: str = "obstacles") -> Obstacles:
    """Obstacles from a list of polygons (each a sequence of (x, y)), validated by `check_polygons` (errors name
    `field`) and padded to `num_slots` slots of `max_vertices` vertices (defaults: just enough, at least 2
    vertices). Padding is finite (zeros) and masked by `num_vertices`."""
    polys = check_polygons(polygons, field)
    longest = max((len(p) for p in polys), default=2)
    num_slots = len(polys) if num_slots is None else int(num_slots)
    max_vertices = max(longest, 2) if max_vertices is None else int(max_vertices)
    if len(polys) > num_slots:
        raise ConfigError(
            f"{field} has {len(polys)} polygons but only {num_slots} obstacle slots; allowed: at "
            f"most {num_slots} polygons"
        )
    if longest > max_vertices:
        raise ConfigError(f"{field} has a polygon of {longest} vertices; allowed: at most {max_vertices}")
    vertices = np.zeros((num_slots, max_vertices, 2), np.float32)
    counts = np.zeros((num_slots,), np.int32)
    for m, p in enumerate(polys):
        vertices[m, : len(p)] = p
        counts[m] = len(p)
    return Obstacles(vertices=jnp.asarray(vertices), num_vertices=jnp.asarray(counts))


# --------------------------------------------------------------------------------------------------
# Traced geometry
# --------------------------------------------------------------------------------------------------


def _slot_edges(obstacles: Obstacles):
    """Edge slots per polygon slot: start and end coordinates ax, ay, bx, by and valid, each (M, V).

    Edge i of slot m runs from vertex i to vertex (i + 1) % n_m. A wall (n = 2) has one edge: its closing
    edge would repeat it. Slots with fewer than 2 vertices have none.
    """
    v = obstacles.vertices
    num_v = v.shape[1]
    n = jnp.minimum(obstacles.num_vertices.astype(jnp.int32), num_v)[:, None]
    i = jnp.arange(num_v, dtype=jnp.int32)[None, :]
    # The end vertex is the next one, or the first for the closing edge: a static shift, not a gather.
    nxt = jnp.concatenate([v[:, 1:], v[:, :1]], axis=1)
    end = jnp.where((i + 1 < n)[..., None], nxt, v[:, :1])
    num_edges = jnp.where(n >= 3, n, jnp.where(n == 2, 1, 0))
    return v[..., 0], v[..., 1], end[..., 0], end[..., 1], i < num_edges


def edges(obstacles: Obstacles):
    """All edge slots: start (E, 2), end (E, 2), valid (E,) bool, with E = M * V (slot-major).

    Edge i of slot m runs from vertex i to vertex (i + 1) % n_m; a wall (2 vertices) has one edge; unused
    slots and vertices give valid = False.
    """
    ax, ay, bx, by, valid = _slot_edges(obstacles)
    start = jnp.stack([ax, ay], -1).reshape(-1, 2)
    end = jnp.stack([bx, by], -1).reshape(-1, 2)
    return start, end, valid.reshape(-1)


def _flat_edges(obstacles: Obstacles):
    ax, ay, bx, by, valid = _slot_edges(obstacles)
    return ax.reshape(-1), ay.reshape(-1), bx.reshape(-1), by.reshape(-1), valid.reshape(-1)


def _closest_on_segment(px, py, ax, ay, bx, by):
    """Closest point (cx, cy) of segments a-b to points p, and its squared distance (broadcast shapes)."""
    ex, ey = bx - ax, by - ay
    len2 = ex * ex + ey * ey
    # A zero-length edge has a zero numerator too: t = 0, its start point.
    t = jnp.clip(((px - ax) * ex + (py - ay) * ey) / jnp.maximum(len2, _TINY), 0.0, 1.0)
    cx, cy = ax + t * ex, ay + t * ey
    dx, dy = px - cx, py - cy
    return cx, cy, dx * dx + dy * dy


def _cross(ux, uy, vx, vy):
    return ux * vy - uy * vx


def _segments_cross(px, py, qx, qy, ax, ay, bx, by):
    """Whether segments p-q and a-b intersect (touching included; collinear pairs are left to the caller)."""
    s1 = jnp.sign(_cross(bx - ax, by - ay, px - ax, py - ay))
    s2 = jnp.sign(_cross(bx - ax, by - ay, qx - ax, qy - ay))
    s3 = jnp.sign(_cross(qx - px, qy - py, ax - px, ay - py))
    s4 = jnp.sign(_cross(qx - px, qy - py, bx - px, by - py))
    # With p and q both on the edge's line (collinear, or a zero-length edge) the sign tests say nothing.
    return (s1 * s2 <= 0) & (s3 * s4 <= 0) & ~((s1 == 0) & (s2 == 0))


# The point-against-edge queries below loop over the edges (`lax.fori_loop`), each iteration one fused,
# vectorised pass over the points with a running result: a (..., E) table reduced over its small minor axis
# vectorises poorly on XLA:CPU (under vmap especially), and a loop unrolled in Python costs minutes of compilation
# in a program that asks many such queries, for no faster code.


def _loop(count: int, body, init):
    """`lax.fori_loop(0, count, body, init)`, or `init` when there is nothing to loop over (no edge slots, no
    discs: the body could not even be traced)."""
    return init if count == 0 else lax.fori_loop(0, count, body, init)


def _inside_slots(px, py, obstacles: Obstacles):
    """Whether points (...) lie inside each polygon slot (..., M), by the crossing number of a ray towards +x."""
    ax, ay, bx, by, valid = _slot_edges(obstacles)
    slots = []
    for m in range(ax.shape[0]):

        def crossing(i, odd, m=m):
            straddle = (ay[m, i] > py) != (by[m, i] > py)
            # The crossing lies right of p: compared by multiplying out the division, by the sign of dy.
            side = _cross(bx[m, i] - ax[m, i], by[m, i] - ay[m, i], px - ax[m, i], py - ay[m, i])
            return odd ^ (straddle & valid[m, i] & jnp.where(by[m, i] > ay[m, i], side > 0, side < 0))

        odd = _loop(ax.shape[1], crossing, jnp.zeros(jnp.shape(px), bool))
        slots.append(odd & (obstacles.num_vertices[m] >= 3))
    if not slots:
        return jnp.zeros(jnp.shape(px) + (0,), bool)
    return jnp.stack(slots, axis=-1)


def _sq_distance(px, py, obstacles: Obstacles):
    ax, ay, bx, by, valid = _flat_edges(obstacles)

    def nearer(e, best):
        sq = _closest_on_segment(px, py, ax[e], ay[e], bx[e], by[e])[2]
        return jnp.where(valid[e], jnp.minimum(best, sq), best)

    return _loop(ax.shape[0], nearer, jnp.full(jnp.shape(px), jnp.inf, jnp.float32))


def distance_to_obstacles(points, obstacles: Obstacles):
    """Smallest distance (...,) from points (..., 2) to any obstacle edge (inf when there is none)."""
    return jnp.sqrt(_sq_distance(points[..., 0], points[..., 1], obstacles))


def inside(points, obstacles: Obstacles):
    """Whether points (..., 2) lie inside any polygon of 3+ vertices (...,) bool (walls have no inside)."""
    return jnp.any(_inside_slots(points[..., 0], points[..., 1], obstacles), axis=-1)


def clearance(points, obstacles: Obstacles):
    """Distance (...,) from points (..., 2) to the nearest edge, negative inside a polygon (inf without
    obstacles)."""
    d = distance_to_obstacles(points, obstacles)
    return jnp.where(inside(points, obstacles), -d, d)


def swept_distance(p0, p1, obstacles: Obstacles):
    """Smallest distance (...,) between the segments p0 -> p1 (..., 2) and any obstacle edge; 0 where they
    cross, inf without obstacles.

    For collision checks of a disc moving from p0 to p1 in one step: a fast robot cannot tunnel through a thin
    wall between two clear positions. Non-crossing segments are nearest at an endpoint of one of them.
    """
    edges = _flat_edges(obstacles)
    px, py, qx, qy = p0[..., 0], p0[..., 1], p1[..., 0], p1[..., 1]

    def nearer(e, best):
        ax, ay, bx, by, valid = (x[e] for x in edges)
        sq = jnp.minimum(
            jnp.minimum(_closest_on_segment(px, py, ax, ay, bx, by)[2], _closest_on_segment(qx, qy, ax, ay, bx, by)[2]),
            jnp.minimum(_closest_on_segment(ax, ay, px, py, qx, qy)[2], _closest_on_segment(bx, by, px, py, qx, qy)[2]),
        )
        sq = jnp.where(_segments_cross(px, py, qx, qy, ax, ay, bx, by), 0.0, sq)
        return jnp.where(valid, jnp.minimum(best, sq), best)

    return jnp.sqrt(_loop(edges[0].shape[0], nearer, jnp.full(px.shape, jnp.inf, jnp.float32)))


def line_of_sight(origin, targets, obstacles: Obstacles):
    """Whether the segment origin (2,) -> target crosses no obstacle edge, for targets (..., 2) -> (...,) bool.

    Occlusion: a human behind a wall is not seen. Touching an edge counts as crossing it (a sight line through
    a corner exactly is blocked); a sight line running along an edge is blocked by the edges next to it only.
    """
    ox, oy = origin[0], origin[1]
    tx, ty = targets[..., 0], targets[..., 1]
    edges = _flat_edges(obstacles)

    def crossed(e, blocked):
        ax, ay, bx, by, valid = (x[e] for x in edges)
        return blocked | (valid & _segments_cross(ox, oy, tx, ty, ax, ay, bx, by))

    return ~_loop(edges[0].shape[0], crossed, jnp.zeros(tx.shape, bool))


def lidar_scan(
    origin, heading, obstacles: Obstacles, circle_pos, circle_radius, circle_mask, *, num_rays: int, max_range
):
    """Ranges (num_rays,) float32 of a 2-D LiDAR at `origin` (2,) with heading `heading` () rad.

    Ray k points at heading + 2 pi k / num_rays (counter-clockwise; ray 0 along the heading: the body frame a
    real 2-D LiDAR reports in) and returns the distance to its first hit among the obstacle edges and the
    discs circle_pos (N, 2) / circle_radius (N,) where circle_mask (N,) holds, capped at `max_range` (a miss
    returns max_range). An origin inside (or on) a disc or inside a polygon blocks the sensor: all ranges 0.
    `num_rays` is static.
    """
    angle = heading + (2.0 * math.pi / num_rays) * jnp.arange(num_rays, dtype=jnp.float32)
    dx, dy = jnp.cos(angle), jnp.sin(angle)  # (R,)
    ox, oy = origin[0], origin[1]

    # Loops over the edges and the discs, each iteration a fused pass over the rays with a running nearest hit (an
    # (R, E) table reduced over its minor axis vectorises poorly under vmap, and its per-pair division is not fused).
    ax, ay, bx, by, valid = _flat_edges(obstacles)
    ex, ey = bx - ax, by - ay
    wx, wy = ax - ox, ay - oy
    t_num = _cross(wx, wy, ex, ey)  # (E,): the numerator of t does not depend on the ray

    # The nearest edge hit as a fraction best_n / best_d (best_d > 0), compared by cross-multiplication: one
    # division per ray; the chosen edge's t is its exact quotient t_num / denom (the signs flip exactly).
    def nearer_edge(e, best):
        best_n, best_d = best
        denom = _cross(dx, dy, ex[e], ey[e])
        # t >= 0 and 0 <= s <= 1 tested on the numerators (times the sign of denom)
        sign, size = jnp.sign(denom), jnp.abs(denom)
        tn, sn = t_num[e] * sign, _cross(wx[e], wy[e], dx, dy) * sign
        hit = valid[e] & (size > _TINY) & (tn >= 0.0) & (sn >= 0.0) & (sn <= size) & (tn * best_d < best_n * size)
        return jnp.where(hit, tn, best_n), jnp.where(hit, size, best_d)

    best = (jnp.full(dx.shape, jnp.inf, jnp.float32), jnp.ones(dx.shape, jnp.float32))
    best_n, best_d = _loop(ax.shape[0], nearer_edge, best)
    edge_range = best_n / best_d  # inf where no edge is hit

    mx, my = circle_pos[:, 0] - ox, circle_pos[:, 1] - oy  # (N,)
    q = mx * mx + my * my - circle_radius * circle_radius

    def nearer_disc(i, circle_range):
        b = dx * mx[i] + dy * my[i]
        disc = b * b - q[i]
        hit = circle_mask[i] & (q[i] > 0.0) & (b > 0.0) & (disc >= 0.0)
        return jnp.where(hit, jnp.minimum(circle_range, b - jnp.sqrt(jnp.maximum(disc, 0.0))), circle_range)

    circle_range = _loop(mx.shape[0], nearer_disc, jnp.full(dx.shape, jnp.inf, jnp.float32))

    ranges = jnp.minimum(jnp.minimum(edge_range, circle_range), max_range)
    blocked = jnp.any(circle_mask & (q <= 0.0)) | inside(origin, obstacles)
    return jnp.where(blocked, 0.0, ranges).astype(jnp.float32)


def wall_force(positions, radii, obstacles: Obstacles, *, a, b):
    """Social-force repulsion (N, 2) of the static obstacles on N discs at positions (N, 2) with radii (N,).

    Helbing, Farkas & Vicsek (2000), eq. 2's wall term without body and friction forces, summed over obstacle
    slots W: A exp((r_i - d_iW) / B) n_iW, where d_iW is the distance from the centre to the nearest point of W
    (over its edges, so a corner shared by two edges counts once) and n_iW the unit vector from that point to
    the centre. The formula leaves a centre inside a polygon undefined; there d_iW is negative and n_iW is
    flipped, so the push is strong and points out of the polygon. A centre exactly on an edge gets no push
    (no direction), as coincident agents in `social_force.step`. The exponent is capped as there.
    """
    ax, ay, bx, by, valid = _slot_edges(obstacles)  # (M, V)
    px, py = positions[:, 0], positions[:, 1]
    cx, cy, sq = _closest_on_segment(px[:, None, None], py[:, None, None], ax, ay, bx, by)  # (N, M, V)
    sq = jnp.where(valid, sq, jnp.inf)
    # Nearest point per slot, picked with a one-hot mask of the first nearest edge (cheaper than a gather).
    num_v = sq.shape[-1]
    nearest = jnp.argmin(sq, axis=-1) if num_v else jnp.zeros(sq.shape[:-1], jnp.int32)
    pick = jnp.arange(num_v)[None, None, :] == nearest[..., None]
    qx = jnp.sum(jnp.where(pick, cx, 0.0), axis=-1)
    qy = jnp.sum(jnp.where(pick, cy, 0.0), axis=-1)  # (N, M)
    ux, uy = px[:, None] - qx, py[:, None] - qy
    dist = jnp.sqrt(jnp.maximum(ux * ux + uy * uy, 1e-12))
    sign = jnp.where(_inside_slots(px, py, obstacles), -1.0, 1.0)
    magnitude = a * jnp.exp(jnp.minimum((radii[:, None] - sign * dist) / b, _MAX_EXPONENT))
    used = jnp.any(valid, axis=-1)[None, :]
    fx = jnp.sum(jnp.where(used, magnitude * sign * ux / dist, 0.0), axis=-1)
    fy = jnp.sum(jnp.where(used, magnitude * sign * uy / dist, 0.0), axis=-1)
    return jnp.stack([fx, fy], -1)
