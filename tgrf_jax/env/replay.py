"""Recorded pedestrians as the simulator's humans (`env.scenario: replay`, docs/replay.md, "Playing
recordings").

On the host, once per env (`load`): the files of `env.replay_files` are read and resampled onto `env.dt`
(`tgrf_jax.pedestrians`), and every scene is packed into fixed-shape arrays. Each person's continuous track is
given a column of its scene by a greedy colouring of the tracks' presence intervals (a column holds one person at
a time and is reused by a later one), so the columns needed are exactly the largest crowd in view, and the env
reads a person's position as `positions[scene, step, column]` with no assignment work at run time.

In the compiled program the scene is a traced index into those arrays (one program for every scene). An episode
(`reset`) draws a scene and a start step (scenes weighted by their length, so every recorded moment is as
likely), a rotation, reflection and translation of the whole scene (`env.replay_augment`), and the robot's start
and goal among the positions people walked on. Human slot j plays column `ReplayState.slot[j]`: column j while
the columns fit the slots, else (`env.replay_overflow: nearest`) the people nearest the robot, re-chosen every
step, a person keeping their slot while they stay among the nearest.

Humans follow their recordings exactly (`env.human_policy: replay`) or, with ORCA or Social Force, take the
velocity that would bring them back onto their recorded position at the next step as their preferred velocity
and avoid each other (and the robot, with `env.robot_visible`) on the way (`steering`).
"""

from __future__ import annotations

import dataclasses
import functools
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from tgrf_jax.config import ConfigError, EnvConfig
from tgrf_jax.env.humans import Steering
from tgrf_jax.env.scenarios.sampling import choose, park, uniform
from tgrf_jax.env.types import EnvParams, Humans, Robot
from tgrf_jax.pedestrians import ETH_UCY, RecordingError, RecordingSpec, default_data_dir, load
from tgrf_jax.pedestrians import catalogue as catalogue_lib

# Positions people walked on kept per scene for the robot's start and goal draws: evenly spaced in time, enough to
# cover any recorded place densely and a small fixed share of the compiled program's constants.
WALKED_MAX = 4096
# A reactive person who fell behind their recording catches up at up to this many times their recorded speed (and
# at least env.human_v_pref_max): fast enough to rejoin it after a detour, slow enough to stay a walker.
CATCH_UP = 1.5
# Robot start and goal candidate pairs drawn per episode, per env.spawn_tries: a crowded moment leaves few
# walked positions clear of people, and a pair must also meet env.min_start_goal_dist.
_PAIRS_PER_TRY = 4


@struct.dataclass
class ReplayState:
    """Which piece of which recording an episode plays, and where it lies in the world.

    A recorded (scene-centred) position p is at `rotation @ p + offset` in the world; `rotation` includes the
    reflection (determinant -1). Step k of the episode is grid step `start + k` of the scene. Human slot j plays
    column `slot[j]` of the packed scene (-1: none)."""

    scene: jnp.ndarray  # () int32
    start: jnp.ndarray  # () int32
    rotation: jnp.ndarray  # (2, 2)
    offset: jnp.ndarray  # (2,)
    slot: jnp.ndarray  # (N,) int32


@dataclasses.dataclass(frozen=True, eq=False)
class ReplayData:
    """The recordings of an env packed for the compiled program (S scenes, T grid steps, K columns, P tracks):

    - ``positions`` (S, T, K, 2) float32: metres, each scene centred on the mean of its walked positions;
    - ``track`` (S, T, K) int32: the track a column holds at a step (its index in the scene), -1 where empty;
    - ``last`` (S, P, 2) float32: each track's last position (where the person goes: the humans' goal);
    - ``lengths`` (S,) int32: grid steps of each scene; ``walked`` (S, W, 2) and ``num_walked`` (S,): positions
      people walked on; ``entry`` (S,) int32: the entry of env.replay_files a scene comes from; ``dt``: the grid
      step (s); ``sources``: the files; ``nearest``: K exceeds the human slots and the slots play the people
      nearest the robot.
    """

    positions: np.ndarray
    track: np.ndarray
    last: np.ndarray
    lengths: np.ndarray
    walked: np.ndarray
    num_walked: np.ndarray
    entry: np.ndarray
    dt: float
    sources: tuple[str, ...]
    nearest: bool

    @property
    def num_columns(self) -> int:
        return int(self.track.shape[2])

    @property
    def entry_lengths(self) -> np.ndarray:
        """(E,) float32: the start steps each entry of env.replay_files offers (its scenes' lengths less one): the
        entries' weights that make every recorded moment equally likely (env.replay_weights None)."""
        return np.bincount(self.entry, weights=self.lengths - 1).astype(np.float32)


