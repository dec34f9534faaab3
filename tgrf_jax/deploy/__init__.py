"""Trained policies outside the simulator: one decision exported as ONNX and StableHLO (`tgrf-export`), and
`Navigator`, which drives a robot from its pose, its goal and the humans it detects (docs/deployment.md).

ONNX export and the 'onnx' runtime need the optional extra: pip install 'tgrf-jax[deploy]'.
"""

from tgrf_jax.deploy.export import export
from tgrf_jax.deploy.navigator import Decision, Detection, Navigator, NonFiniteDecision, RobotState
from tgrf_jax.deploy.policy import FORMATS, PolicyStep, read_interface
from tgrf_jax.deploy.runtimes import RUNTIMES, make_runtime
from tgrf_jax.deploy.source import PolicySource, load_source

__all__ = [
    "FORMATS",
    "RUNTIMES",
    "Decision",
    "Detection",
    "Navigator",
    "NonFiniteDecision",
    "PolicySource",
    "PolicyStep",
    "RobotState",
    "export",
    "load_source",
    "make_runtime",
    "read_interface",
]
