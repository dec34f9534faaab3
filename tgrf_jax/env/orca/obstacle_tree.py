"""RVO2's addObstacle and processObstacles for every scene: the polygons as directed edges, and RVO2's kd-tree
(a BSP) built one level at a time, for the edges it splits and the order in which its query visits adjacent
edges.  Edge tables are (E, B): edge slot, scene."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from tgrf_jax.env.orca.numerics import RVO_EPSILON, _det, _left_of, _normalized


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