def resolve(files) -> list[tuple[int, RecordingSpec]]:
    """`env.replay_files` (as the config normalises it) as (the entry's index, spec) pairs, one per file: catalogue
    names are looked up in the user data directory (`tgrf_jax.pedestrians.default_data_dir`)."""
    out = []
    for i, item in enumerate(files):
        if isinstance(item, str):
            for entry in catalogue_entries(item):
                out.append((i, entry.spec()))
        else:
            out.append((i, RecordingSpec(**dict(item))))
    return out


def catalogue_entries(name: str):
    """The catalogue files a name stands for: 'eth-ucy' (all), a leave-one-scene-out fold ('eth', 'hotel', 'univ',
    'zara1', 'zara2': its test files) or a file's name in the data directory ('ucy/crowds_zara03.txt')."""
    if name in catalogue_lib.DATASETS:
        return catalogue_lib.DATASETS[name]
    if name in catalogue_lib.FOLDS:
        return catalogue_lib.split(name)[1]
    found = tuple(e for e in ETH_UCY if e.name == name)
    if not found:
        raise KeyError(name)
    return found


def assign_columns(mask: np.ndarray) -> tuple[np.ndarray, int]:
    """Columns (P,) for tracks with presence `mask` (T, P) (each track present on one contiguous run of steps),
    no two tracks sharing a column at a step, and their number (the largest crowd: greedy colouring of intervals
    in order of their start is optimal). A column left free for at least one step is preferred, so a person
    leaving and another entering the same slot show as a step with the slot inactive where the crowd allows."""
    present = mask.any(axis=0)
    first = np.where(present, mask.argmax(axis=0), 0)
    last = np.where(present, mask.shape[0] - 1 - mask[::-1].argmax(axis=0), -1)
    ends: list[int] = []  # the last step of each column's latest track
    columns = np.full(mask.shape[1], -1, np.int64)
    for p in sorted(np.flatnonzero(present), key=lambda p: (first[p], p)):
        free = [c for c, e in enumerate(ends) if e < first[p]]
        if free:
            rested = [c for c in free if ends[c] < first[p] - 1]
            c = min(rested or free, key=lambda c: ends[c])  # the longest free: the most room for the next one
            ends[c] = last[p]
        else:
            c = len(ends)
            ends.append(last[p])
        columns[p] = c
    return columns, len(ends)


def _stat(index: int, spec: RecordingSpec) -> tuple:
    """What the cache of packed recordings is keyed on for one file: its entry, spec, size and modification time
    (an edited file is read again)."""
    name = f"env.replay_files[{index}]"
    try:
        info = pathlib.Path(spec.path).stat()
    except OSError:
        hint = " (fetch the catalogue's recordings with `tgrf-data fetch eth-ucy`)"
        known = str(spec.path).startswith(str(default_data_dir()))
        raise ConfigError(f"{name}: {spec.path}: no such file{hint if known else ''}") from None
    return index, spec, info.st_size, info.st_mtime_ns


def _load_scenes(files: tuple, dt: float):
    scenes = []
    for index, spec, _, _ in files:
        name = f"env.replay_files[{index}]"
        try:
            scene = load(spec, dt=dt)
        except RecordingError as e:
            raise ConfigError(f"{name}: {e}") from None
        if scene.num_steps < 2:
            raise ConfigError(f"{name}: {spec.path}: shorter than two steps of env.dt = {dt:g} s")
        scenes.append((name, scene))
    return scenes


