"""What the command-line tools share: `command_line` (their error and interrupt handling), the config / `--set` /
run-directory arguments and their loading (`load_playable`, `check_policy_fits`), and the process setup done
before JAX starts (CPU flags, compilation cache)."""

from __future__ import annotations

import argparse
import dataclasses
import functools
import os
import pathlib
import sys
from collections.abc import Callable

from tgrf_jax.config import (
    ConfigError,
    EnvConfig,
    RewardConfig,
    TrainConfig,
    apply_overrides,
    load_yaml,
    reward_config_from_dict,
)


def add_config_args(parser: argparse.ArgumentParser, config_help: str, *, run_dir: bool = False) -> None:
    """The positional config (or, with `run_dir`, RUN_DIR|CONFIG) argument and the repeatable `--set`."""
    parser.add_argument("config", nargs="?", metavar="RUN_DIR|CONFIG" if run_dir else "CONFIG", help=config_help)
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config value, e.g. --set ppo.lr=1e-4 --set env.human_policy=social_force",
    )


def train_config(path: str | None, overrides: list[str]) -> TrainConfig:
    """A TrainConfig from an optional YAML file plus `--set` overrides (the embedded default without a file)."""
    return TrainConfig.from_dict(apply_overrides(load_yaml(path) if path else {}, overrides))


@dataclasses.dataclass(frozen=True)
class Playable:
    """What tgrf-eval and tgrf-render play: the env / reward of a run directory (and its trained policy), of a
    pretrained policy (and its parameters), or of a YAML file (baseline robots only)."""

    env: EnvConfig
    reward: RewardConfig
    run_dir: pathlib.Path | None = None
    config: TrainConfig | None = None  # the run's (or pretrained policy's) config with the --set overrides
    pretrained: str | None = None  # a pretrained policy's name or directory
    params: dict | None = None  # its network parameters
    trained: TrainConfig | None = None  # the config the policy was trained with (no overrides)

    @property
    def has_policy(self) -> bool:
        return self.trained is not None


def add_pretrained_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--pretrained",
        metavar="NAME|DIR",
        help="a trained policy shipped with tgrf-jax (see tgrf_jax.pretrained.available()) or "
        "exported to a directory, played on its own env/reward config",
    )


def add_layout_arg(parser: argparse.ArgumentParser, help: str) -> None:
    """--layout of the tools that train several runs (tgrf-sweep, tgrf-tune, tgrf-reproduce); `resolve_layout`
    reads it."""
    from tgrf_jax.sweep.grid import LAYOUTS

    parser.add_argument("--layout", choices=(*LAYOUTS, "auto"), default=None, help=help)


def resolve_layout(layout: str | None, multi_host: bool = False) -> str | None:
    """'auto' as the runs' devices decide it: sequential on CPU devices of one host (XLA:CPU trains one program at a
    time faster than their vmapped batch), batched elsewhere. JAX must be started (`start`)."""
    if layout != "auto":
        return layout
    import jax

    return "sequential" if jax.default_backend() == "cpu" and not multi_host else "batched"


def load_playable(source: str | None, overrides: list[str], tool: str, pretrained: str | None = None) -> Playable:
    """Resolve RUN_DIR|CONFIG (or a pretrained policy) plus `--set` (only env.* and reward.* apply); raises
    ConfigError. A tgrf-train config file is checked whole and its env / reward sections are played."""
    bad = [o for o in overrides if o.split(".", 1)[0] not in ("env", "reward")]
    if pretrained is not None:
        from tgrf_jax import pretrained as pretrained_lib

        if source is not None:
            raise ConfigError(f"--pretrained plays its own config; give no RUN_DIR|CONFIG (got {source!r})")
        if bad:
            raise ConfigError(f"with --pretrained only env.* and reward.* can be overridden, not {bad}")
        trained, params, _ = pretrained_lib.load(pretrained)
        config = TrainConfig.from_dict(apply_overrides(trained.to_dict(), overrides))
        return Playable(config.env, config.reward, None, config, pretrained, params, trained)
    if source is not None and pathlib.Path(source).is_dir():
        from tgrf_jax.train.run_dir import load_run_config

        trained = load_run_config(source)
        if bad:
            raise ConfigError(f"with a RUN_DIR only env.* and reward.* can be overridden, not {bad}")
        config = TrainConfig.from_dict(apply_overrides(trained.to_dict(), overrides))
        return Playable(config.env, config.reward, pathlib.Path(source), config, trained=trained)
    if bad:
        raise ConfigError(f"{tool} plays the env.* and reward.* settings; only those can be overridden, not {bad}")
    data = apply_overrides(load_yaml(source) if source else {}, overrides)
    sections = [f.name for f in dataclasses.fields(TrainConfig)]
    unknown = set(data) - set(sections)
    if unknown:
        raise ConfigError(
            f"unknown config section(s) {sorted(unknown)} in {source!r}; {tool} reads env and reward "
            f"(of a tgrf-train config: {', '.join(sections)})"
        )
    if set(data) - {"env", "reward"}:
        config = TrainConfig.from_dict(data)  # a tgrf-train config: every section checked, env / reward played
        return Playable(config.env, config.reward)
    return Playable(EnvConfig.from_dict(data.get("env")), reward_config_from_dict(data.get("reward")))


