"""`Navigator`: a trained policy driven by what a robot has (its pose and velocity, the goal, detected humans),
returning a velocity command in the robot's own kinematics.

It builds the observation as the env does (`tgrf_jax.env.sensing.observe`): humans beyond the sensor range
(edge to edge) are left out, the rest sorted by centre distance and cut to the network's rows, positions and
predictions relative to the robot, padding rows zero and masked. Predictions are made from the detections as
the env makes them from its humans: constant velocity from each detection's velocity, or the learned GST model
from a 5-frame history kept per tracked human (which is why gst needs track ids). Ground-truth predictions need
the crowd's true future and are refused.

A policy trained with a 2-D LiDAR (env.lidar_rays = R > 0) also needs the robot's scan each decision: R ranges in
metres, ray 0 along the robot's heading, counter-clockwise (the body frame of a 2-D laser scanner), as the env's
`Obs.lidar`. Ranges above the sensor range are clipped to it, non-finite ones (a driver's "no return" or a fault)
become the sensor range and are counted like dropped detections. The env keeps a holonomic robot's heading at
pi/2, so for a holonomic policy the scan is turned from the robot's real heading to that one (a circular shift
with linear interpolation between rays, `tgrf_jax.policies.nets.frames.rotate_scan`'s rule; exact when the
headings differ by whole rays). A policy without a LiDAR refuses a scan rather than ignore it: a caller passing
one expects it to be used.

Every input is checked against what float32 and physics allow before anything is computed (docs/deployment.md):
the caller's own values (the robot's state, the goal, the scan's shape) are refused with a ValueError naming the
argument; a detection, which a tracker can get wrong, is dropped and counted instead. A network output that is not
finite raises `NonFiniteDecision` and changes nothing: the recurrent state and the GST history stay as they were.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Mapping, Sequence

import numpy as np

from tgrf_jax.config import MAX_BODY_RADIUS, ConfigError
from tgrf_jax.deploy.policy import PolicyStep
from tgrf_jax.deploy.runtimes import make_runtime
from tgrf_jax.deploy.source import PolicySource, load_source
from tgrf_jax.pretrained import check_params

log = logging.getLogger(__name__)

HOLONOMIC_HEADING = np.float32(np.pi / 2)  # what the env keeps a holonomic robot's heading at (its training input)
# Positions (robot, goal, detections) within +-POSITION_BOUND m of the map origin on each axis: there float32, the
# network's number type, still resolves a millimetre, and no square of a distance comes near its overflow.
POSITION_BOUND = 1.0e4
# The robot never drives faster than v_max (the env scales or clips every command to it); a measured speed above
# this many times v_max is a unit or frame mistake, not odometry noise.
ROBOT_SPEED_FACTOR = 1.5
# Reduced headings lie in [HEADING_CENTRE - pi, HEADING_CENTRE + pi): the turn around the heading every simulated
# robot starts with, where the env's unwrapped headings mostly are (a goal-frame network sees only differences).
HEADING_CENTRE = np.pi / 2
HUMAN_SPEED_MAX = 12.5  # m/s, above any person's sprint: a faster detection is a tracking error
HUMAN_RADIUS_MAX = MAX_BODY_RADIUS  # m, the largest body radius a config accepts (a human's is 0.2 .. 0.5 m)


class NonFiniteDecision(RuntimeError):
    """The network's output for this reading was not finite; the Navigator's state is as before the call."""


@dataclasses.dataclass(frozen=True)
class RobotState:
    """The robot's pose and velocity in the world (map) frame: metres, radians counter-clockwise from x, m/s."""

    x: float
    y: float
    heading: float
    vx: float
    vy: float


@dataclasses.dataclass(frozen=True)
class Detection:
    """A detected human: world position (m), velocity (m/s), optional radius (m) and optional track id."""

    position: Sequence[float]
    velocity: Sequence[float]
    radius: float | None = None
    id: object = None


