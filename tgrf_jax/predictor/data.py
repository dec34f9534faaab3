"""Training data for the predictor, collected from the JAX simulator as CrowdNav++ records it, or made from
recorded pedestrians (`recorded`).

The robot is driven by ORCA and is invisible to the humans; episodes never end (collisions are ignored and a
robot that reaches its goal gets a new one: half the time the median human position, half the time uniform
in the arena). Each frame logs the robot position, every human's position, whether the robot sees the human
(5 m edge-to-edge) and a per-slot segment counter that advances when a human re-enters the view or respawns,
so a returning human is a new pedestrian. A dataset is a `.npz` of these arrays plus the config that made
it (also beside it as JSON); the same config and seed give the same arrays.

Windows are 10 frames (5 observed, 5 predicted) at stride 1, kept when at least one pedestrian is present in
all 10. The first 80% of the envs (each one long episode) train, the last 20% validate.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from tgrf_jax.env import scenarios, sensing
from tgrf_jax.env.crowd import CrowdNavEnv
from tgrf_jax.env.gst.history import FILLER_OFFSET
from tgrf_jax.env.gst.model import OBS_LEN, PRED_LEN
from tgrf_jax.env.types import EnvState, Obs
from tgrf_jax.policies import OrcaPolicy

WINDOW = OBS_LEN + PRED_LEN
CROWDS = ("orca", "social_force")
TRAIN_FRACTION = 0.8
_RESPAWN_JUMP = 1.0  # metres in one step: no human walks that far (v_pref <= 1.5 m/s, dt 0.25 s)
_FORMAT = 1
MAX_FRAMES = 20_000_000


class DatasetError(ValueError):
    """A dataset file is missing, corrupt or inconsistent; the message names the path."""


@dataclasses.dataclass(frozen=True)
class CollectConfig:
    crowd: str = "orca"
    num_envs: int = 512
    steps: int = 4000
    seed: int = 0
    num_humans: int = 20
    chunk: int = 250

    def __post_init__(self):
        if self.crowd not in CROWDS:
            raise ValueError(f"crowd = {self.crowd!r} is not allowed; allowed: {', '.join(map(repr, CROWDS))}")
        for name, low, high in (
            ("num_envs", 5, 100_000),
            ("steps", WINDOW, 1_000_000),
            ("num_humans", 1, 200),
            ("chunk", 1, 1_000_000),
        ):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < low:
                raise ValueError(f"{name} = {value!r} must be an integer >= {low}")
            if value > high:
                raise ValueError(f"{name} = {value:,} is out of range; allowed: {low} .. {high:,}")
        if self.num_envs * self.steps > MAX_FRAMES:  # the arrays are held in memory whole
            raise ValueError(
                f"num_envs x steps = {self.num_envs * self.steps:,} frames is out of range; allowed: <= {MAX_FRAMES:,}"
            )
        if not isinstance(self.seed, int) or not 0 <= self.seed < 2**31:
            raise ValueError(f"seed = {self.seed!r} must be an integer in [0, 2^31)")

    @property
    def frames(self) -> int:
        return self.num_envs * self.steps

    def env(self) -> CrowdNavEnv:
        return CrowdNavEnv({"num_humans": self.num_humans, "human_policy": self.crowd, "predictor": "none"})


@struct.dataclass
class Recorder:
    obs: Obs
    state: EnvState
    visible: jnp.ndarray  # (N,) bool, human-index order
    seg: jnp.ndarray  # (N,) int32 segment counter per slot


def _new_goal(key, state: EnvState, params):
    """Half the time the median human position, half the time uniform in the arena."""
    k_coin, k_pt = jax.random.split(key)
    uniform = scenarios.uniform(k_pt, (2,), -params.arena_size, params.arena_size)
    median = jnp.median(state.humans.pos, axis=0)
    return jnp.where(scenarios.uniform(k_coin, ()) < 0.5, median, uniform)


def make_recorder(config: CollectConfig):
    """(init(key) -> Recorder, step(rec, key) -> (rec, frame)) for one env; vmap over envs."""
    env = config.env()
    params = env.default_params
    robot_policy = OrcaPolicy()

    def init(key):
        obs, state = env.reset_env(key, params)
        visible = sensing.visible_mask(state, params)
        return Recorder(obs=obs, state=state, visible=visible, seg=jnp.zeros(visible.shape, jnp.int32))

    def step(rec: Recorder, key):
        k_step, k_goal = jax.random.split(key)
        _, state, *_ = env.step_env(k_step, rec.state, robot_policy.action(rec.obs), params)
        reached = jnp.linalg.norm(state.robot.pos - state.robot.goal) < params.goal_tolerance
        goal = jnp.where(reached, _new_goal(k_goal, state, params), state.robot.goal)
        state = state.replace(robot=state.robot.replace(goal=goal))
        visible = sensing.visible_mask(state, params)
        obs = sensing.observe(state, params, None, visible)
        respawned = jnp.linalg.norm(state.humans.pos - rec.state.humans.pos, axis=-1) > _RESPAWN_JUMP
        seg = rec.seg + (visible & (~rec.visible | respawned)).astype(jnp.int32)
        frame = dict(robot_pos=state.robot.pos, human_pos=state.humans.pos, visible=visible, seg=seg)
        return Recorder(obs=obs, state=state, visible=visible, seg=seg), frame

    return init, step


def collect(config: CollectConfig, log=print) -> dict:
    """Run the collector; returns the dataset's arrays (env-major: (B, T, ...)) and its config."""
    init, step = make_recorder(config)
    b, t, n = config.num_envs, config.steps, config.num_humans
    k_init, k_run = jax.random.split(jax.random.key(config.seed))
    rec = jax.jit(jax.vmap(init))(jax.random.split(k_init, b))

    @functools.partial(jax.jit, static_argnames="length")
    def run_chunk(rec, key, length):
        keys = jax.random.split(key, (length, b))
        return jax.lax.scan(lambda r, k: jax.vmap(step)(r, k), rec, keys)

    out = dict(
        robot_pos=np.zeros((b, t, 2), np.float32),
        human_pos=np.zeros((b, t, n, 2), np.float32),
        visible=np.zeros((b, t, n), bool),
        seg=np.zeros((b, t, n), np.int32),
    )
    start = time.perf_counter()
    done = 0
    for key in jax.random.split(k_run, -(-t // config.chunk)):
        length = min(config.chunk, t - done)
        rec, frames = run_chunk(rec, key, length)
        for name, arr in frames.items():
            out[name][:, done : done + length] = np.swapaxes(np.asarray(arr), 0, 1)
        done += length
        elapsed = time.perf_counter() - start
        log(
            f"collect {config.crowd}: {done * b:,}/{config.frames:,} frames, {elapsed:.1f} s "
            f"({done * b / elapsed:,.0f} frames/s)"
        )
    out["seg"] = out["seg"].astype(np.int16 if out["seg"].max() < 2**15 else np.int32)
    return {"arrays": out, "config": dataclasses.asdict(config), "collect_seconds": time.perf_counter() - start}


RECORDED = "recorded"  # the crowd name of a dataset made from recordings
CHUNK_STEPS = 200  # a recording is cut into "envs" of this many steps (50 s at dt 0.25)


def recorded(specs, dt: float = 0.25, chunk_steps: int = CHUNK_STEPS) -> dict:
    """A dataset of recorded pedestrians (`specs`: `pedestrians.RecordingSpec` per file), in the arrays a simulated
    one has: each file resampled onto `dt`, its people packed into columns as the replay scenario packs them (a
    column holds one person at a time; `seg` is the person's track, so a new person in a column is a new
    pedestrian), everyone present counted as seen, cut into envs of `chunk_steps` steps. The envs are ordered by
    their place in their file (each file's first chunks first), so the last 20%, the held-out split, is the last
    fifth or so of every file. Raises pedestrians.RecordingError naming a bad file."""
    from tgrf_jax.env.replay import assign_columns
    from tgrf_jax.pedestrians import load

    if not 1 <= chunk_steps <= 100_000 or chunk_steps < WINDOW:
        raise ValueError(f"chunk_steps = {chunk_steps} is out of range; allowed: {WINDOW} .. 100,000")
    chunks, sources = [], []
    for spec in specs:
        scene = load(spec, dt=dt)
        columns, k = assign_columns(scene.mask)
        steps, tracks = np.nonzero(scene.mask)
        pos = np.zeros((scene.num_steps, max(k, 1), 2), np.float32)
        seg = np.zeros((scene.num_steps, max(k, 1)), np.int32)
        vis = np.zeros((scene.num_steps, max(k, 1)), bool)
        pos[steps, columns[tracks]] = scene.positions[steps, tracks]
        seg[steps, columns[tracks]] = tracks + 1
        vis[steps, columns[tracks]] = True
        starts = range(0, scene.num_steps - WINDOW + 1, chunk_steps)
        for i, start in enumerate(starts):
            chunks.append(
                (
                    (i + 0.5) / len(starts),
                    pos[start : start + chunk_steps],
                    vis[start : start + chunk_steps],
                    seg[start : start + chunk_steps],
                )
            )
        sources.append(str(spec.path))
    if len(chunks) < 2:
        raise ValueError(f"the recordings make {len(chunks)} chunk(s) of {chunk_steps} steps; need at least 2")
    chunks.sort(key=lambda c: c[0])
    b, n = len(chunks), max(c[1].shape[1] for c in chunks)
    out = dict(
        robot_pos=np.zeros((b, chunk_steps, 2), np.float32),
        human_pos=np.zeros((b, chunk_steps, n, 2), np.float32),
        visible=np.zeros((b, chunk_steps, n), bool),
        seg=np.zeros((b, chunk_steps, n), np.int32),
    )
    for j, (_, pos, vis, seg) in enumerate(chunks):
        t, k = vis.shape
        out["human_pos"][j, :t, :k], out["visible"][j, :t, :k], out["seg"][j, :t, :k] = pos, vis, seg
        # the robot is nowhere in a recording: unseen frames are filled relative to the crowd's centre
        out["robot_pos"][j] = pos[vis].mean(axis=0) if vis.any() else 0.0
    out["seg"] = out["seg"].astype(np.int16 if out["seg"].max() < 2**15 else np.int32)
    config = {"crowd": RECORDED, "files": sources, "dt": dt, "chunk_steps": chunk_steps}
    return {"arrays": out, "config": config, "collect_seconds": None}


def save_dataset(path, dataset: dict) -> pathlib.Path:
    """Write the arrays and config to `path` (.npz; config also as a .json beside it), atomically."""
    path = pathlib.Path(path)
    if path.suffix != ".npz":
        path = path.with_suffix(".npz")
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {"format": _FORMAT, "config": dataset["config"], "collect_seconds": dataset.get("collect_seconds")}
    tmp = path.with_name(path.stem + ".tmp.npz")
    np.savez(tmp, meta=np.array(json.dumps(meta)), **dataset["arrays"])
    tmp.replace(path)
    path.with_suffix(".json").write_text(json.dumps(meta, indent=2))
    return path


def content_hash(arrays: dict) -> str:
    """SHA-256 of a dataset's arrays (names, dtypes, shapes and bytes): what identifies it, whatever its file is
    called and whatever config it records."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}:{a.dtype.str}:{a.shape};".encode())
        h.update(memoryview(a).cast("B"))
    return h.hexdigest()


_KINDS = {
    "robot_pos": ("f", "floating-point"),
    "human_pos": ("f", "floating-point"),
    "visible": ("b", "boolean"),
    "seg": ("iu", "integer"),
}


def check_arrays(arrays: dict, where: str) -> None:
    """Shapes, dtypes and finite positions of a dataset's arrays; raises DatasetError naming `where` and the array.
    (A float `visible` or NaN positions would otherwise train silently into NaN weights.)"""
    human = arrays["human_pos"]
    if human.ndim != 4 or human.shape[-1] != 2:
        raise DatasetError(f"{where}: human_pos has shape {human.shape}; expected (envs, steps, humans, 2)")
    for name, (kinds, label) in _KINDS.items():
        if arrays[name].dtype.kind not in kinds:
            raise DatasetError(f"{where}: {name} has dtype {arrays[name].dtype}; expected {label}")
    b, t, n, _ = human.shape
    expected = {"robot_pos": (b, t, 2), "visible": (b, t, n), "seg": (b, t, n)}
    for name, shape in expected.items():
        if arrays[name].shape != shape:
            raise DatasetError(f"{where}: {name} has shape {arrays[name].shape}, expected {shape}")
    if b < 2 or t < WINDOW:
        raise DatasetError(f"{where} is too small ({b} envs x {t} steps; need >= 2 x {WINDOW})")
    for name in ("robot_pos", "human_pos"):
        bad = int(np.size(arrays[name]) - np.count_nonzero(np.isfinite(arrays[name])))
        if bad:
            raise DatasetError(f"{where}: {name} holds {bad:,} non-finite values (NaN or inf); collect it again")


def load_dataset(path) -> dict:
    """Load and check a dataset written by `save_dataset`; its "sha256" is `content_hash` of the arrays."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise DatasetError(f"dataset {str(path)!r} does not exist (make one with `tgrf-predictor collect`)")
    where = f"dataset {str(path)!r}"
    try:
        with np.load(path) as data:
            arrays = {k: data[k] for k in ("robot_pos", "human_pos", "visible", "seg")}
            meta = json.loads(str(data["meta"]))
    except Exception as e:  # zip / pickle / key errors of a damaged file
        raise DatasetError(f"{where} is corrupt or not a predictor dataset: {type(e).__name__}: {e}") from None
    if not isinstance(meta, dict) or meta.get("format") != _FORMAT:
        found = meta.get("format") if isinstance(meta, dict) else meta
        raise DatasetError(f"{where} has format {found!r}; this version reads {_FORMAT}")
    config = meta.get("config")
    if not isinstance(config, dict) or not isinstance(config.get("crowd"), str):
        raise DatasetError(
            f"{where}: its metadata has no config with a crowd name (config = "
            f"{str(config)[:80]}); collect it again with `tgrf-predictor collect`"
        )
    check_arrays(arrays, where)
    return {
        "arrays": arrays,
        "config": config,
        "collect_seconds": meta.get("collect_seconds"),
        "sha256": content_hash(arrays),
    }


# ------------------------------------------------------------------------------------------ windows
def window_index(visible, seg, envs) -> np.ndarray:
    """(W, 2) int32 (env, start) of the windows of `envs` with a pedestrian present in all 10 frames."""
    rows = []
    for b in envs:
        vis = visible[b].astype(np.int32)  # (T, N)
        csum = np.concatenate([np.zeros((1, vis.shape[1]), np.int32), np.cumsum(vis, 0)])
        full = (csum[WINDOW:] - csum[:-WINDOW]) == WINDOW  # (T - 9, N) visible in all 10 frames
        same = seg[b][WINDOW - 1 :] == seg[b][: -(WINDOW - 1)]  # and no re-entry or respawn inside
        starts = np.nonzero(np.any(full & same, axis=1))[0]
        rows.append(np.stack([np.full_like(starts, b), starts], 1))
    return np.concatenate(rows).astype(np.int32)


def split_index(arrays) -> tuple[np.ndarray, np.ndarray]:
    """Train / validation windows: the first 80% of the envs (episodes) train, the rest validate."""
    b = arrays["visible"].shape[0]
    cut = max(1, min(b - 1, int(round(TRAIN_FRACTION * b))))
    return (
        window_index(arrays["visible"], arrays["seg"], range(cut)),
        window_index(arrays["visible"], arrays["seg"], range(cut, b)),
    )


@struct.dataclass
class Batch:
    positions: jnp.ndarray  # (N, 5, 2) observed, absolute; unseen frames hold the env's filler
    visible: jnp.ndarray  # (N, 5) bool
    target: jnp.ndarray  # (N, 5, 2) true positions at t+1..t+5
    target_valid: jnp.ndarray  # (N, 5) bool, present in that frame and the one before (displacement valid)


def make_window(data: dict, env_start) -> Batch:
    """One window from device arrays `data` (robot_pos, human_pos, visible, seg); jit/vmap-able.

    A slot's pedestrian is its most recent segment seen in the observed frames; frames of other segments
    (before a re-entry, after a respawn) count as absent.
    """
    b, s = env_start[0], env_start[1]
    n = data["visible"].shape[-1]
    take = lambda x: jax.lax.dynamic_slice(x, (b, s) + (0,) * (x.ndim - 2), (1, WINDOW) + x.shape[2:])[0]  # noqa: E731
    pos, vis, seg, robot = take(data["human_pos"]), take(data["visible"]), take(data["seg"]), take(data["robot_pos"])
    seg = seg.astype(jnp.int32)
    ref = jnp.max(jnp.where(vis[:OBS_LEN], seg[:OBS_LEN], -1), axis=0)
    present = vis & (seg == ref[None, :])  # (10, N)
    filler = robot[:OBS_LEN, None, :] + FILLER_OFFSET
    obs = jnp.where(present[:OBS_LEN, :, None], pos[:OBS_LEN], jnp.broadcast_to(filler, (OBS_LEN, n, 2)))
    return Batch(
        positions=jnp.swapaxes(obs, 0, 1),
        visible=present[:OBS_LEN].T,
        target=jnp.swapaxes(pos[OBS_LEN:], 0, 1),
        target_valid=(present[OBS_LEN:] & present[OBS_LEN - 1 : -1]).T,
    )


def device_arrays(arrays: dict) -> dict:
    return {k: jnp.asarray(arrays[k]) for k in ("robot_pos", "human_pos", "visible", "seg")}
