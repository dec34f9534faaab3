"""PPO training: `make_train` (one compiled program), the chunked outer loop, checkpoints and plots."""

from tgrf_jax.train.ppo import (
    HParams,
    Train,
    Trainer,
    TrainState,
    Transition,
    compute_gae,
    hparams_from_config,
    make_train,
    ppo_loss,
)

__all__ = [
    "HParams",
    "Train",
    "TrainState",
    "Trainer",
    "Transition",
    "compute_gae",
    "hparams_from_config",
    "make_train",
    "ppo_loss",
]
