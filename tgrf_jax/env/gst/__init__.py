"""The learned trajectory predictor's inference inside the env: the Gumbel Social Transformer (GST) of CrowdNav++
in flax, its per-env observation history and its shipped weights.

Public surface: `predict(params, positions, visible)`, `from_torch_state_dict(arrays)`, `pretrained(crowd)`.
Collecting data and training new weights is `tgrf_jax.predictor`, which builds on the env (never the reverse).
"""

from tgrf_jax.env.gst.model import (
    Prediction,
    StepGaussians,
    init_params,
    predict,
    step_gaussians,
)
from tgrf_jax.env.gst.weights import (
    WeightsError,
    from_torch_state_dict,
    load_params,
    pretrained,
    save_params,
)

__all__ = [
    "Prediction",
    "StepGaussians",
    "WeightsError",
    "from_torch_state_dict",
    "init_params",
    "load_params",
    "predict",
    "pretrained",
    "save_params",
    "step_gaussians",
]
