"""The paper's experiments as data (configs/experiments/*.yaml), run row by row as tgrf-sweeps, with reports
that put our numbers beside the paper's; and search experiments, whose tune, random and grid rows compare ways of
searching one space at equal env steps (`tgrf_jax.experiments.search`)."""

from tgrf_jax.experiments.spec import Experiment, Row, available, load

__all__ = ["Experiment", "Row", "available", "load"]
