"""The environment side of the learned predictor: a 5-frame history per env and the predictions made from it.

The history holds, in human-index order, each human's position and visibility in the last 5 observed frames
(frame 4 = now). A frame where a human is unseen holds the reference env's filler (robot position + 15 m per
axis), because through the released model's displacement quirk that filler can reach the network. A new
episode starts from a fresh history (the current frame only, earlier frames unseen), unlike the reference,
which carries the previous episode's frames into the first predictions of the next one.
"""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct

from tgrf_jax.env.gst.model import OBS_LEN, PRED_LEN, Prediction, predict

FILLER_OFFSET = 15.0  # unseen frames hold robot position + 15 m per axis, as the reference env fills them


@struct.dataclass
class History:
    positions: jnp.ndarray  # (N, 5, 2) absolute
    visible: jnp.ndarray  # (N, 5) bool


def _frame(robot_pos, human_pos, visible):
    return jnp.where(visible[:, None], human_pos, robot_pos + FILLER_OFFSET)


def fresh(robot_pos, human_pos, visible) -> History:
    """History at an episode start: only the current frame is seen."""
    n = human_pos.shape[0]
    frame = _frame(robot_pos, human_pos, visible)
    return History(
        positions=jnp.broadcast_to(frame[:, None], (n, OBS_LEN, 2)),
        visible=jnp.zeros((n, OBS_LEN), bool).at[:, -1].set(visible),
    )


def push(history: History, robot_pos, human_pos, visible) -> History:
    """Drop the oldest frame and append the current one."""
    frame = _frame(robot_pos, human_pos, visible)
    return History(
        positions=jnp.concatenate([history.positions[:, 1:], frame[:, None]], axis=1),
        visible=jnp.concatenate([history.visible[:, 1:], visible[:, None]], axis=1),
    )


def predictions(params, history: History) -> Prediction:
    """Predicted world positions (N, 5, 2) and `out_mask`; humans without a prediction hold their position."""
    return predict(params, history.positions, history.visible)


def fresh_predictions(history: History) -> jnp.ndarray:
    """What `predictions(...).means` returns for a `fresh` history, without running the model: the model
    predicts only humans seen in the last two frames, so every human holds its current frame's position."""
    n = history.positions.shape[0]
    return jnp.broadcast_to(history.positions[:, -1:], (n, PRED_LEN, 2))
