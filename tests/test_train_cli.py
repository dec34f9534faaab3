"""tgrf-train / tgrf-eval RUN_DIR: run-directory artifacts, config errors, checkpoints, stopping on a signal, resume
after SIGKILL."""

import csv
import json
import os
import pathlib
import shutil
import signal
import subprocess
import sys
import time

import pytest
from helpers import CompileCounter, flip_a_bit, signal_this_thread

from tgrf_jax.cli import eval_main, train_main
from tgrf_jax.storage.checkpoint import CheckpointError
from tgrf_jax.storage.checkpoint import tree_digest as params_digest
from tgrf_jax.train.run_dir import load_run_config, restore_run, train_run

ROOT = pathlib.Path(__file__).resolve().parents[1]
TINY = str(ROOT / "configs" / "tiny.yaml")


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("runs") / "tiny"
    assert train_main([TINY, "--out-dir", str(run_dir), "--set", "run.eval_episodes=8"]) == 0
    return run_dir


def test_train_writes_all_artifacts(tiny_run):
    for name in ("config.yaml", "metrics.csv", "progress.log", "eval.json", "learning_curve.png"):
        assert (tiny_run / name).is_file() and (tiny_run / name).stat().st_size > 0, name
    steps = sorted(int(p.name) for p in (tiny_run / "checkpoints").iterdir() if p.name.isdigit())
    assert steps[-1] == 12 and 8 in steps  # checkpoint_every 4, keep 3
    assert not list((tiny_run / "checkpoints").glob("*tmp*"))  # all saves finalised
    rows = list(csv.DictReader(open(tiny_run / "metrics.csv")))
    assert [int(r["update"]) for r in rows] == [2, 4, 6, 8, 10, 12]
    assert float(rows[-1]["sps"]) > 0
    ev = json.loads((tiny_run / "eval.json").read_text())
    assert ev["results"]["learned"]["n_episodes"] == 8 and ev["updates"] == 12
    assert "run.eval_episodes" not in (tiny_run / "config.yaml").read_text()
    assert "eval_episodes: 8" in (tiny_run / "config.yaml").read_text()
    # the one compilation that may take long is announced before it starts
    log = (tiny_run / "progress.log").read_text().splitlines()
    assert [line for line in log if "the training program" in line][0] == "compiling the training program ..."
    assert (
        log.index("compiling the training program ...") + 1
        == [i for i, line in enumerate(log) if line.startswith("compiled the training program in ")][0]
    )


def test_eval_run_dir(tiny_run, tmp_path, monkeypatch, capsys):
    import tgrf_jax.evaluate

    monkeypatch.setattr(tgrf_jax.evaluate, "MAX_BATCH", 3)  # 6 episodes: two batches, with a progress line each
    out = tmp_path / "eval.json"
    assert eval_main([str(tiny_run), "--episodes", "6", "--policy", "straight", "--out", str(out)]) == 0
    payload = json.loads(out.read_text())
    assert set(payload["results"]) == {"learned", "straight"} and payload["update"] == 12
    assert {r["n_episodes"] for r in payload["results"].values()} == {6}
    lines = capsys.readouterr().out.splitlines()
    compiling = [i for i, line in enumerate(lines) if "compiling the evaluation program" in line]
    assert len(compiling) == 1 and compiling[0] < min(i for i, line in enumerate(lines) if "/6 episodes" in line)
    assert [line.strip() for line in lines if "/6 episodes" in line] == [
        "learned: 3/6 episodes",
        "learned: 6/6 episodes",
        "straight: 3/6 episodes",
        "straight: 6/6 episodes",
    ]


def test_print_config_applies_overrides(capsys):
    assert train_main(["--print-config", "--set", "ppo.lr=1e-4", "--set", "reward.h_disc=2.0"]) == 0
    out = capsys.readouterr().out
    assert "lr: 0.0001" in out and "h_disc: 2.0" in out


