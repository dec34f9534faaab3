"""tgrf-sweep: grid parsing and validation, artifacts, equality with tgrf-train, resume, sharding over 4 CPU devices.

One 6-run sweep of configs/tiny.yaml (h_disc in {1, 2.5, 4} x seeds {0, 1}, 8 evaluation episodes) is trained once
per module and compared with (a) the same config and seed trained alone by tgrf-train's `train_run`, (b) the same
sweep interrupted and resumed, and (c) the same sweep on 4 fake CPU devices in a subprocess (6 runs padded to 8).
"""

import csv
import json
import math
import os
import pathlib
import shutil
import subprocess
import sys

import jax
import numpy as np
import pytest
from helpers import CompileCounter, cpu_devices_env, flip_a_bit

from tgrf_jax.cli.sweep import main
from tgrf_jax.config import ConfigError, TrainConfig, load_yaml
from tgrf_jax.sweep import (
    SweepSpec,
    batched_trainer,
    griddable_fields,
    parse_grid,
    plot_sweep,
    run_sweep,
    write_results,
)
from tgrf_jax.train.run_dir import restore_run, train_run

ROOT = pathlib.Path(__file__).resolve().parents[1]
TINY = str(ROOT / "configs" / "tiny.yaml")
GRID = ["--grid", "reward.h_disc=1.0,2.5,4", "--grid", "reward.sigma_disc=0.2", "--seeds", "2"]
SETS = ["--set", "run.eval_episodes=8"]
RUN = "p001_h_disc=2.5_sigma_disc=0.2_seed=1"  # the run compared with tgrf-train
NAMES = [f"p{p:03d}_h_disc={h}_sigma_disc=0.2_seed={s}" for p, h in enumerate(("1", "2.5", "4")) for s in (0, 1)]
# float columns of metrics.csv that must agree (wall_s / sps are timings)
CURVE_FLOATS = ("episode_return", "loss", "pg_loss", "vf_loss", "entropy", "approx_kl", "grad_norm", "reward_mean")
CURVE_EXACT = ("update", "env_steps", "episodes", "success_rate", "collision_rate", "timeout_rate")


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _leaves(tree):
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(jax.device_get(tree))]


def _assert_states(a, b, exact: bool):
    la, lb = _leaves(a), _leaves(b)
    assert len(la) == len(lb)
    for x, y in zip(la, lb):
        assert x.shape == y.shape and x.dtype == y.dtype
        if exact or x.dtype.kind != "f":
            np.testing.assert_array_equal(x, y)
        else:
            np.testing.assert_allclose(x, y, rtol=1e-4, atol=1e-4)


def _assert_curves(path_a, path_b, exact: bool):
    ra, rb = _rows(path_a), _rows(path_b)
    assert len(ra) == len(rb) > 0
    for x, y in zip(ra, rb):
        for k in CURVE_EXACT:
            assert x[k] == y[k], (k, x[k], y[k])
        for k in CURVE_FLOATS:
            if exact:
                assert x[k] == y[k], (k, x[k], y[k])
            else:
                a, b = float(x[k]), float(y[k])
                assert (math.isnan(a) and math.isnan(b)) or math.isclose(a, b, rel_tol=1e-4, abs_tol=1e-5), (k, a, b)


def _assert_evals(path_a, path_b, exact: bool):
    ea = json.loads(pathlib.Path(path_a).read_text())["results"]["learned"]
    eb = json.loads(pathlib.Path(path_b).read_text())["results"]["learned"]
    if exact:
        assert ea == eb
        return
    for k, v in ea.items():
        if k in ("n_episodes", "success_rate", "collision_rate", "timeout_rate", "nav_time"):
            assert eb[k] == v, k  # same episodes, same outcomes, same number of steps
        elif v is None:
            assert eb[k] is None, k
        else:
            assert eb[k] == pytest.approx(v, rel=1e-4, abs=1e-5), k


def _sweep_cli(args, env_extra, **kw):
    env = dict(
        os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}", **env_extra
    )
    code = "import sys; from tgrf_jax.cli.sweep import main; sys.exit(main(sys.argv[1:]))"
    return subprocess.Popen([sys.executable, "-c", code, TINY, *GRID, *SETS, *args], cwd=ROOT, env=env, **kw)


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    out = tmp_path_factory.mktemp("sweeps") / "sweep"
    # start JAX first, as the rest of the suite would have: main's request for one CPU device per core then has
    # no effect, so this file alone gives the same one-device sweep as the whole suite and leaves XLA_FLAGS alone
    jax.devices()
    assert main([TINY, *GRID, *SETS, "--out", str(out)]) == 0
    return out