@functools.lru_cache(maxsize=8)
def _packed(files: tuple, dt: float, num_humans: int, overflow: str) -> ReplayData:
    scenes = _load_scenes(files, dt)
    for name, scene in scenes:
        crowd = scene.max_crowd()
        if crowd.count > num_humans and overflow == "error":
            frame = crowd.time / scene.seconds_per_frame
            raise ConfigError(
                f"{name}: {scene.source}: {crowd.count} people are in view at frame {frame:g} "
                f"({crowd.time:.2f} s), more than env.num_humans = {num_humans} human slots; raise env.num_humans "
                "or set env.replay_overflow: nearest (the slots then play the people nearest the robot)"
            )
    coloured = [assign_columns(scene.mask) for _, scene in scenes]
    s, t = len(scenes), max(scene.num_steps for _, scene in scenes)
    k = max(1, max(n for _, n in coloured))
    p = max(1, max(scene.num_tracks for _, scene in scenes))
    positions = np.zeros((s, t, k, 2), np.float32)
    track = np.full((s, t, k), -1, np.int32)
    last = np.zeros((s, p, 2), np.float32)
    walked = np.zeros((s, WALKED_MAX, 2), np.float32)
    num_walked = np.zeros((s,), np.int32)
    for i, ((_, scene), (columns, _)) in enumerate(zip(scenes, coloured)):
        ground = scene.walked_positions()
        centre = ground.mean(axis=0) if len(ground) else np.zeros(2, np.float32)
        steps, tracks = np.nonzero(scene.mask)
        positions[i, steps, columns[tracks]] = scene.positions[steps, tracks] - centre
        track[i, steps, columns[tracks]] = tracks
        for q in range(scene.num_tracks):
            present = np.flatnonzero(scene.mask[:, q])
            if present.size:
                last[i, q] = scene.positions[present[-1], q] - centre
        keep = np.linspace(0, len(ground) - 1, min(len(ground), WALKED_MAX)).astype(np.int64)
        walked[i, : len(keep)] = ground[keep] - centre
        num_walked[i] = len(keep)
    lengths = np.asarray([scene.num_steps for _, scene in scenes], np.int32)
    sources = tuple(scene.source for _, scene in scenes)
    entry = np.asarray([index for index, *_ in files], np.int32)
    return ReplayData(positions, track, last, lengths, walked, num_walked, entry, float(dt), sources, k > num_humans)


def load_data(config: EnvConfig) -> ReplayData:
    """The env's recordings, read and packed once per (files and their versions on disk, dt, capacity, overflow:
    envs of one config share them); raises ConfigError naming
    the entry of env.replay_files and the file for a missing or malformed file and for a crowd that does not fit
    the human slots."""
    files = tuple(_stat(index, spec) for index, spec in resolve(config.replay_files))
    return _packed(files, float(config.dt), config.num_humans, config.replay_overflow)


# ---------------------------------------------------------------------------------------------- compiled side


def _world(state: ReplayState, points):
    return points @ state.rotation.T + state.offset


def _columns(state: ReplayState):
    return jnp.maximum(state.slot, 0), state.slot >= 0


def _at(data: ReplayData, state: ReplayState, step):
    """(world positions (K, 2), tracks (K,)) of every column at grid step `step` (clipped to the scene)."""
    step = jnp.clip(step, 0, data.track.shape[1] - 1)
    pos = jnp.asarray(data.positions)[state.scene, step]
    return _world(state, pos), jnp.asarray(data.track)[state.scene, step]


def _nearest_slots(data: ReplayData, state: ReplayState, step, robot_pos, num_humans: int):
    """The slot mapping at `step` with the slots playing the people nearest `robot_pos`: a person already in a slot
    keeps it while among the nearest; newcomers take the freed slots in column order."""
    k = data.num_columns
    pos, track = _at(data, state, step)
    present = track >= 0
    dist = jnp.where(present, jnp.sum(jnp.square(pos - robot_pos), -1), jnp.inf)
    rank = jnp.argsort(jnp.argsort(dist))
    wanted = present & (rank < num_humans)
    old, had = _columns(state)
    keep = had & wanted[old]
    taken = jnp.zeros((k,), bool).at[jnp.where(keep, old, k)].set(True, mode="drop")
    newcomers = wanted & ~taken
    order = jnp.argsort(~newcomers, stable=True)  # the newcomers' columns first, in column order
    free_rank = jnp.cumsum(~keep) - 1
    assign = ~keep & (free_rank < jnp.sum(newcomers))
    new = order[jnp.clip(free_rank, 0, k - 1)]
    return jnp.where(keep, old, jnp.where(assign, new, -1)).astype(jnp.int32)


