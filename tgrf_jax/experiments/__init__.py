"""The paper's experiments as data (configs/experiments/*.yaml), run row by row as tgrf-sweeps, with reports
that put our numbers beside the paper's."""

from tgrf_jax.experiments.spec import Experiment, Row, available, load

__all__ = ["Experiment", "Row", "available", "load"]