def test_sweep_artifacts(sweep):
    for name in (
        "sweep.yaml",
        "config.yaml",
        "metrics.csv",
        "progress.log",
        "evals.csv",
        "summary.csv",
        "summary.md",
        "learning_curves.png",
        "grid_metrics.png",
    ):
        assert (sweep / name).is_file() and (sweep / name).stat().st_size > 0, name
    assert sorted(p.name for p in (sweep / "runs").iterdir()) == NAMES
    for name in NAMES:
        run = sweep / "runs" / name
        assert [int(r["update"]) for r in _rows(run / "metrics.csv")] == [2, 4, 6, 8, 10, 12]
        assert (run / "checkpoints" / "12").is_dir()
        assert json.loads((run / "eval.json").read_text())["results"]["learned"]["n_episodes"] == 8
    spec = load_yaml(sweep / "sweep.yaml")
    assert spec["grid"] == {"reward.h_disc": [1.0, 2.5, 4.0], "reward.sigma_disc": [0.2]}
    assert spec["seeds"] == [0, 1] and [r["name"] for r in spec["runs"]] == NAMES
    assert len(_rows(sweep / "metrics.csv")) == 6 * 6  # runs x chunks, long format
    # one compiled training program for all runs and every chunk length, at the batch of all 6 runs
    batched = batched_trainer(TrainConfig.from_dict(spec["base"]), jax.devices())
    assert list(batched.compiled) == [6]

    # the summary is the mean / sample std over the seeds of each grid point of the per-run evaluations
    evals = {r["run"]: r for r in _rows(sweep / "evals.csv")}
    summary = _rows(sweep / "summary.csv")
    assert [float(r["reward.h_disc"]) for r in summary] == [1.0, 2.5, 4.0]
    for p, row in enumerate(summary):
        sr = [
            json.loads((sweep / "runs" / n / "eval.json").read_text())["results"]["learned"]["success_rate"]
            for n in NAMES[2 * p : 2 * p + 2]
        ]
        assert [float(evals[n]["success_rate"]) for n in NAMES[2 * p : 2 * p + 2]] == sr
        assert float(row["success_rate_mean"]) == pytest.approx(np.mean(sr))
        assert float(row["success_rate_std"]) == pytest.approx(np.std(sr, ddof=1))
        assert row["seeds"] == "2"
    md = (sweep / "summary.md").read_text()
    assert md.startswith("| h_disc | sigma_disc | seeds | SR |") and md.count("\n") == 5 and " ± " in md


