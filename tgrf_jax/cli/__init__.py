"""The command-line tools: tgrf-train, tgrf-eval, tgrf-sweep, tgrf-render and tgrf-reproduce (one module each;
`common` holds the shared config / `--set` / run-directory arguments and the process setup)."""

from tgrf_jax.cli.eval import main as eval_main
from tgrf_jax.cli.render import main as render_main
from tgrf_jax.cli.reproduce import main as reproduce_main
from tgrf_jax.cli.sweep import main as sweep_main
from tgrf_jax.cli.train import main as train_main

__all__ = ["eval_main", "render_main", "reproduce_main", "sweep_main", "train_main"]
