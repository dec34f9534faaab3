"""Shared test helpers: small environments and hand-built states."""

import os
import signal
import threading

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

from tgrf_jax import CrowdNavEnv
from tgrf_jax.config import TrainConfig
from tgrf_jax.env import EnvState, Humans, Robot, stuck
from tgrf_jax.env import obstacles as obstacles_lib


def signal_this_thread(sig: int) -> None:
    """Send `sig` to the calling thread: its handler has run when this returns. (A signal sent to the process
    may be taken by another of its threads, XLA's or JAX's, and reach Python's handler only later.)"""
    signal.pthread_kill(threading.get_ident(), sig)


def cpu_devices_env(n: int) -> dict:
    """XLA_FLAGS for a subprocess with n CPU devices, keeping the suite's other XLA settings (tests/conftest.py)."""
    return {"XLA_FLAGS": f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={n}"}


def tiny_config(**sections) -> TrainConfig:
    """A training config that compiles and runs in seconds: 8 envs x 8 steps, 4 updates, no humans, small MLP.
    `sections` update its sections, e.g. tiny_config(ppo={"num_steps": 12})."""
    base = {
        "env": {"num_humans": 0, "predictor": "none"},
        "network": {"name": "mlp", "size": "small"},
        "ppo": {
            "num_envs": 8,
            "num_steps": 8,
            "total_steps": 8 * 8 * 4,
            "update_epochs": 2,
            "num_minibatches": 2,
            "num_shards": 1,
        },
    }
    for k, v in sections.items():
        base.setdefault(k, {}).update(v)
    return TrainConfig.from_dict(base)


def make_env(**overrides) -> CrowdNavEnv:
    reward = overrides.pop("reward", "tgrf")
    return CrowdNavEnv(overrides, reward)


def hand_state(
    robot_pos, robot_goal, human_pos, human_vel=None, human_goal=None, radius=0.3, v_pref=1.0, neighbor_dist=10.0
):
    """An EnvState with the robot and humans exactly where a test wants them."""
    human_pos = jnp.asarray(human_pos, jnp.float32).reshape(-1, 2)
    n = human_pos.shape[0]
    human_vel = jnp.zeros((n, 2)) if human_vel is None else jnp.asarray(human_vel, jnp.float32)
    # Default goals lie far away so no human counts as arrived (and respawns) during a short test.
    human_goal = human_pos + jnp.array([0.0, 100.0]) if human_goal is None else jnp.asarray(human_goal, jnp.float32)
    robot = Robot(
        pos=jnp.asarray(robot_pos, jnp.float32),
        vel=jnp.zeros(2),
        goal=jnp.asarray(robot_goal, jnp.float32),
        heading=jnp.float32(jnp.pi / 2),
        speed=jnp.float32(0.0),
    )
    humans = Humans(
        pos=human_pos,
        vel=human_vel,
        goal=human_goal,
        radius=jnp.full((n,), radius, jnp.float32),
        v_pref=jnp.full((n,), v_pref, jnp.float32),
        active=jnp.ones((n,), bool),
    )
    return EnvState(
        robot=robot,
        humans=humans,
        goal_dist_ref=jnp.linalg.norm(robot.pos - robot.goal),
        step_count=jnp.zeros((), jnp.int32),
        orca_neighbor_dist=jnp.float32(neighbor_dist),
        scenario=jnp.zeros((), jnp.int32),
        obstacles=obstacles_lib.empty(),
        obstacles_dropped=jnp.zeros((), jnp.int32),
        progress=stuck.fresh(humans),
    )


def rollout(env, key, params, n_steps, policy_fn):
    """Jitted scan of `n_steps` auto-reset steps with actions from policy_fn(obs); returns stacked outputs."""

    def body(carry, k):
        obs, state = carry
        action = policy_fn(obs)
        obs, state, reward, term, trunc, info = env.step(k, state, action, params)
        return (obs, state), (state, reward, term, trunc, info)

    @jax.jit
    def run(key):
        k0, k1 = jax.random.split(key)
        obs, state = env.reset(k0, params)
        return jax.lax.scan(body, (obs, state), jax.random.split(k1, n_steps))[1]

    return run(key)


def to_goal(obs):
    offset = obs.robot_node[3:5] - obs.robot_node[:2]
    return offset / jnp.maximum(jnp.linalg.norm(offset), 1e-6)


# jax.monitoring events: a function traced to a jaxpr, and a program compiled by XLA (cache misses of jit).
TRACE_EVENT = "/jax/core/compile/jaxpr_trace_duration"
COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"


class CompileCounter:
    """Counts jaxpr traces and XLA backend compilations while active (a context manager):

    with CompileCounter() as c:
        ...
    assert c.compiles == 0
    """

    def __enter__(self):
        self.traces = self.compiles = 0
        jax.monitoring.register_event_duration_secs_listener(self._listener)
        return self

    def _listener(self, event: str, duration: float, **_):
        if event == TRACE_EVENT:
            self.traces += 1
        elif event == COMPILE_EVENT:
            self.compiles += 1

    def __exit__(self, *exc):
        jax.monitoring.unregister_event_duration_listener(self._listener)
        return False


def _read_arrays(item_dir):
    with ocp.PyTreeCheckpointer() as checkpointer:
        return jax.tree_util.tree_leaves(checkpointer.restore(item_dir))


def flip_a_bit(step_dir):
    """Flip one bit of a checkpoint step's largest array data file so that the step still reads, with other
    values: what a failing disk does unnoticed, so only the step's checksum can catch it. Returns that file.

    The file holds the arrays' compressed chunks in an order that varies from one save to the next, and a bit
    flipped in a chunk's header makes the step unreadable instead; so bits are tried from the middle on until one
    changes values and leaves the step readable."""
    item = step_dir / "default"
    before = _read_arrays(item)
    data = max((p for p in item.rglob("*") if p.is_file() and p.parent.name == "d"), key=lambda p: p.stat().st_size)
    raw = bytearray(data.read_bytes())
    for offset in range(len(raw) // 2, len(raw), 61):
        raw[offset] ^= 0x10
        data.write_bytes(bytes(raw))
        try:
            after = _read_arrays(item)
        except Exception:  # unreadable: try the next bit
            after = None
        if after is not None and any(not np.array_equal(a, b) for a, b in zip(before, after)):
            return data
        raw[offset] ^= 0x10
    data.write_bytes(bytes(raw))
    raise AssertionError(f"no bit of {data} could be flipped without making the step unreadable")


def write_catalogue_recordings(data_dir) -> None:
    """Small stand-ins for every file of the ETH/UCY catalogue under `data_dir`, each at its catalogue path, in
    its format and frame spacing: three people crossing for 20 s, annotated every 0.4 s (per file a little
    shifted, so the files differ)."""
    import pathlib

    from tgrf_jax.pedestrians import ETH_UCY

    walkers = (((-10.0, 0.0), (1.2, 0.0)), ((0.0, -10.0), (0.0, 1.0)), ((10.0, 3.0), (-1.0, 0.1)))
    for i, entry in enumerate(ETH_UCY):
        spf = entry.seconds_per_frame
        every = round(0.4 / spf)
        frames = range(0, round(20.0 / spf) + 1, every)
        lines = []
        for f in frames:
            t = f * spf
            for pid, ((x0, y0), (vx, vy)) in enumerate(walkers, start=1):
                x, y = x0 + vx * t + 0.1 * i, y0 + vy * t
                if entry.format == "obsmat":  # frame id x z y vx vz vy, scientific notation, CRLF
                    lines.append("".join(f"{v:15.7e}" for v in (f, pid, x, 0.0, y, vx, 0.0, vy)) + "\r\n")
                else:
                    lines.append(f"{f:.1f}\t{pid:.1f}\t{x:.10g}\t{y:.10g}\n")
        path = pathlib.Path(data_dir) / entry.name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes("".join(lines).encode())
