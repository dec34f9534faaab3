"""`tgrf_jax.cli.common.command_line`, the wrapper every tgrf-* entry point runs in: bad input anywhere ends the
process with one line on stderr and exit status 2, an interruption with one line (and how to resume) and 130, and
anything else is left to propagate (a bug keeps its traceback). The tools' own catalogue of bad inputs is
tests/test_bad_inputs.py."""

import importlib
import pathlib

import pytest

from tgrf_jax.cli.common import Recovery, check_policy_fits, command_line, load_playable
from tgrf_jax.config import ConfigError
from tgrf_jax.storage.checkpoint import CheckpointError

ROOT = pathlib.Path(__file__).resolve().parents[1]


def tool(body):
    """A tool whose run is `body(recovery)`."""
    return command_line("tgrf-test")(lambda argv, recovery: body(recovery))


def deep_config_error(recovery: Recovery) -> int:
    recovery.resume = "resume with: tgrf-test --resume here"

    def training():
        raise ConfigError("'here/metrics.csv' is damaged: line 2 is not UTF-8 text")

    training()
    return 0


def test_a_config_error_raised_anywhere_is_one_line_and_exit_2(capsys):
    assert tool(deep_config_error)([]) == 2
    err = capsys.readouterr().err
    assert err == "tgrf-test: error: 'here/metrics.csv' is damaged: line 2 is not UTF-8 text\n"


def test_an_interruption_says_how_to_resume_and_exits_130(capsys):
    def interrupted(recovery):
        recovery.resume = "resume with: tgrf-test --resume here"
        raise KeyboardInterrupt

    assert tool(interrupted)([]) == 130
    assert capsys.readouterr().err == "tgrf-test: interrupted; resume with: tgrf-test --resume here\n"

    def interrupted_early(recovery):
        raise KeyboardInterrupt

    assert tool(interrupted_early)([]) == 130
    assert capsys.readouterr().err == "tgrf-test: interrupted\n"


def test_a_damaged_checkpoint_names_the_command_to_go_on_from_an_intact_one(capsys):
    def damaged(recovery):
        recovery.from_checkpoint = "tgrf-test --resume here --from-step"
        error = CheckpointError("checkpoint 'here/checkpoints/12' (step 12) is damaged")
        error.intact = (4, 8)
        raise error

    assert tool(damaged)([]) == 2
    assert capsys.readouterr().err.splitlines() == [
        "tgrf-test: error: checkpoint 'here/checkpoints/12' (step 12) is damaged",
        "tgrf-test: the latest intact checkpoint: tgrf-test --resume here --from-step 8",
    ]


def test_other_errors_propagate():
    def bug(recovery):
        raise ZeroDivisionError("a bug")

    with pytest.raises(ZeroDivisionError):
        tool(bug)([])
    # what counts as bad input is the tool's choice (tgrf-predictor: its dataset and weight files' ValueErrors)
    with pytest.raises(ValueError):
        tool(lambda recovery: int("x"))([])
    assert command_line("tgrf-test", bad_input=(ValueError,))(lambda argv, recovery: int("x"))([]) == 2


def test_every_entry_point_runs_in_the_wrapper():
    section = (ROOT / "pyproject.toml").read_text().split("[project.scripts]\n", 1)[1].split("\n\n", 1)[0]
    scripts = dict(line.replace('"', "").split(" = ") for line in section.splitlines() if line.startswith("tgrf-"))
    assert len(scripts) >= 7
    for name, target in scripts.items():
        module, function = target.split(":")
        main = getattr(importlib.import_module(module), function)
        assert main.__wrapped__.__code__.co_varnames[:2] == ("argv", "recovery"), name


def test_a_pretrained_policy_plays_settings_that_keep_its_parameters_and_no_others():
    """(The tools' refusals, end to end: tests/test_bad_inputs.py.)"""
    name = "obstacles-random_obstacles-tgrf"
    # a human policy, the time step, the crowd size of an attention network, the reward: the same parameters
    kept = ["env.human_policy=social_force", "env.dt=0.2", "env.num_humans=5", "reward.h_disc=1.0"]
    check_policy_fits(load_playable(None, kept, "tgrf-eval", name))
    with pytest.raises(
        ConfigError, match=r"trained with env.lidar_rays = 72; these overrides make it env.lidar_rays = 0,"
    ):
        check_policy_fits(load_playable(None, [*kept, "env.lidar_rays=0"], "tgrf-eval", name))