def test_run_in_sweep_matches_tgrf_train(sweep, tmp_path):
    """The same config and seed trained alone by tgrf-train's loop: same chunks, same episodes and outcomes, and
    parameters / losses / returns equal up to float32 rounding (the batched program is compiled differently);
    bit-identical when the sweep holds only that run."""
    run_dir = sweep / "runs" / RUN
    alone_cfg = TrainConfig.from_yaml(
        TINY, ["reward.h_disc=2.5", "reward.sigma_disc=0.2", "run.seed=1", "run.eval_episodes=8"]
    )
    sweep_cfg = TrainConfig.from_dict(load_yaml(run_dir / "config.yaml"))
    a, b = alone_cfg.to_dict(), sweep_cfg.to_dict()
    a["run"].pop("name"), b["run"].pop("name")
    assert a == b  # runs/<name>/config.yaml is exactly the tgrf-train config of that run
    alone = train_run(alone_cfg, tmp_path / "alone", log=lambda m: None)
    _, in_sweep = restore_run(run_dir)
    _assert_states(alone.state, in_sweep, exact=False)
    _assert_curves(tmp_path / "alone" / "metrics.csv", run_dir / "metrics.csv", exact=False)
    _assert_evals(tmp_path / "alone" / "eval.json", run_dir / "eval.json", exact=False)

    # A device holding a single run runs tgrf-train's unbatched program: a one-run sweep is bit-identical.
    single = SweepSpec.create(TINY, ["reward.h_disc=2.5", "reward.sigma_disc=0.2"], "1,", ["run.eval_episodes=8"])
    res = run_sweep(single, tmp_path / "single", log=lambda m: None)
    _assert_states(alone.state, jax.tree_util.tree_map(lambda x: x[0], res.state), exact=True)
    single_dir = tmp_path / "single" / "runs" / "p000_h_disc=2.5_sigma_disc=0.2_seed=1"
    _assert_curves(tmp_path / "alone" / "metrics.csv", single_dir / "metrics.csv", exact=True)
    # (evaluation only up to rounding: tgrf-train's evaluate bakes the parameters into the program as constants)
    _assert_evals(tmp_path / "alone" / "eval.json", single_dir / "eval.json", exact=False)

    # The sequential layout trains each run through tgrf-train's own program: bit-identical, evaluation included,
    # also across an interruption (its checkpoints hold the batched layout's stacked state).
    seq = SweepSpec.create(
        TINY, ["reward.h_disc=1.0,2.5", "reward.sigma_disc=0.2"], "1,", ["run.eval_episodes=8"], layout="sequential"
    )
    run_sweep(seq, tmp_path / "seq", log=lambda m: None, stop_after_updates=6)
    assert load_yaml(tmp_path / "seq" / "sweep.yaml")["layout"] == "sequential"
    assert main(["--resume", str(tmp_path / "seq")]) == 0
    seq_dir = tmp_path / "seq" / "runs" / "p001_h_disc=2.5_sigma_disc=0.2_seed=1"
    _, in_seq = restore_run(seq_dir)
    _assert_states(alone.state, in_seq, exact=True)
    _assert_curves(tmp_path / "alone" / "metrics.csv", seq_dir / "metrics.csv", exact=True)
    _assert_evals(tmp_path / "alone" / "eval.json", seq_dir / "eval.json", exact=True)

    # A sweep begun batched (on a GPU, say) can go on in the sequential layout: both checkpoint the same state.
    # (One run: both layouts then run tgrf-train's program, so the switched sweep still equals it bit for bit.)
    switched = tmp_path / "switched"
    run_sweep(single, switched, log=lambda m: None, stop_after_updates=4)
    with pytest.raises(ConfigError, match="layout switches the layout of a resumed sweep"):
        run_sweep(single, tmp_path / "new", layout="sequential")
    assert main(["--resume", str(switched), "--layout", "sequential"]) == 0
    assert load_yaml(switched / "sweep.yaml")["layout"] == "sequential"
    assert "layout switched from batched to sequential" in (switched / "progress.log").read_text()
    _, in_switched = restore_run(switched / "runs" / single_dir.name)
    _assert_states(alone.state, in_switched, exact=True)
    _assert_curves(tmp_path / "alone" / "metrics.csv", switched / "runs" / single_dir.name / "metrics.csv", exact=True)


def test_resume_after_interruption_matches_uninterrupted(sweep, tmp_path):
    out = tmp_path / "resumed"
    spec = SweepSpec.create(TINY, ["reward.h_disc=1.0,2.5,4", "reward.sigma_disc=0.2"], "2", ["run.eval_episodes=8"])
    assert [r.name for r in spec.runs()] == NAMES
    # stops after update 6: the last checkpoint is update 4, so chunk 5-6 (already in the CSVs) runs again
    first = run_sweep(spec, out, log=lambda m: None, stop_after_updates=6)
    assert first.updates == 6 and not (out / "summary.csv").exists()
    assert sorted(int(p.name) for p in (out / "checkpoints").iterdir() if p.name.isdigit()) == [0, 4]
    assert [int(r["update"]) for r in _rows(out / "runs" / NAMES[0] / "metrics.csv")] == [2, 4, 6]
    with pytest.raises(ConfigError, match="already holds a sweep"):
        run_sweep(spec, out, log=lambda m: None)
    assert main(["--resume", str(out)]) == 0
    for name in NAMES:
        _, a = restore_run(sweep / "runs" / name)
        _, b = restore_run(out / "runs" / name)
        _assert_states(a, b, exact=True)  # bit-identical to the uninterrupted sweep
        _assert_curves(sweep / "runs" / name / "metrics.csv", out / "runs" / name / "metrics.csv", exact=True)
        _assert_evals(sweep / "runs" / name / "eval.json", out / "runs" / name / "eval.json", exact=True)
    assert len(_rows(out / "metrics.csv")) == 6 * 6  # the rows of the re-run chunk are not duplicated


