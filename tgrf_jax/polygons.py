"""Obstacle polygons as a config gives them: host-side (numpy) validation, before anything is traced.

`check_polygons` is what `env.obstacles` and `tgrf_jax.env.obstacles.from_polygons` run: a config names its bad
polygon when it is built, not when an env compiles. It sits below `tgrf_jax.config` (pyproject's import layers),
beside the declaration machinery, because config needs it and may not import the env; the traced geometry of the
obstacles (distances, occlusion, LiDAR) is in `tgrf_jax.env.obstacles`.
"""

from __future__ import annotations

import numbers

import numpy as np

from tgrf_jax.fields import ConfigError


def _describe(polygon) -> str:
    text = repr(polygon)
    return text if len(text) <= 80 else text[:77] + "..."


def segments_intersect(a, b, c, d) -> np.ndarray:
    """Whether closed segments a-b and c-d intersect (touching included); arrays of shape (..., 2), float64."""

    def orient(p, q, r):
        return np.sign(
            (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0])
        )

    def on_segment(p, q, r):  # r collinear with p-q: within its bounding box
        return (
            (np.minimum(p[..., 0], q[..., 0]) <= r[..., 0])
            & (r[..., 0] <= np.maximum(p[..., 0], q[..., 0]))
            & (np.minimum(p[..., 1], q[..., 1]) <= r[..., 1])
            & (r[..., 1] <= np.maximum(p[..., 1], q[..., 1]))
        )

    o1, o2, o3, o4 = orient(a, b, c), orient(a, b, d), orient(c, d, a), orient(c, d, b)
    proper = (o1 * o2 < 0) & (o3 * o4 < 0)
    touch = (
        ((o1 == 0) & on_segment(a, b, c))
        | ((o2 == 0) & on_segment(a, b, d))
        | ((o3 == 0) & on_segment(c, d, a))
        | ((o4 == 0) & on_segment(c, d, b))
    )
    return proper | touch


def _edges(polygon: np.ndarray):
    """(start, end) of a polygon's edges (a 2-vertex wall has one)."""
    if len(polygon) == 2:
        return polygon[:1], polygon[1:]
    return polygon, np.roll(polygon, -1, axis=0)


def _point_segment_distance(p, a, b) -> np.ndarray:
    e = b - a
    t = np.clip(np.sum((p - a) * e, -1) / np.maximum(np.sum(e * e, -1), 1e-300), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[..., None] * e), axis=-1)


def polygon_gap(p, q) -> float:
    """Smallest distance between the edges of polygons p and q ((n, 2) each); 0 where they touch or cross (one
    inside the other also counts as 0 only where edges meet, which is enough to find narrow gaps)."""
    a, b = (x[:, None, :] for x in _edges(np.asarray(p, float)))
    c, d = (x[None, :, :] for x in _edges(np.asarray(q, float)))
    a, b, c, d = np.broadcast_arrays(a, b, c, d)
    if np.any(segments_intersect(a, b, c, d)):
        return 0.0
    return float(
        np.min(
            np.minimum(
                np.minimum(_point_segment_distance(a, c, d), _point_segment_distance(b, c, d)),
                np.minimum(_point_segment_distance(c, a, b), _point_segment_distance(d, a, b)),
            )
        )
    )


def narrow_gaps(polygons, width: float) -> list[tuple[int, int, float]]:
    """(i, j, gap) for each pair of polygons whose gap is open (> 0) but narrower than `width`."""
    polys = [np.asarray(p, float) for p in polygons]
    found = []
    for i in range(len(polys)):
        for j in range(i + 1, len(polys)):
            gap = polygon_gap(polys[i], polys[j])
            if 0.0 < gap < width:
                found.append((i, j, gap))
    return found


