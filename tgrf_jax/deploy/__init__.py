"""Trained policies outside the simulator: one decision exported as ONNX and StableHLO (`tgrf-export`), and
`Navigator`, which drives a robot from its pose, its goal and the humans it detects (docs/deployment.md).

ONNX export and the 'onnx' runtime need the optional extra: pip install 'tgrf-jax[deploy]'.
"""

from tgrf_jax.deploy.export import FORMATS, export
from tgrf_jax.deploy.navigator import Decision, Detection, Navigator, RobotState
from tgrf_jax.deploy.policy import PolicySource, PolicyStep, load_source, read_interface
from tgrf_jax.deploy.runtimes import RUNTIMES, make_runtime

__all__ = [
    "FORMATS",
    "RUNTIMES",
    "Decision",
    "Detection",
    "Navigator",
    "PolicySource",
    "PolicyStep",
    "RobotState",
    "export",
    "load_source",
    "make_runtime",
    "read_interface",
]
