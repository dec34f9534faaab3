"""Learned trajectory predictor: the Gumbel Social Transformer (GST) of CrowdNav++, in flax.

Public surface: `predict(params, positions, visible)`, `from_torch_state_dict(arrays)`, `pretrained(crowd)`.
"""

from tgrf_jax.predictor.model import Prediction, StepGaussians, init_params, predict, step_gaussians
from tgrf_jax.predictor.weights import WeightsError, from_torch_state_dict, load_params, pretrained, save_params

__all__ = [
    "Prediction", "StepGaussians", "WeightsError", "from_torch_state_dict", "init_params", "load_params",
    "predict", "pretrained", "save_params", "step_gaussians",
]