def test_resume_of_a_finished_sweep_recreates_its_results(sweep, tmp_path):
    out = tmp_path / "copy"
    shutil.copytree(sweep, out)
    # what a kill during the final evaluation leaves: no evaluations, tables, plots or exported run checkpoints
    for name in ("evals.csv", "summary.csv", "summary.md", "learning_curves.png", "grid_metrics.png"):
        (out / name).unlink()
    for name in NAMES:
        (out / "runs" / name / "eval.json").unlink()
        shutil.rmtree(out / "runs" / name / "checkpoints")
    kept = {p: p.stat().st_mtime_ns for p in [out / "metrics.csv", *(out / "checkpoints").rglob("*")]}
    with CompileCounter() as counter:  # trains nothing; the evaluation program is the one compiled for `sweep`
        assert main(["--resume", str(out)]) == 0
    assert counter.compiles == 0
    for name in ("evals.csv", "summary.csv", "summary.md"):
        assert (out / name).read_text() == (sweep / name).read_text(), name
    assert (out / "grid_metrics.png").stat().st_size > 0
    for name in NAMES:
        _assert_evals(sweep / "runs" / name / "eval.json", out / "runs" / name / "eval.json", exact=True)
        _assert_states(restore_run(sweep / "runs" / name)[1], restore_run(out / "runs" / name)[1], exact=True)
    assert {p: p.stat().st_mtime_ns for p in kept} == kept

    # once more, now that nothing is missing: the run directories are left as they are
    kept = {p: p.stat().st_mtime_ns for p in (out / "runs").rglob("*")}
    assert main(["--resume", str(out)]) == 0
    assert {p: p.stat().st_mtime_ns for p in kept} == kept


def test_damaged_checkpoint_names_intact_steps_and_resumes_from_one(sweep, tmp_path, capsys):
    out = tmp_path / "copy"
    shutil.copytree(sweep, out)
    flip_a_bit(out / "checkpoints" / "12")
    assert main(["--resume", str(out)]) == 2
    err = capsys.readouterr().err
    assert "(step 12) is damaged: its content does not match the checksum" in err
    assert "intact earlier steps: 4, 8" in err and f"tgrf-sweep --resume {out} --from-step 8" in err
    assert main(["--resume", str(out), "--from-step", "8"]) == 0
    assert sorted(int(p.name) for p in (out / "checkpoints").iterdir() if p.name.isdigit()) == [4, 8, 12]
    for name in NAMES:  # updates 9-12 trained again: bit-identical to the uninterrupted sweep
        _assert_states(restore_run(sweep / "runs" / name)[1], restore_run(out / "runs" / name)[1], exact=True)
        _assert_curves(sweep / "runs" / name / "metrics.csv", out / "runs" / name / "metrics.csv", exact=True)
        _assert_evals(sweep / "runs" / name / "eval.json", out / "runs" / name / "eval.json", exact=True)
    assert len(_rows(out / "metrics.csv")) == 6 * 6
    assert (out / "summary.md").read_text() == (sweep / "summary.md").read_text()


def _damage_a_middle_row(out):
    """Line 18 of 37 (update 6, before the last checkpoint, so it is checked): a word for its loss."""
    lines = (out / "metrics.csv").read_text().splitlines(keepends=True)
    fields = lines[17].split(",")
    fields[lines[0].split(",").index("loss")] = "abc"
    lines[17] = ",".join(fields)
    (out / "metrics.csv").write_text("".join(lines))


@pytest.mark.parametrize(
    "damage, error",
    [
        (_damage_a_middle_row, "'{out}/metrics.csv' is damaged: line 18: loss = 'abc' is not a number"),
        (
            lambda out: (out / "metrics.csv").write_text(
                "".join((out / "metrics.csv").read_text().splitlines(True)[1:])
            ),
            "'{out}/metrics.csv' is damaged: line 1 is not its header (expected run,point,seed,reward.h_disc,...)",
        ),
        (
            lambda out: shutil.rmtree(out / "runs" / RUN),
            "run directory '{out}/runs/" + RUN + "' of the sweep is missing or has no config.yaml; restore it",
        ),
    ],
    ids=["non-numeric value", "no header", "run directory deleted"],
)
def test_resume_of_a_damaged_finished_sweep_names_the_damage(sweep, tmp_path, capsys, damage, error):
    """A finished sweep whose bookkeeping was damaged is not reported done: exit 2, one line naming the file, and
    nothing compiled, trained or rewritten."""
    out = tmp_path / "copy"
    shutil.copytree(sweep, out)
    damage(out)
    kept = {p: p.read_bytes() for p in [*out.glob("*.csv"), *out.glob("*.md")]}
    log = (out / "progress.log").read_text()
    with CompileCounter() as counter:
        assert main(["--resume", str(out)]) == 2
    std = capsys.readouterr()
    lines = std.err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"tgrf-sweep: error: {error.format(out=out)}"), std.err
    assert "done:" not in std.out and "done:" not in (out / "progress.log").read_text()[len(log) :]
    assert counter.compiles == 0
    assert {p: p.read_bytes() for p in kept} == kept


