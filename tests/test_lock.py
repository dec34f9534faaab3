"""One writer per run / sweep / experiment directory."""

import pathlib
import subprocess
import sys
import time

import pytest

from tgrf_jax.config import ConfigError, TrainConfig
from tgrf_jax.storage.lock import OWNER_FILE, exclusive
from tgrf_jax.train.run_dir import train_run

ROOT = pathlib.Path(__file__).resolve().parents[1]
TINY = str(ROOT / "configs" / "tiny.yaml")
HOLD = (
    "import sys, time; from tgrf_jax.storage.lock import exclusive\n"
    "with exclusive(sys.argv[1]):\n    print('held', flush=True); time.sleep(60)"
)


@pytest.fixture
def held(tmp_path):
    """A directory whose lock another process holds."""
    directory = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(directory)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "held"
    yield directory, proc.pid
    proc.kill()
    proc.wait()


def test_second_writer_is_refused_naming_the_directory_and_the_holder(held):
    directory, pid = held
    with pytest.raises(ConfigError, match=rf"is being written by another process \(pid {pid}\)"):
        with exclusive(directory):
            pass
    assert (directory / OWNER_FILE).read_text().strip() == str(pid)


def test_train_run_refuses_a_directory_in_use(held):
    directory, pid = held
    with pytest.raises(ConfigError, match=rf"{directory.name}' is being written by another process \(pid {pid}\)"):
        train_run(TrainConfig.from_yaml(TINY), directory, log=lambda m: None)
    assert not (directory / "config.yaml").exists()


def test_the_lock_goes_with_its_process(held):
    directory, pid = held
    subprocess.run(["kill", "-9", str(pid)], check=True)
    deadline = time.time() + 10
    while True:
        try:
            with exclusive(directory):
                break
        except ConfigError:
            assert time.time() < deadline
            time.sleep(0.1)


def test_resume_of_a_run_stopped_before_its_first_checkpoint_starts_from_scratch(tmp_path):
    from tgrf_jax.storage.checkpoint import tree_digest as params_digest

    config = TrainConfig.from_yaml(TINY, ["run.eval_episodes=0"])
    fresh = train_run(config, tmp_path / "fresh", log=lambda m: None)
    stopped = tmp_path / "stopped"
    stopped.mkdir()
    (stopped / "config.yaml").write_text(config.to_yaml())  # what a kill during start-up leaves
    lines = []
    resumed = train_run(config, stopped, resume=True, log=lines.append)
    assert any("starting from the beginning" in line for line in lines)
    assert resumed.updates == fresh.updates == 12
    assert params_digest(resumed.state.params) == params_digest(fresh.state.params)


def test_resume_refuses_config_edits_other_than_extending_training(tmp_path):
    config = TrainConfig.from_yaml(TINY, ["run.eval_episodes=0"])
    run = tmp_path / "run"
    train_run(config, run, log=lambda m: None, stop_after_updates=4)
    text = (run / "config.yaml").read_text()
    (run / "config.yaml").write_text(text.replace("lr: 0.001", "lr: 0.002").replace("num_humans: 2", "num_humans: 3"))
    with pytest.raises(ConfigError, match=r"only ppo.total_steps may change .*ppo.lr: 0.001 -> 0.002") as e:
        train_run(config, run, resume=True, log=lambda m: None)
    assert "env.num_humans: 2 -> 3" in str(e.value)
    (run / "config.yaml").write_text(text.replace("total_steps: 1536", "total_steps: 2048"))
    assert train_run(config, run, resume=True, log=lambda m: None).updates == 16
