"""Sweeps: a grid of hyper-parameters x seeds trained as one vmapped, compiled program, sharded over devices.

    tgrf-sweep configs/tiny.yaml --grid reward.h_disc=0.5,1.0,2.5 --grid reward.sigma_disc=0.1,0.2,0.4 --seeds 3

`grid` parses and validates the grid and run list, `program` compiles the batched program and places the runs on
the devices, `run` trains them through the outer loop shared with tgrf-train, `report` writes tables and plots.
"""

from tgrf_jax.config import griddable_fields
from tgrf_jax.sweep.grid import (
    GridAxis,
    RunSpec,
    SweepSpec,
    load_sweep,
    parse_grid,
    parse_seeds,
)
from tgrf_jax.sweep.program import BatchedProgram, BatchedTrainer, SequentialProgram, batched_trainer
from tgrf_jax.sweep.report import (
    format_summary_markdown,
    plot_sweep,
    training_tail,
    write_results,
)
from tgrf_jax.sweep.run import SweepResult, default_sweep_dir, run_sweep

__all__ = [
    "BatchedProgram",
    "BatchedTrainer",
    "GridAxis",
    "RunSpec",
    "SequentialProgram",
    "SweepResult",
    "SweepSpec",
    "batched_trainer",
    "default_sweep_dir",
    "format_summary_markdown",
    "griddable_fields",
    "load_sweep",
    "parse_grid",
    "parse_seeds",
    "plot_sweep",
    "run_sweep",
    "training_tail",
    "write_results",
]