@dataclasses.dataclass(frozen=True)
class Decision:
    """What `Navigator.act` returns (always finite: a non-finite network output raises `NonFiniteDecision`).

    command: (2,) float; holonomic: (vx, vy) in m/s, world frame, norm <= v_max; unicycle: (v, omega) in m/s and
    rad/s, v within +-v_max and omega = dtheta / dt with dtheta within the per-step limit.
    action: (2,) the network's raw output (what the env would be given).
    """

    command: np.ndarray
    action: np.ndarray
    num_detected: int  # detections passed in
    num_dropped: int  # of those, dropped as implausible (a non-finite number, or beyond the bounds of the module)
    num_in_range: int  # within the sensor range
    num_used: int  # rows fed to the network (the nearest, at most its capacity)
    num_lidar_invalid: int = 0  # LiDAR rays with a non-finite range, read as the sensor range (LiDAR policies)


def _vector(value, n: int, name: str, what: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be {n} numbers ({what}); got {value!r}") from None
    if arr.shape != (n,):
        raise ValueError(f"{name} must be {n} numbers ({what}); got shape {arr.shape}: {value!r}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite ({what}); got {arr.tolist()}")
    return arr


def rotate_scan(scan: np.ndarray, angle: float) -> np.ndarray:
    """NumPy twin of `tgrf_jax.policies.nets.frames.rotate_scan` for one scan: the scan (R,) re-expressed in a
    frame turned by `angle` rad counter-clockwise (out[j] = scan at ray j + angle R / (2 pi), linearly
    interpolated between neighbouring rays, indices modulo R)."""
    r = scan.shape[0]
    shift = float(np.mod(angle * r / (2.0 * math.pi), r))
    whole = round(shift)
    if abs(shift - whole) < 1e-3:  # as frames.rotate_scan: whole ray steps shift exactly
        shift = float(whole)
    base = math.floor(shift)
    frac = np.float32(shift - base)
    idx = (np.arange(r) + base) % r
    lo, hi = scan[idx], scan[(idx + 1) % r]
    return (lo + frac * (hi - lo)).astype(np.float32)


def _within_map(xy: np.ndarray, name: str) -> None:
    if np.max(np.abs(xy)) > POSITION_BOUND:
        raise ValueError(
            f"{name} ({xy[0]:g}, {xy[1]:g}) m is beyond +-{POSITION_BOUND:g} m of the map origin, where float32 "
            "loses its millimetre resolution: positions are in metres; re-centre the map frame near the robot"
        )


def reduce_heading(heading: float) -> float:
    """`heading` rad modulo 2 pi, within [HEADING_CENTRE - pi, HEADING_CENTRE + pi)."""
    return float(np.mod(heading - HEADING_CENTRE + math.pi, 2.0 * math.pi) + HEADING_CENTRE - math.pi)


def _robot_state(state, v_max: float) -> np.ndarray:
    """(x, y, heading, vx, vy) from a RobotState, a {'pose', 'velocity'} mapping or 5 numbers, checked (see the
    module's bounds) and with the heading reduced modulo 2 pi."""
    if isinstance(state, RobotState):
        state = (state.x, state.y, state.heading, state.vx, state.vy)
    if isinstance(state, Mapping):
        unknown = set(state) - {"pose", "velocity"}
        if unknown or "pose" not in state or "velocity" not in state:
            raise ValueError(
                f"robot_state mapping needs keys 'pose' (x, y, heading) and 'velocity' (vx, vy); got {sorted(state)}"
            )
        pose = _vector(state["pose"], 3, "robot_state pose", "x m, y m, heading rad")
        vel = _vector(state["velocity"], 2, "robot_state velocity", "vx, vy in m/s, world frame")
        rs = np.concatenate([pose, vel])
    else:
        rs = _vector(state, 5, "robot_state", "x m, y m, heading rad, vx m/s, vy m/s")
    _within_map(rs[0:2], "robot_state position")
    speed = math.hypot(rs[3], rs[4])
    if speed > ROBOT_SPEED_FACTOR * v_max:
        raise ValueError(
            f"robot_state velocity ({rs[3]:g}, {rs[4]:g}) m/s: its speed {speed:g} m/s is over {ROBOT_SPEED_FACTOR:g} "
            f"x v_max = {ROBOT_SPEED_FACTOR * v_max:g} m/s, faster than the robot drives: velocities are in m/s, "
            "world frame"
        )
    rs[2] = reduce_heading(rs[2])
    return rs


class _GstTracker:
    """The learned predictor's 5-frame history, one slot per tracked human, as the env keeps it per human index
    (`tgrf_jax.env.gst.history`): a frame holds the human's position where it was in range, else the env's
    filler (robot position + 15 m per axis)."""

    def __init__(self, env_config, slots: int):
        import jax

        from tgrf_jax.env.gst import history, weights
        from tgrf_jax.env.gst.model import OBS_LEN, predict

        self.obs_len, self.filler = OBS_LEN, np.float32(history.FILLER_OFFSET)
        self.slots = slots
        self.weights = weights.for_env(env_config)
        self._predict = jax.jit(lambda w, pos, vis: predict(w, pos, vis).means)
        self.reset()

    def reset(self):
        self.positions = None  # (slots, OBS_LEN, 2) float32
        self.visible = None  # (slots, OBS_LEN) bool
        self.robot_hist = None  # (OBS_LEN, 2) the robot position of each frame (the filler's origin)
        self.owner: list = [None] * self.slots
        self.last_seen = np.full(self.slots, -(10**9))
        self.frame = 0

    def _slots_for(self, ids) -> list[int]:
        index = {owner: s for s, owner in enumerate(self.owner) if owner is not None}
        taken, out = set(), []
        for tid in ids:
            if tid in index:
                out.append(index[tid])
                taken.add(index[tid])
                continue
            out.append(None)
        for i, tid in enumerate(ids):
            if out[i] is not None:
                continue
            free = [
                s
                for s in range(self.slots)
                if s not in taken and (self.owner[s] is None or self.frame - self.last_seen[s] >= self.obs_len)
            ]
            # An integer id in range keeps its own slot, so ids equal to the env's human indices lay the
            # history out exactly as the env does.
            if isinstance(tid, (int, np.integer)) and 0 <= tid < self.slots and tid in free:
                slot = int(tid)
            elif free:
                slot = free[0]
            else:  # every slot holds a human seen in the last frames: the longest unseen one makes room
                slot = min((s for s in range(self.slots) if s not in taken), key=lambda s: self.last_seen[s])
                self._forget(slot)
            if self.owner[slot] is not None and self.owner[slot] != tid:
                self._forget(slot)
            self.owner[slot] = tid
            taken.add(slot)
            out[i] = slot
        return out

    def snapshot(self) -> tuple:
        """Everything `predictions` changes, for `restore` (arrays copied: `_forget` writes into them)."""
        arrays = (self.positions, self.visible, self.robot_hist)
        return (
            *(None if a is None else a.copy() for a in arrays),
            list(self.owner),
            self.last_seen.copy(),
            self.frame,
        )

    def restore(self, saved: tuple) -> None:
        self.positions, self.visible, self.robot_hist, self.owner, self.last_seen, self.frame = saved

    def _forget(self, slot: int):
        if self.positions is not None:
            self.positions[slot] = self.robot_hist + self.filler
            self.visible[slot] = False

    def predictions(self, robot_pos: np.ndarray, pos: np.ndarray, ids) -> np.ndarray:
        """World predictions (M, 5, 2) for the M humans in range at `pos`, after adding this frame."""
        slots = self._slots_for(ids)
        frame = np.broadcast_to(robot_pos + self.filler, (self.slots, 2)).copy()
        seen = np.zeros(self.slots, bool)
        frame[slots] = pos
        seen[slots] = True
        self.last_seen[slots] = self.frame
        if self.positions is None:
            self.positions = np.repeat(frame[:, None], self.obs_len, axis=1)
            self.visible = np.zeros((self.slots, self.obs_len), bool)
            self.visible[:, -1] = seen
            self.robot_hist = np.repeat(robot_pos[None], self.obs_len, axis=0)
            # As the env at an episode start: no human is seen in two frames, so all hold their position.
            means = np.repeat(self.positions[:, -1:], self.obs_len, axis=1)
        else:
            self.positions = np.concatenate([self.positions[:, 1:], frame[:, None]], axis=1)
            self.visible = np.concatenate([self.visible[:, 1:], seen[:, None]], axis=1)
            self.robot_hist = np.concatenate([self.robot_hist[1:], robot_pos[None]])
            means = np.asarray(self._predict(self.weights, self.positions, self.visible))
        self.frame += 1
        return means[slots]


class Navigator:
    """Drive a robot with a trained policy.

        nav = Navigator("table1-const_vel-tgrf")         # a pretrained name, a run directory or a tgrf-export dir
        nav.reset()                                       # at the start of every trip
        decision = nav.act((x, y, heading, vx, vy), (gx, gy), [Detection((hx, hy), (hvx, hvy), 0.3)])
        vx, vy = decision.command                         # unicycle policies: v, omega

    runtime: 'jax' (the network jitted), 'onnx' or 'stablehlo' (the files of a tgrf-export directory).
    default_human_radius: used for detections without a radius (default: the env's largest human radius, so a
    human is taken as in range no later than the env would).
    """

    def __init__(
        self,
        source: str | PolicySource,
        *,
        runtime: str = "jax",
        step: int | None = None,
        threads: int = 1,
        default_human_radius: float | None = None,
    ) -> None:
        if isinstance(source, PolicySource):  # load_source checks what it loads; a source built in memory too
            check_params(source.config, source.params, "the policy's parameters")
        self.source = source if isinstance(source, PolicySource) else load_source(source, step=step)
        env = self.source.config.env
        if env.predictor == "truth":
            raise ConfigError(
                "this policy was trained on ground-truth predictions (env.predictor = 'truth'), "
                "the crowd's true future that only a simulator has; deploy a const_vel, gst or none "
                "policy instead"
            )
        self.env_config = env
        self.kinematics = env.kinematics
        self.dt = float(env.dt)
        self.capacity = env.num_humans
        self.lidar_rays = env.lidar_rays
        self.runtime_name = runtime
        self._step_info = PolicyStep(self.source.config, self.source.params)
        self._run = make_runtime(self.source, runtime, threads)
        self._k = env.pred_horizon if env.uses_predictions else 0
        self._steps = (np.arange(1, self._k + 1, dtype=np.float32) * np.float32(env.dt))[None, :, None]
        radius = env.human_radius_max if default_human_radius is None else default_human_radius
        if not (math.isfinite(radius) and radius >= 0):
            raise ConfigError(f"default_human_radius = {radius} must be a finite radius >= 0 m")
        self.default_human_radius = float(radius)
        self._gst = _GstTracker(env, self.capacity) if env.predictor == "gst" else None
        self.dropped_total = 0
        self.lidar_invalid_total = 0
        self.reset()

    def __repr__(self) -> str:
        lidar = f", lidar_rays={self.lidar_rays}" if self.lidar_rays else ""
        return (
            f"Navigator({self.source.config.network.name}/{self.source.config.network.size}, "
            f"{self.kinematics}, predictor={self.env_config.predictor!r}{lidar}, runtime={self.runtime_name!r})"
        )

    def reset(self) -> None:
        """Start a trip: zero recurrent state, empty prediction history."""
        self.state = np.zeros(self._step_info.state_size, np.float32)
        if self._gst is not None:
            self._gst.reset()

    # ------------------------------------------------------------------------------------------ parsing

    def _detections(self, humans, ids):
        """(pos (M, 2), vel (M, 2), radius (M,), ids or None, detected, dropped by reason) with implausible rows
        removed: a non-finite number, a position beyond the map bound, a speed above HUMAN_SPEED_MAX or a radius
        outside [0, HUMAN_RADIUS_MAX]."""
        if humans is None:
            humans = []
        if isinstance(humans, np.ndarray) or (
            isinstance(humans, Sequence) and humans and not isinstance(humans[0], (Detection, Mapping))
        ):
            arr = np.asarray(humans, dtype=np.float64)
            if arr.ndim != 2 or arr.shape[1] not in (4, 5):
                raise ValueError(
                    f"humans as an array must be (M, 4) [x, y, vx, vy] or (M, 5) [x, y, vx, vy, "
                    f"radius] in m and m/s; got shape {arr.shape}"
                )
            pos, vel = arr[:, 0:2], arr[:, 2:4]
            radius = arr[:, 4] if arr.shape[1] == 5 else np.full(len(arr), self.default_human_radius)
        else:
            pos, vel, radius, own_ids = [], [], [], []
            for i, h in enumerate(humans):
                if isinstance(h, Mapping):
                    unknown = set(h) - {"position", "velocity", "radius", "id"}
                    if unknown or "position" not in h:
                        raise ValueError(
                            f"humans[{i}] needs 'position' (and 'velocity', optional 'radius', 'id'); "
                            f"got keys {sorted(h)}"
                        )
                    h = Detection(h["position"], h.get("velocity", (0.0, 0.0)), h.get("radius"), h.get("id"))
                elif not isinstance(h, Detection):
                    raise ValueError(f"humans[{i}] must be a Detection or a mapping; got {type(h).__name__}")
                p = np.asarray(h.position, np.float64)
                v = np.asarray(h.velocity, np.float64)
                if p.shape != (2,) or v.shape != (2,):
                    raise ValueError(
                        f"humans[{i}]: position and velocity must be 2 numbers each (m, m/s); got "
                        f"shapes {p.shape} and {v.shape}"
                    )
                pos.append(p)
                vel.append(v)
                radius.append(self.default_human_radius if h.radius is None else float(h.radius))
                own_ids.append(h.id)
            pos = np.reshape(pos, (-1, 2))
            vel = np.reshape(vel, (-1, 2))
            radius = np.asarray(radius, np.float64)
            if ids is None and any(t is not None for t in own_ids):
                ids = own_ids
        detected = len(pos)
        if ids is not None:
            ids = list(ids)
            if len(ids) != detected:
                raise ValueError(f"ids has {len(ids)} entries for {detected} humans")
        finite = np.isfinite(pos).all(1) & np.isfinite(vel).all(1) & np.isfinite(radius)
        with np.errstate(invalid="ignore", over="ignore"):  # the non-finite rows are dropped by `finite` anyway
            reasons = {
                "a non-finite number": ~finite,
                f"a position beyond +-{POSITION_BOUND:g} m": finite & (np.abs(pos).max(1, initial=0) > POSITION_BOUND),
                f"a speed over {HUMAN_SPEED_MAX:g} m/s": finite & (np.hypot(vel[:, 0], vel[:, 1]) > HUMAN_SPEED_MAX),
                f"a radius outside [0, {HUMAN_RADIUS_MAX:g}] m": finite & ((radius < 0) | (radius > HUMAN_RADIUS_MAX)),
            }
        bad = np.logical_or.reduce(list(reasons.values())) if detected else np.zeros(0, bool)
        dropped = {reason: int(rows.sum()) for reason, rows in reasons.items() if rows.any()}
        if bad.any():
            keep = np.flatnonzero(~bad)
            pos, vel, radius = pos[keep], vel[keep], radius[keep]
            ids = [ids[i] for i in keep] if ids is not None else None
        return pos, vel, radius, ids, detected, dropped

    def _scan(self, lidar, heading: float):
        """The policy's `lidar` input from a robot's scan: (ranges (R,) float32, rays that were not finite)."""
        r, max_range = self.lidar_rays, float(self.env_config.sensor_range)
        frame = (
            "metres, ray 0 along the robot's heading, counter-clockwise (the scanner's body frame), "
            f"ray k at heading + 2 pi k / {r}"
        )
        if lidar is None:
            raise ValueError(f"lidar: this policy reads a {r}-ray 2-D LiDAR scan; pass lidar = {r} ranges in {frame}")
        try:
            scan = np.asarray(lidar, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"lidar must be {r} numbers (ranges in {frame}); got {lidar!r}") from None
        if scan.ndim != 1 or scan.shape[0] != r:
            got = f"{scan.shape[0]} rays" if scan.ndim == 1 else f"shape {scan.shape}"
            raise ValueError(
                f"lidar has {got} but this policy was trained on {r} rays (ranges in {frame}); "
                f"resample the scan to {r} rays"
            )
        finite = np.isfinite(scan)
        bad = np.flatnonzero(finite & (scan < 0))
        if len(bad):
            raise ValueError(f"lidar[{bad[0]}] = {scan[bad[0]]}: a range must be >= 0 m")
        invalid = int(r - finite.sum())
        scan = np.minimum(np.where(finite, scan, max_range), max_range).astype(np.float32)
        if self.kinematics == "holonomic":
            # the policy's body frame is the env's: heading pi/2 (see the module docstring)
            scan = rotate_scan(scan, float(HOLONOMIC_HEADING) - heading)
        return scan, invalid

    # ------------------------------------------------------------------------------------------ observation

    def observation(self, robot_state, goal, humans, lidar=None, *, ids=None) -> tuple[tuple, tuple]:
        """The network's inputs (robot_node, robot_vel, humans, human_mask[, lidar]) for this situation, plus the
        counts (detected, dropped, in range, used[, LiDAR rays not finite]); the bracketed parts exactly for a policy
        with a LiDAR. Advances the GST history: call it once per decision, or use `act`."""
        obs, counts, _, _ = self._observe(robot_state, goal, humans, lidar, ids)
        return obs, counts

    def _observe(self, robot_state, goal, humans, lidar, ids):
        """(inputs, counts, robot state (5,), detections dropped by reason) as `observation`. Every check comes
        before the GST history advances, so a refused reading changes nothing."""
        env = self.env_config
        v_max = np.float32(env.robot_v_max)
        rs = _robot_state(robot_state, float(v_max))
        if self.lidar_rays:
            scan, invalid = self._scan(lidar, float(rs[2]))
        elif lidar is not None:
            raise ValueError(
                "lidar: this policy has no scan input (it was trained with env.lidar_rays = 0); turn "
                "the scan into human detections (positions and velocities) and pass those as `humans`"
            )
        goal = _vector(goal, 2, "goal", "gx, gy in m, world frame")
        _within_map(goal, "goal")
        pos, vel, radius, ids, detected, dropped = self._detections(humans, ids)
        if self._gst is not None and ids is None and len(pos):
            raise ValueError(
                "the gst predictor follows each human over 5 frames: give every detection an id "
                "(Detection(..., id=track_id) or act(..., ids=[...]))"
            )

        f32 = np.float32
        robot_pos = rs[0:2].astype(f32)
        rel = pos.astype(f32) - robot_pos
        dist = np.sqrt(np.square(rel[:, 0]) + np.square(rel[:, 1]))
        edge = dist - f32(env.robot_radius) - radius.astype(f32)
        in_range = np.flatnonzero(edge <= f32(env.sensor_range))
        order = in_range[np.argsort(dist[in_range], kind="stable")]
        used = order[: self.capacity]

        feats = [rel[used]]
        if self._k:
            if self._gst is not None:
                pred = self._gst.predictions(robot_pos, pos.astype(f32)[used], [ids[i] for i in used])
            else:
                pred = pos.astype(f32)[used, None, :] + self._steps * vel.astype(f32)[used, None, :]
            feats.append((pred.astype(f32) - robot_pos).reshape(len(used), 2 * self._k))
        elif self._gst is not None:
            self._gst.predictions(robot_pos, pos.astype(f32)[used], [ids[i] for i in used])
        rows = np.zeros((self.capacity, self._step_info.obs_human_dim), f32)
        rows[: len(used)] = np.concatenate(feats, axis=1)
        mask = np.zeros(self.capacity, f32)
        mask[: len(used)] = 1.0
        heading = f32(rs[2]) if self.kinematics == "unicycle" else HOLONOMIC_HEADING
        robot_node = np.array([robot_pos[0], robot_pos[1], env.robot_radius, goal[0], goal[1], v_max, heading], f32)
        robot_vel = rs[3:5].astype(f32)
        counts = (detected, detected - len(pos), len(in_range), len(used))
        if self.lidar_rays:
            return (robot_node, robot_vel, rows, mask, scan), counts + (invalid,), rs, dropped
        return (robot_node, robot_vel, rows, mask), counts, rs, dropped

    # ------------------------------------------------------------------------------------------ decision

    def act(self, robot_state, goal, humans=None, lidar=None, *, ids=None) -> Decision:
        """One decision. robot_state: RobotState, {'pose': (x, y, heading), 'velocity': (vx, vy)} or
        (x, y, heading, vx, vy), world frame, m / rad / m/s. goal: (gx, gy) m. humans: Detections, mappings with
        'position', 'velocity' and optional 'radius' / 'id', or an (M, 4|5) array [x, y, vx, vy(, radius)].
        ids: track ids (gst needs them). lidar: for a policy trained with a LiDAR (env.lidar_rays = R > 0,
        `self.lidar_rays`), required: the R ranges in metres, ray 0 along the robot's heading, counter-clockwise;
        ranges above the sensor range are clipped to it, non-finite ones read as the sensor range and counted
        (`Decision.num_lidar_invalid`, logged). A policy without a LiDAR (every shipped one) refuses a scan.

        Refused with a ValueError naming the argument: a robot position or goal beyond +-POSITION_BOUND m, a robot
        speed over ROBOT_SPEED_FACTOR x v_max, a non-finite number in them (headings are reduced modulo 2 pi).
        Dropped, counted in `Decision.num_dropped` and logged: detections with a non-finite number, a position
        beyond the bound, a speed over HUMAN_SPEED_MAX or a radius outside [0, HUMAN_RADIUS_MAX]. A network output
        that is not finite raises NonFiniteDecision. A call that raises leaves the recurrent state and the GST
        history as they were, so the next reading is decided as if the refused one had never come."""
        saved = self._gst.snapshot() if self._gst is not None else None
        obs, counts, rs, dropped = self._observe(robot_state, goal, humans, lidar, ids)
        detected, num_dropped, in_range, used = counts[:4]
        invalid = counts[4] if self.lidar_rays else 0
        action, new_state = self._run(*obs, self.state)
        action = np.asarray(action, np.float32)
        new_state = np.asarray(new_state, np.float32)
        if not (np.isfinite(action).all() and np.isfinite(new_state).all()):
            if saved is not None:
                self._gst.restore(saved)
            raise NonFiniteDecision(
                f"the policy's output for this reading is not finite (action {action.tolist()}, "
                f"{int(new_state.size - np.isfinite(new_state).sum())} non-finite recurrent state values); no "
                "command: the recurrent state and the prediction history are left as they were, so stop the robot "
                "(or hold a safe command) and decide again on the next reading"
            )
        self.state = new_state
        if num_dropped:
            self.dropped_total += num_dropped
            log.warning(
                "dropped %d of %d detections (%s; %d so far)",
                num_dropped,
                detected,
                ", ".join(f"{n} with {reason}" for reason, n in dropped.items()),
                self.dropped_total,
            )
        if invalid:
            self.lidar_invalid_total += invalid
            log.warning(
                "%d of %d LiDAR rays had a non-finite range, read as the sensor range %g m (%d so far)",
                invalid,
                self.lidar_rays,
                self.env_config.sensor_range,
                self.lidar_invalid_total,
            )
        return Decision(self._command(action, rs), action, detected, num_dropped, in_range, used, invalid)

    def _command(self, action: np.ndarray, rs: np.ndarray) -> np.ndarray:
        env = self.env_config
        a = action.astype(np.float64)
        if self.kinematics == "holonomic":
            speed = math.hypot(a[0], a[1])
            return (a * min(1.0, env.robot_v_max / max(speed, 1e-12))).astype(np.float32)
        dv = np.clip(a[0], env.unicycle_dv_min, env.unicycle_dv_max)
        dtheta = np.clip(a[1], -env.unicycle_dtheta_max, env.unicycle_dtheta_max)
        forward = rs[3] * math.cos(rs[2]) + rs[4] * math.sin(rs[2])
        v = np.clip(forward + dv, -env.robot_v_max, env.robot_v_max)
        return np.array([v, dtheta / env.dt], np.float32)
