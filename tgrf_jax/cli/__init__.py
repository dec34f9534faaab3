"""The command-line tools: tgrf-train, tgrf-eval, tgrf-sweep, tgrf-tune, tgrf-render, tgrf-reproduce, tgrf-predictor,
tgrf-export and tgrf-data, one module each with its `main` (`common` holds `command_line`, the error and interrupt
handling every `main` runs in, the shared config / `--set` / run-directory arguments and the process setup). The
functions below import their tool on call, so `python -m tgrf_jax.cli.<tool>` runs a module not imported before."""


def train_main(argv=None) -> int:
    from tgrf_jax.cli.train import main

    return main(argv)


def eval_main(argv=None) -> int:
    from tgrf_jax.cli.eval import main

    return main(argv)


def sweep_main(argv=None) -> int:
    from tgrf_jax.cli.sweep import main

    return main(argv)


def render_main(argv=None) -> int:
    from tgrf_jax.cli.render import main

    return main(argv)


def reproduce_main(argv=None) -> int:
    from tgrf_jax.cli.reproduce import main

    return main(argv)


def predictor_main(argv=None) -> int:
    from tgrf_jax.cli.predictor import main

    return main(argv)


def export_main(argv=None) -> int:
    from tgrf_jax.cli.export import main

    return main(argv)


def tune_main(argv=None) -> int:
    from tgrf_jax.cli.tune import main

    return main(argv)