def check_policy_fits(playable: Playable) -> None:
    """The trained policy's network against the env it is to play, before anything compiles (shapes are traced,
    not computed; call it after `start`). Its parameter shapes follow from what the robot senses
    (env.lidar_rays, the predictor and its horizon, with an MLP the crowd size, ...), so an override that changes
    them is refused naming the trained values. With a RUN_DIR the observation's shapes must stay too."""
    if not playable.has_policy or playable.trained.env == playable.env:
        return
    import jax

    from tgrf_jax.env import CrowdNavEnv
    from tgrf_jax.policies import make_network_for

    trained, played = playable.trained, playable.config
    where = f"the policy in {str(playable.run_dir)!r}" if playable.run_dir else f"pretrained {playable.pretrained}"
    changed = [
        f.name for f in dataclasses.fields(EnvConfig) if getattr(trained.env, f.name) != getattr(played.env, f.name)
    ]

    def obs_shapes(env: EnvConfig) -> dict:
        obs = jax.eval_shape(lambda k: CrowdNavEnv(env, playable.reward).reset(k)[0], jax.random.key(0))
        return {path: leaf.shape for path, leaf in jax.tree_util.tree_flatten_with_path(obs)[0]}

    if playable.run_dir is not None and obs_shapes(trained.env) != obs_shapes(played.env):
        changes = "; ".join(f"env.{n}: {getattr(trained.env, n)!r} -> {getattr(played.env, n)!r}" for n in changed)
        raise ConfigError(
            f"{where} was trained on observations of other shapes than these overrides give ({changes}); with a "
            "RUN_DIR only settings that keep the observation's shapes can change (e.g. env.human_policy, env.dt, "
            "reward.*)"
        )

    def param_shapes(env: EnvConfig) -> dict:
        params = jax.eval_shape(make_network_for(dataclasses.replace(trained, env=env)).init, jax.random.PRNGKey(0))
        return {jax.tree_util.keystr(p): leaf.shape for p, leaf in jax.tree_util.tree_flatten_with_path(params)[0]}

    def shapes_change(name: str) -> bool:
        try:
            return param_shapes(dataclasses.replace(trained.env, **{name: getattr(played.env, name)})) != expected
        except ConfigError:  # a value valid only together with another change
            return True

    expected = param_shapes(trained.env)
    if param_shapes(played.env) != expected:
        names = [n for n in changed if shapes_change(n)] or changed
        raise ConfigError(
            f"{where} was trained with {_settings(trained.env, names)}; these overrides make it "
            f"{_settings(played.env, names)}, which changes the shapes of its network's parameters: only settings "
            "that keep them can change (e.g. env.human_policy, env.dt, reward.*)"
        )


def _settings(env: EnvConfig, names: list[str]) -> str:
    return ", ".join(f"env.{n} = {getattr(env, n)!r}" for n in names)


def progress_line(message: str) -> None:
    """Print a line of training progress. If the reader of stdout has gone (tgrf-reproduce killed, `| head`
    closed), training goes on without it rather than dying between checkpoints: the run directory's
    progress.log keeps every line."""
    try:
        print(message, flush=True)
    except BrokenPipeError:
        stdout, stderr = os.fstat(1), os.fstat(2)
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 1)
        if (stdout.st_dev, stdout.st_ino) == (stderr.st_dev, stderr.st_ino):  # one pipe for both (tgrf-reproduce)
            os.dup2(devnull, 2)


def error(tool: str, e: Exception, hint: str | None = None) -> int:
    print(f"{tool}: error: {e}", file=sys.stderr)
    if hint:
        print(f"{tool}: {hint}", file=sys.stderr)
    return 2


def checkpoint_error(tool: str, e: Exception, command: str | None) -> int:
    """`error` for a CheckpointError; where a damaged step has intact earlier ones, the hint is `command` followed
    by the latest of them."""
    intact = getattr(e, "intact", ())
    return error(tool, e, f"the latest intact checkpoint: {command} {intact[-1]}" if intact and command else None)


