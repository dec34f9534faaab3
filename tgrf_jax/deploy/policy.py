"""One policy decision as a plain function of flat arrays.

The env's observation is a pytree and the network's recurrent state a dict whose layout depends on the network;
neither travels well to another runtime. `PolicyStep` fixes one flat, unbatched signature

    (robot_node (7,), robot_vel (2,), humans (N, D), human_mask (N,), state (S,)) -> (action (2,), new_state (S,))

all float32, world frame (the network's own frame change happens inside), the action being the Gaussian's mean
(the deterministic policy `tgrf-eval` scores). A policy trained with a 2-D LiDAR (env.lidar_rays = R > 0) takes
one more input before the state, `lidar` (R,): ranges in metres in the robot's body frame (ray k at angle
robot_node's heading + 2 pi k / R, counter-clockwise), values above the sensor range read as the sensor range and
NaN as "no return" (the sensor range). The exported ONNX file and StableHLO artifact are this function.
"""

from __future__ import annotations

import json
import pathlib
from collections.abc import Callable

import numpy as np

from tgrf_jax.config import ConfigError, TrainConfig

INTERFACE_FILE = "interface.json"
ONNX_FILE = "policy.onnx"
STABLEHLO_FILE = "policy.stablehlo"
INPUT_NAMES = ("robot_node", "robot_vel", "humans", "human_mask", "state")  # a policy without a LiDAR
LIDAR_INPUT_NAMES = ("robot_node", "robot_vel", "humans", "human_mask", "lidar", "state")  # with one
OUTPUT_NAMES = ("action", "new_state")
FORMAT_FILES = {"onnx": ONNX_FILE, "stablehlo": STABLEHLO_FILE}  # export format -> its file
FORMATS = tuple(FORMAT_FILES)


class PolicyStep:
    """The single-decision function of a trained network (see the module docstring) and its sizes."""

    def __init__(self, config: TrainConfig, params: dict) -> None:
        import jax

        from tgrf_jax.policies import make_network_for

        self.config = config
        self.net = make_network_for(config)
        self.params = params
        self.num_humans = config.env.num_humans
        self.obs_human_dim = config.env.obs_human_dim
        self.lidar_rays = config.env.lidar_rays
        self.lidar_range = float(config.env.sensor_range)
        self.input_names = LIDAR_INPUT_NAMES if self.lidar_rays else INPUT_NAMES
        carry = self.net.initialize_carry(1)
        self._leaves, self._treedef = jax.tree_util.tree_flatten(carry)
        self._sizes = [int(np.prod(leaf.shape[1:])) for leaf in self._leaves]
        self.state_size = sum(self._sizes)

    def input_shapes(self) -> list[tuple[int, ...]]:
        """Shapes of the inputs, in the order of `input_names`."""
        lidar = [(self.lidar_rays,)] if self.lidar_rays else []
        return [(7,), (2,), (self.num_humans, self.obs_human_dim), (self.num_humans,), *lidar, (self.state_size,)]

    def zeros(self) -> list[np.ndarray]:
        return [np.zeros(s, np.float32) for s in self.input_shapes()]

    def state_from_carry(self, carry) -> np.ndarray:
        """The flat state of row 0 of a batched carry (the env-side recurrent state, for tests and replay)."""
        import jax

        return np.concatenate([np.asarray(leaf)[0].reshape(-1) for leaf in jax.tree_util.tree_leaves(carry)])

    def __call__(self, robot_node, robot_vel, humans, human_mask, *rest) -> tuple:
        """(robot_node, robot_vel, humans, human_mask[, lidar], state) -> (action, new_state): `lidar` exactly
        when the policy reads a scan (see `input_names`)."""
        import jax
        import jax.numpy as jnp

        from tgrf_jax.env.obstacles import empty as empty_obstacles
        from tgrf_jax.env.types import Obs

        if len(rest) != 1 + bool(self.lidar_rays):
            raise TypeError(
                f"the policy step takes {len(self.input_names)} inputs {self.input_names}; got {4 + len(rest)}"
            )
        if self.lidar_rays:
            lidar, state = rest
            # NaN: no return. Ranges beyond the sensor range are clipped inside the network's scaling.
            lidar = jnp.where(jnp.isnan(lidar), jnp.float32(self.lidar_range), lidar)
        else:
            (state,) = rest
            lidar = jnp.zeros((0,), jnp.float32)

        cuts = np.cumsum(self._sizes)[:-1].tolist()
        parts = jnp.split(state, cuts) if cuts else [state]
        carry = jax.tree_util.tree_unflatten(
            self._treedef, [p.reshape((1,) + leaf.shape[1:]) for p, leaf in zip(parts, self._leaves)]
        )
        n = self.num_humans
        # A float mask keeps every input one dtype for runtimes fed from other languages; 0.5 splits 0 from 1.
        obs = Obs(
            robot_node=robot_node[None],
            robot_vel=robot_vel[None],
            humans=humans[None],
            human_mask=(human_mask > 0.5)[None],
            human_vel=jnp.zeros((1, n, 2), jnp.float32),
            human_radius=jnp.zeros((1, n), jnp.float32),
            lidar=lidar[None],
            obstacles=jax.tree_util.tree_map(lambda x: x[None], empty_obstacles()),
        )
        carry, pi, _ = self.net.apply(self.params, carry, obs, None)
        new_state = jnp.concatenate([leaf.reshape(-1) for leaf in jax.tree_util.tree_leaves(carry)])
        return pi.mean()[0], new_state

    def jitted(self) -> Callable:
        import jax

        return jax.jit(self.__call__)


def read_interface(directory: str | pathlib.Path) -> dict:
    """An exported directory's interface.json as it is on disk (`tgrf_jax.deploy.load_source` checks it against
    the policy)."""
    path = pathlib.Path(directory) / INTERFACE_FILE
    try:
        spec = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise ConfigError(f"{str(path)!r}: cannot read the interface ({type(e).__name__}: {e})") from None
    if not isinstance(spec, dict):
        raise ConfigError(f"{str(path)!r} must hold a JSON object, not {type(spec).__name__}")
    return spec