def recorded_humans(data: ReplayData, state: ReplayState, step, radius, v_pref) -> Humans:
    """The humans as recorded at grid step `step`: slot j at its column's position, active where a person is
    present; velocity: what brought them there from the previous step (the next step's for a person just
    entering); goal: where the person's track ends. The rest are parked."""
    col, has = _columns(state)
    pos, track = _at(data, state, step)
    prev_pos, prev_track = _at(data, state, step - 1)
    next_pos, next_track = _at(data, state, step + 1)
    tr = track[col]
    active = has & (tr >= 0)
    came = (step > 0) & (prev_track[col] == tr)
    goes = (step + 1 < jnp.asarray(data.lengths)[state.scene]) & (next_track[col] == tr)
    here = pos[col]
    vel = jnp.where(
        came[:, None], here - prev_pos[col], jnp.where(goes[:, None], next_pos[col] - here, 0.0)
    ) / jnp.float32(data.dt)
    goal = _world(state, jnp.asarray(data.last)[state.scene, jnp.maximum(tr, 0)])
    return park(Humans(pos=here, vel=vel, goal=goal, radius=radius, v_pref=v_pref, active=active))


def reset(key, data: ReplayData, params: EnvParams, config: EnvConfig, radius, v_pref):
    """An episode of the recordings: (ReplayState, Robot, Humans)."""
    k_scene, k_start, k_angle, k_flip, k_shift, k_robot = jax.random.split(key, 6)
    lengths = jnp.asarray(data.lengths)
    usable = (lengths - 1).astype(jnp.float32)  # start steps 0 .. length - 2 leave at least one step to play
    # a scene's share of its entry's weight is its share of the entry's start steps
    entry = jnp.asarray(data.entry)
    weights = params.replay_weights[entry] * usable / jnp.asarray(data.entry_lengths)[entry]
    edges = jnp.cumsum(weights)
    scene = jnp.minimum(jnp.sum(edges <= uniform(k_scene, ()) * edges[-1]), lengths.shape[0] - 1).astype(jnp.int32)
    start = jnp.minimum(jnp.floor(uniform(k_start, ()) * usable[scene]), usable[scene] - 1).astype(jnp.int32)
    if config.replay_augment:
        angle = uniform(k_angle, (), 0.0, 2.0 * jnp.pi)
        flip = jnp.where(uniform(k_flip, ()) < 0.5, -1.0, 1.0)
        offset = uniform(k_shift, (2,), -0.5, 0.5) * params.arena_size
    else:
        angle, flip, offset = jnp.zeros(()), jnp.ones(()), jnp.zeros((2,))
    c, s = jnp.cos(angle), jnp.sin(angle)
    rotation = jnp.stack([jnp.stack([c * flip, -s]), jnp.stack([s * flip, c])])  # rotate(angle) @ diag(flip, 1)
    n = config.num_humans
    k = data.num_columns
    first = jnp.where(jnp.arange(n) < k, jnp.arange(n), -1).astype(jnp.int32)
    state = ReplayState(scene, start, rotation, offset, first)

    # The robot: start and goal among walked positions, the start clear of everyone present now.
    pairs = config.spawn_tries * _PAIRS_PER_TRY
    pick = jnp.floor(uniform(k_robot, (2, pairs)) * jnp.asarray(data.num_walked)[scene]).astype(jnp.int32)
    ends = _world(state, jnp.asarray(data.walked)[scene][pick])  # (2, pairs, 2)
    people, track = _at(data, state, start)
    gap = jnp.linalg.norm(ends[0][:, None] - people[None], axis=-1)
    room = params.robot_radius + params.human_radius_max + params.spawn_clearance
    clear = jnp.min(jnp.where(track[None] >= 0, gap - room, jnp.inf), axis=-1, initial=jnp.inf)
    apart = jnp.linalg.norm(ends[1] - ends[0], axis=-1) - params.min_start_goal_dist
    chosen = choose(jnp.concatenate([ends[0], ends[1]], -1), jnp.minimum(clear, apart))
    robot = Robot(
        pos=chosen[:2],
        vel=jnp.zeros(2),
        goal=chosen[2:],
        heading=jnp.asarray(jnp.pi / 2, jnp.float32),
        speed=jnp.zeros(()),
    )
    if data.nearest:
        state = state.replace(slot=_nearest_slots(data, state.replace(slot=jnp.full((n,), -1)), start, robot.pos, n))
    return state, robot, recorded_humans(data, state, start, radius, v_pref)