@dataclasses.dataclass
class Recovery:
    """What a tool's last words after a damaged checkpoint or an interruption tell the user to run next; the tool
    fills it in as soon as it knows its directory."""

    resume: str | None = None  # after an interruption, e.g. "resume with: tgrf-train --resume runs/x"
    from_checkpoint: str | None = None  # a damaged checkpoint: this command, followed by the latest intact step


def _checkpoint_error() -> tuple[type[Exception], ...]:
    # storage.checkpoint imports orbax: only a process that loaded it can have raised its error
    module = sys.modules.get("tgrf_jax.storage.checkpoint")
    return (module.CheckpointError,) if module is not None else ()


def command_line(
    tool: str, bad_input: tuple[type[Exception], ...] = (ConfigError,)
) -> Callable[[Callable[[list[str] | None, Recovery], int]], Callable[[list[str] | None], int]]:
    """Decorator of a tool's `run(argv, recovery) -> exit status`, making its `main(argv=None)`, what every tgrf-*
    command runs: bad input (`bad_input`; a damaged checkpoint) ends it with one line on stderr naming the problem
    and exit status 2, never a traceback; an interruption (Ctrl-C, SIGTERM during training) with a line saying so,
    and how to resume where `recovery` knows it, and exit status 130."""

    def decorate(run: Callable[[list[str] | None, Recovery], int]) -> Callable[[list[str] | None], int]:
        @functools.wraps(run)
        def main(argv: list[str] | None = None) -> int:
            recovery = Recovery()
            try:
                return run(argv, recovery)
            except KeyboardInterrupt:
                print(f"{tool}: interrupted" + (f"; {recovery.resume}" if recovery.resume else ""), file=sys.stderr)
                return 130
            except Exception as e:
                if isinstance(e, _checkpoint_error()):
                    return checkpoint_error(tool, e, recovery.from_checkpoint)
                if isinstance(e, bad_input):
                    return error(tool, e)
                raise

        return main

    return decorate


def check_jax() -> None:
    """JAX settings the tools do not support, refused before anything runs."""
    import jax

    if jax.config.jax_enable_x64:
        raise ConfigError(
            "JAX_ENABLE_X64 is on, but tgrf-jax computes in float32 and int32 (its programs and "
            "checkpoints); unset JAX_ENABLE_X64"
        )


def check_seed(seed: int, flag: str = "--seed") -> None:
    if not 0 <= seed <= 2**31 - 1:
        raise ConfigError(f"{flag} = {seed} is out of range; allowed: 0 .. {2**31 - 1}")


def check_writable(path, flag: str, *, directory: bool) -> None:
    """Raise ConfigError unless `path` (a directory with `directory`, else a file) can be created or written:
    checked before any work, so that no evaluation or training is lost to an unwritable output."""
    import tempfile

    path = pathlib.Path(path)
    if directory and path.exists() and not path.is_dir():
        raise ConfigError(f"{flag} {str(path)!r} exists and is not a directory")
    if not directory and path.is_dir():
        raise ConfigError(f"{flag} {str(path)!r} is a directory; give a file name")
    existing = path if directory and path.is_dir() else path.parent
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise ConfigError(f"{flag} {str(path)!r} cannot be created: {str(existing)!r} is a file, not a directory")
    try:
        with tempfile.NamedTemporaryFile(dir=existing):
            pass
    except OSError as e:
        raise ConfigError(
            f"{flag} {str(path)!r} is not writable: no file can be created in {str(existing)!r} ({e.strerror})"
        ) from None
    if not directory and path.is_file():
        try:
            with open(path, "a"):
                pass
        except OSError as e:
            raise ConfigError(f"{flag} {str(path)!r} is not writable ({e.strerror})") from None


def start(devices: int | None = None, say_cache: bool = False) -> None:
    """Process setup before JAX starts: XLA:CPU flags (`tgrf_jax.configure_cpu`) and the compilation cache."""
    from tgrf_jax.runtime import compile_cache
    from tgrf_jax.runtime.cpu import configure_cpu

    configure_cpu(devices)
    cache_dir = compile_cache.enable()
    if cache_dir and say_cache:
        print(f"compilation cache: {cache_dir} (set {compile_cache.ENV_VAR}=off to disable)", flush=True)


def episode_progress(label: str):
    """An `evaluate` progress callback: a line per batch when the episodes take more than one batch."""
    from tgrf_jax import evaluate

    def progress(done: int, total: int) -> None:
        if total > evaluate.MAX_BATCH:
            print(f"  {label}: {done:,}/{total:,} episodes", flush=True)

    return progress


def write_json(path: str | None, payload: dict) -> None:
    import json

    if path:
        out = pathlib.Path(path)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(payload, indent=2))
        print(f"wrote {out}")