def test_resume_of_a_finished_run_trains_and_evaluates_nothing(tiny_run, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    (run / "learning_curve.png").unlink()
    kept = {
        p: p.stat().st_mtime_ns for p in [run / "eval.json", run / "metrics.csv", *(run / "checkpoints").rglob("*")]
    }
    with CompileCounter() as counter:
        assert train_main(["--resume", str(run)]) == 0
    assert counter.compiles == 0
    assert (run / "learning_curve.png").stat().st_size > 0  # the missing result file is made again
    assert {p: p.stat().st_mtime_ns for p in kept} == kept


def test_damaged_checkpoint_names_intact_steps_and_resumes_from_one(tiny_run, tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    flip_a_bit(run / "checkpoints" / "12")
    with pytest.raises(CheckpointError, match="is damaged") as e:
        restore_run(run)
    assert (e.value.step, e.value.intact) == (12, (4, 8))
    with CompileCounter() as counter:
        assert train_main(["--resume", str(run)]) == 2
        err = capsys.readouterr().err
        assert f"'{run / 'checkpoints' / '12'}' (step 12) is damaged" in err and "intact earlier steps: 4, 8" in err
        assert f"tgrf-train --resume {run} --from-step 8" in err
        assert eval_main([str(run), "--episodes", "2"]) == 2
        assert f"tgrf-eval {run} --step 8" in capsys.readouterr().err
        assert train_main(["--resume", str(run), "--from-step", "6"]) == 2
        assert "--from-step 6: " in (err := capsys.readouterr().err) and "it holds: 4, 8, 12" in err
    assert counter.compiles == 0
    # --from-step 8: the later checkpoints go, the CSV is cut back to 8 and the stale evaluation removed (stopped
    # there, as an interruption would; tests/test_sweep.py trains such a resume to the end)
    train_run(load_run_config(run), run, resume=True, from_step=8, log=lambda m: None, stop_after_updates=8)
    assert sorted(int(p.name) for p in (run / "checkpoints").iterdir() if p.name.isdigit()) == [4, 8]
    assert [int(r["update"]) for r in csv.DictReader(open(run / "metrics.csv"))] == [2, 4, 6, 8]
    assert not (run / "eval.json").exists()


def test_sigterm_stops_after_the_chunk_with_a_checkpoint_and_resume_is_bit_identical(tiny_run, tmp_path):
    """(tests/test_stop.py: Ctrl-C, a second signal, ignored signals.)"""
    run, config, signum = tmp_path / "run", load_run_config(tiny_run), signal.SIGTERM
    handlers = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    lines = []

    def signal_during_update_2(line):  # update 2 is no checkpoint update (checkpoint_every 4)
        lines.append(line)
        if "update 2]" in line:
            signal_this_thread(signum)

    with pytest.raises(KeyboardInterrupt):
        train_run(config, run, log=signal_during_update_2)
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == handlers
    assert sorted(int(p.name) for p in (run / "checkpoints").iterdir() if p.name.isdigit()) == [0, 2]
    assert f"stopped by {signal.Signals(signum).name} at update 2/12" in lines[-1]
    train_run(config, run, resume=True, log=lambda m: None)
    assert [int(r["update"]) for r in csv.DictReader(open(run / "metrics.csv"))] == [2, 4, 6, 8, 10, 12]
    assert params_digest(restore_run(run)[1].params) == params_digest(restore_run(tiny_run)[1].params)


def _cli(args, **kw):
    code = "import sys; from tgrf_jax.cli import train_main; sys.exit(train_main(sys.argv[1:]))"
    env = dict(os.environ, PYTHONPATH=f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    return subprocess.Popen([sys.executable, "-c", code, *args], cwd=ROOT, env=env, **kw)


@pytest.mark.slow
def test_resume_after_sigkill_matches_uninterrupted(tmp_path):
    """Kill -9 a run right after its first checkpoint, resume it, and compare with an uninterrupted run."""
    sets = [
        "--set",
        "ppo.total_steps=8192",
        "--set",
        "run.checkpoint_every=4",
        "--set",
        "run.log_every=2",
        "--set",
        "run.eval_episodes=0",
    ]  # 64 updates, 16 checkpoints
    full, killed = tmp_path / "full", tmp_path / "killed"
    assert _cli([TINY, "--out-dir", str(full), *sets]).wait(timeout=300) == 0

    proc = _cli([TINY, "--out-dir", str(killed), *sets], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    ckpts = killed / "checkpoints"
    deadline = time.time() + 300
    while time.time() < deadline:
        if ckpts.is_dir() and any(p.name.isdigit() and int(p.name) > 0 for p in ckpts.iterdir()):
            break
        time.sleep(0.005)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL
    done = sorted(int(p.name) for p in ckpts.iterdir() if p.name.isdigit())
    assert done[-1] < 64, f"the run finished before it was killed ({done})"

    assert _cli(["--resume", str(killed)]).wait(timeout=300) == 0
    _, s_full = restore_run(full)
    _, s_res = restore_run(killed)
    assert int(s_full.update) == int(s_res.update) == 64
    assert params_digest(s_full.params) == params_digest(s_res.params)
    assert params_digest(s_full.opt_state) == params_digest(s_res.opt_state)
    assert params_digest(s_full.env_state) == params_digest(s_res.env_state)
    rows = [int(r["update"]) for r in csv.DictReader(open(killed / "metrics.csv"))]
    assert rows == list(range(2, 65, 2))  # no duplicated rows after the resume