def advance(data: ReplayData, state: ReplayState, humans0: Humans, moved: Humans, robot: Robot, step_count):
    """The humans and replay state after a step to episode step `step_count`: the recording's people at that grid
    step; `moved` (the humans as the step's velocities moved them: reactive replay) keeps each person who stays in
    their slot (non-reactive replay passes the recording itself, None)."""
    step = state.start + step_count
    old = state
    if data.nearest:
        state = state.replace(slot=_nearest_slots(data, state, step, robot.pos, humans0.pos.shape[0]))
    recorded = recorded_humans(data, state, step, humans0.radius, humans0.v_pref)
    if moved is None:
        return recorded, state
    # a person who was in the same slot at the step before (same column, same track) walked on from where they were
    col, _ = _columns(state)
    _, before = _at(data, state, step - 1)
    _, now = _at(data, state, step)
    stays = humans0.active & recorded.active & (old.slot == state.slot) & (before[col] == now[col])
    pick = lambda a, b: jnp.where(stays.reshape(stays.shape + (1,) * (a.ndim - 1)), a, b)
    return recorded.replace(pos=pick(moved.pos, recorded.pos), vel=pick(moved.vel, recorded.vel)), state


def steering(data: ReplayData, state: ReplayState, humans: Humans, params: EnvParams, step_count):
    """Reactive replay: (Steering, the humans with their speed limits) for the step from episode step
    `step_count`. Each person heads for their recorded position at the next grid step, the preferred velocity
    being the one that reaches it in one step (their recorded velocity while on track), capped at CATCH_UP times
    their recorded speed (and at least env.human_v_pref_max)."""
    step = state.start + step_count
    col, _ = _columns(state)
    now, track = _at(data, state, step)
    target, next_track = _at(data, state, step + 1)
    on = humans.active & (next_track[col] == track[col])
    target = jnp.where(on[:, None], target[col], humans.pos)
    recorded_speed = jnp.linalg.norm(target - now[col], axis=-1) / jnp.float32(data.dt)
    cap = jnp.maximum(params.human_v_pref_max, CATCH_UP * recorded_speed)
    wish = (target - humans.pos) / jnp.float32(data.dt)
    speed = jnp.linalg.norm(wish, axis=-1)
    wish = wish * jnp.minimum(1.0, cap / jnp.maximum(speed, 1e-9))[:, None]
    n = humans.pos.shape[0]
    steer = Steering(target, jnp.zeros((n,), bool), jnp.zeros((n, 2)), velocity=wish)
    return steer, humans.replace(v_pref=jnp.where(humans.active, cap, humans.v_pref))


def future(data: ReplayData, state: ReplayState, humans: Humans, step_count, k: int):
    """The recorded future (N, k, 2) of each slot's person at the next k grid steps (world frame); after their
    track ends, where it ended; inactive slots stay where they are parked."""
    step = state.start + step_count
    col, _ = _columns(state)
    _, track = _at(data, state, step)
    tr = track[col]
    ahead = jax.vmap(lambda s: _at(data, state, s))(step + 1 + jnp.arange(k))  # (k, K, 2), (k, K)
    same = ahead[1][:, col] == tr
    end = _world(state, jnp.asarray(data.last)[state.scene, jnp.maximum(tr, 0)])
    fut = jnp.where(same[..., None], ahead[0][:, col], end)
    fut = jnp.where(humans.active[None, :, None], fut, humans.pos)
    return jnp.swapaxes(fut, 0, 1)


def finished(data: ReplayData, state: ReplayState, step_count):
    """The recording has no grid step left for another step after episode step `step_count`."""
    return state.start + step_count >= jnp.asarray(data.lengths)[state.scene] - 1


__all__ = [
    "CATCH_UP",
    "ReplayData",
    "ReplayState",
    "advance",
    "assign_columns",
    "finished",
    "future",
    "load_data",
    "recorded_humans",
    "reset",
    "steering",
]