def test_sharded_over_4_devices_matches_unsharded(sweep, tmp_path):
    """The same sweep on 4 fake CPU devices (6 runs padded to 8, 2 per device) in a subprocess."""
    out = tmp_path / "sharded"
    proc = _sweep_cli(
        ["--out", str(out)], cpu_devices_env(4), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    _, stderr = proc.communicate(timeout=600)
    assert proc.returncode == 0, stderr[-3000:]
    log = (out / "progress.log").read_text()
    assert "6 runs, padded to 8 on 4 cpu device(s), 2 run(s) per device" in log
    assert sorted(p.name for p in (out / "runs").iterdir()) == NAMES  # the padding is dropped
    # Each device runs the same vmapped program on 2 runs instead of 6, which XLA compiles differently: equal up to
    # float32 rounding (max |diff| ~1e-5 over the whole state after 12 updates), same episodes and outcomes.
    for name in NAMES:
        _, a = restore_run(sweep / "runs" / name)
        _, b = restore_run(out / "runs" / name)
        _assert_states(a, b, exact=False)
        _assert_curves(sweep / "runs" / name / "metrics.csv", out / "runs" / name / "metrics.csv", exact=False)
        _assert_evals(sweep / "runs" / name / "eval.json", out / "runs" / name / "eval.json", exact=False)


@pytest.mark.slow
def test_two_hosts_match_one_host(tmp_path):
    """Multi-controller JAX: 2 processes x 2 CPU devices (jax.distributed over localhost, gloo) give bit-identical
    runs to 1 process x 4 devices (2 runs per device in both)."""
    one, two = tmp_path / "one", tmp_path / "two"
    four = cpu_devices_env(4)
    assert _sweep_cli(["--out", str(one)], four).wait(timeout=900) == 0
    two_devices = cpu_devices_env(2)
    port = 12000 + os.getpid() % 2000
    procs = [
        _sweep_cli(
            ["--out", str(two), "--coordinator", f"127.0.0.1:{port}", "--num-processes", "2", "--process-id", str(i)],
            two_devices,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        for i in range(2)
    ]
    assert [p.wait(timeout=900) for p in procs] == [0, 0]
    assert "on 4 cpu device(s), 2 run(s) per device" in (two / "progress.log").read_text()
    for name in NAMES:
        _, a = restore_run(one / "runs" / name)
        _, b = restore_run(two / "runs" / name)
        _assert_states(a, b, exact=True)
        _assert_curves(one / "runs" / name / "metrics.csv", two / "runs" / name / "metrics.csv", exact=True)
        _assert_evals(one / "runs" / name / "eval.json", two / "runs" / name / "eval.json", exact=True)


# ----------------------------------------------------------------------------------- grid parsing (no compile)


def test_grid_parsing_and_plan(capsys):
    fields = griddable_fields()
    for name in (
        "ppo.lr",
        "ppo.ent_coef",
        "ppo.clip_eps",
        "ppo.gamma",
        "ppo.gae_lambda",
        "ppo.vf_coef",
        "ppo.max_grad_norm",
        "reward.h_disc",
        "reward.sigma_disc",
        "reward.scheme",
        "env.sf_a",
        "env.robot_v_max",
    ):
        assert name in fields, name
    for name in ("ppo.num_envs", "ppo.num_steps", "network.name", "env.num_humans", "env.predictor", "run.seed"):
        assert name not in fields, name
    axes = parse_grid(["ppo.lr=1e-4,3e-4", "reward.scheme=tgrf,crowdnav_pp"])
    assert axes[0].values == (1e-4, 3e-4) and axes[1].values == ("tgrf", "crowdnav_pp")
    spec = SweepSpec.create(TINY, ["ppo.lr=1e-4,3e-4", "reward.scheme=tgrf,crowdnav_pp"], "5,9", ["ppo.ent_coef=0.01"])
    runs = spec.runs()
    assert len(runs) == 8 and [r.seed for r in runs[:2]] == [5, 9]
    assert runs[3].config.ppo.lr == 1e-4 and runs[3].config.reward.scheme == "crowdnav_pp"
    assert runs[3].config.run.seed == 9 and all(r.config.ppo.ent_coef == 0.01 for r in runs)
    assert SweepSpec.from_dict(spec.to_dict()).to_dict() == spec.to_dict()
    assert [r.seed for r in SweepSpec.create(TINY, [], "3").runs()] == [0, 1, 2]  # run.seed, run.seed + 1, ...
    assert main([TINY, *GRID, "--print-plan"]) == 0
    out = capsys.readouterr().out
    assert "3 grid point(s) x 2 seed(s) = 6 runs" in out and NAMES[-1] in out


def test_summary_and_plots_from_results(tmp_path):
    """Tables and plots of a 2 x 2 grid with 3 seeds from synthetic per-run results (no training)."""
    spec = SweepSpec.create(TINY, ["reward.h_disc=1,2", "reward.sigma_disc=0.1,0.2"], "3")
    fields = ["update", "env_steps", "episodes", "episode_return", "success_rate"]
    evals, long_rows = [], []
    for r in spec.runs():
        d = tmp_path / "runs" / r.name
        d.mkdir(parents=True)
        rows = [
            dict(update=u, env_steps=128 * u, episodes=4, episode_return=r.point + u, success_rate=0.25 * r.point)
            for u in (2, 4, 6)
        ]
        with open(d / "metrics.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=fields)
            w.writeheader()
            w.writerows(rows)
        long_rows += [dict(row, run=r.name, point=r.point, seed=r.seed) for row in rows]
        res = {
            k: 0.0
            for k in (
                "collision_rate",
                "timeout_rate",
                "nav_time",
                "path_length",
                "itr_future",
                "itr_disc",
                "intrusion_dist_future",
                "intrusion_dist_disc",
                "mean_return",
            )
        }
        res.update(n_episodes=10, success_rate=0.1 * r.point + 0.01 * r.seed, itr_disc=None)
        evals.append({"results": {"learned": res}})
    with open(tmp_path / "metrics.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["run", "point", "seed"] + fields)
        w.writeheader()
        w.writerows(long_rows)
    summary = write_results(tmp_path, spec, evals)
    assert len(summary) == 4
    assert summary[3]["success_rate_mean"] == pytest.approx(0.3 + 0.01)
    assert summary[3]["success_rate_std"] == pytest.approx(0.01)
    assert math.isnan(summary[0]["itr_disc_mean"])  # no finite value: n/a, not 0
    assert summary[2]["train_return_mean"] == pytest.approx(2 + 6)  # last 10% of updates: the last chunk
    md = (tmp_path / "summary.md").read_text()
    assert "| 2 | 0.2 | 3 | 31.0% ± 1.0% |" in md and "n/a" in md
    paths = plot_sweep(tmp_path, spec, summary)
    assert {p.name for p in paths} == {"learning_curves.png", "heatmap.png"}
    assert all(p.stat().st_size > 10_000 for p in paths)


def test_layout_is_recorded_and_checked():
    spec = SweepSpec.create(TINY, [], "1", [], layout="sequential")
    data = spec.to_dict()
    assert data["layout"] == "sequential" and SweepSpec.from_dict(data).layout == "sequential"
    del data["layout"]  # a sweep.yaml written before layouts existed ran batched
    assert SweepSpec.from_dict(data).layout == "batched"
    with pytest.raises(ConfigError, match="layout = 'vmap': allowed batched, sequential"):
        SweepSpec.from_dict(dict(data, layout="vmap"))
    with pytest.raises(ConfigError, match="--layout = 'fast': allowed batched, sequential"):
        SweepSpec.create(TINY, layout="fast")


def test_sequential_layout_is_refused_for_multi_host_before_anything_is_written(tmp_path, capsys):
    out = tmp_path / "never"
    assert main([TINY, "--layout", "sequential", "--distributed", "--out", str(out)]) != 0
    assert "needs the batched layout" in capsys.readouterr().err
    assert not out.exists()
