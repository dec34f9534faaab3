"""The batched kernel and the public entry points: :func:`solve` and :func:`solve_with_info` for one scene,
whose custom_vmap rule hands a whole ``jax.vmap`` batch (nested too) to one kernel over every scene."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from tgrf_jax.env.orca.agent_lines import _neighbour_lines
from tgrf_jax.env.orca.linear_program import _linear_program2, _lp2_start
from tgrf_jax.env.orca.linear_program3 import _linear_program3
from tgrf_jax.env.orca.obstacle_lines import _obstacle_lines
from tgrf_jax.env.orca.obstacle_lp import _lp3_obstacle_part, _obstacle_bounds, _obstacle_lp, _obstacle_walk
from tgrf_jax.env.orca.obstacle_tree import _TABLE_LEAVES, _ObstacleTable, _process_scenes, _table_from_leaves

# linearProgram2's blocks (each runs dense rounds until its slowest problem is done) and linearProgram3's chunks
# (each runs dense inner LP2 rounds until its slowest problem is done), in problems
CPU_BLOCK = 128
WHOLE_BATCH = 2**31 - 1  # one block: all problems (clamped to their number)


def default_block() -> int:
    """The block size for the backend that programs compile for: CPU_BLOCK on a CPU, WHOLE_BATCH elsewhere."""
    return CPU_BLOCK if jax.default_backend() == "cpu" else WHOLE_BATCH


def _solve_scenes(pos, vel, rad, pref, vmax, mask, time_horizon, dt, neighbor_dist, *obstacles, k, block):
    """Batched core: pos/vel/pref (B, N, 2), rad/vmax/mask (B, N), scalars (B,); ``obstacles``: none, or
    vertices (B, M, V, 2), num_vertices (B, M) (or the leaves of their :class:`ObstacleTable`, each (B, E)) and
    time_horizon_obst (B,).  Returns (B, N, 2) and the
    per-agent LP2 failure flag (B, N)."""
    b, n = rad.shape
    f32 = jnp.float32
    pos, vel, pref = pos.astype(f32), vel.astype(f32), pref.astype(f32)
    a = b * n
    agent_major = lambda x: x.T.reshape(a)  # (B, N) -> problem p = agent * B + scene
    scene_major = lambda x: x.reshape(n, b).T
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
    f32 = lambda x: jnp.asarray(x, jnp.float32)
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
    left to the caller.  Jittable and vmappable (``jax.vmap(solve)`` runs one batched kernel, see
    docs/design.md).  float32 throughout.

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
        rebuilding RVO2's obstacle tree in every call.  Under ``jax.vmap`` each scene may have its own (or
        all share unbatched ones).  None, or M * V == 0: the obstacle-free program.  RVO2's kd-tree splits
        edges; here at most :func:`obstacle_tree._edge_capacity` (M * V) - M * V of them (the env's layouts
        need far fewer), an edge beyond that staying whole.
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