def check_polygons(polygons, field: str, *, max_polygons=None, max_vertices=None, why: str = "") -> tuple:
    """Validate obstacle polygons on the host; returns them as tuples of (x, y) float pairs (hashable, as configs are).

    Raises ConfigError naming `field`, the polygon's index and what is allowed for: anything but a list of
    polygons, more than `max_polygons` polygons or a polygon of more than `max_vertices` vertices (capacities,
    checked before the rest; `why` says where a bound comes from), a polygon with fewer than 2 vertices, vertices
    that are not pairs of finite numbers, a clockwise polygon, zero-length edges (repeated consecutive vertices,
    the last and first included), a polygon of 3+ vertices that encloses no area, and a self-intersecting polygon.
    """
    if polygons is None or isinstance(polygons, (str, bytes, dict)) or not hasattr(polygons, "__len__"):
        raise ConfigError(f"{field} = {_describe(polygons)} must be a list of polygons, each a list of [x, y] vertices")
    if max_polygons is not None and len(polygons) > max_polygons:
        raise ConfigError(
            f"{field} has {len(polygons)} polygons; allowed: at most {max_polygons}" + (f" ({why})" if why else "")
        )
    checked = []
    for i, polygon in enumerate(polygons):
        where = f"{field}[{i}] = {_describe(polygon)}"
        # Checked coordinate by coordinate: numpy would quietly parse strings such as "1.5" as numbers.
        try:
            rows = [list(vertex) for vertex in polygon]
        except TypeError:
            rows = None
        if (
            rows is None
            or isinstance(polygon, (str, bytes, dict))
            or not all(
                len(r) == 2 and all(isinstance(c, numbers.Real) and not isinstance(c, bool) for c in r) for r in rows
            )
        ):
            raise ConfigError(f"{where} must be a list of [x, y] vertices, each a pair of numbers")
        if max_vertices is not None and len(rows) > max_vertices:
            raise ConfigError(f"{where} has {len(rows)} vertices; allowed: at most {max_vertices}")
        v = np.array(rows, dtype=np.float64).reshape(-1, 2)
        n = v.shape[0]
        if n < 2:
            raise ConfigError(f"{where} has {n} vertices; allowed: 2 (a wall segment) or more (a polygon)")
        if not np.all(np.isfinite(v)):
            raise ConfigError(f"{where} has non-finite coordinates; every coordinate must be a finite number")
        nxt = np.roll(v, -1, axis=0)
        edge_len = np.hypot(*(nxt - v).T)
        if np.any(edge_len[: n if n >= 3 else 1] == 0.0):
            raise ConfigError(
                f"{where} has a zero-length edge (repeated consecutive vertices, the last and the "
                "first included); give each vertex once"
            )
        if n >= 3:
            # Every pair of edges must meet only where they share a vertex. Adjacent edges share one; they
            # intersect elsewhere only by folding back over each other, caught by the collinear test below.
            j = np.arange(n)
            hit = segments_intersect(v[:, None], nxt[:, None], v[None, :], nxt[None, :])
            adjacent = (
                (j[:, None] == j[None, :]) | ((j[:, None] + 1) % n == j[None, :]) | ((j[None, :] + 1) % n == j[:, None])
            )
            e, f = nxt - v, np.roll(nxt - v, -1, axis=0)  # edge k and edge k + 1, which share vertex k + 1
            folds = (e[:, 0] * f[:, 1] - e[:, 1] * f[:, 0] == 0) & (e[:, 0] * f[:, 0] + e[:, 1] * f[:, 1] < 0)
            if np.any(hit & ~adjacent) or np.any(folds):
                raise ConfigError(
                    f"{where} intersects itself; allowed: simple polygons (edges meet only at shared vertices)"
                )
            area = 0.5 * np.sum(v[:, 0] * nxt[:, 1] - nxt[:, 0] * v[:, 1])
            if area < 0:
                raise ConfigError(
                    f"{where} is clockwise (signed area {area:g}); give the vertices "
                    "counter-clockwise (interior on the left of each edge, as RVO2)"
                )
            if area == 0:
                raise ConfigError(f"{where} encloses no area (collinear vertices); use 2 vertices for a wall")
        checked.append(tuple((float(x), float(y)) for x, y in v))
    return tuple(checked)
