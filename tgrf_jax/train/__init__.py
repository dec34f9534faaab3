"""PPO training: the `Trainer` (one compiled program), the chunked outer loop, run directories, checkpoints and
plots."""

from tgrf_jax.train.ppo import (
    HParams,
    Trainer,
    TrainState,
    Transition,
    compute_gae,
    hparams_from_config,
    make_trainer,
    ppo_loss,
)

__all__ = [
    "HParams",
    "TrainState",
    "Trainer",
    "Transition",
    "compute_gae",
    "hparams_from_config",
    "make_trainer",
    "ppo_loss",
]
