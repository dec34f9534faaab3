"""tgrf-reproduce: experiment files, the resumable row runner and the paper-layout report."""

import csv
import dataclasses
import json
import math
import pathlib
import subprocess
import sys

import pytest
import yaml
from helpers import signal_this_thread

from tgrf_jax.cli.reproduce import main
from tgrf_jax.config import ConfigError
from tgrf_jax.experiments import report, runner
from tgrf_jax.experiments import spec as spec_lib

ROOT = pathlib.Path(__file__).resolve().parents[1]
TINY = str(ROOT / "configs" / "tiny.yaml")
PAPER = {"sr_mean": 50.0, "sr_std": 5.0, "sr": 55.0, "nt": 20.0, "pl": 21.0, "itr": 5.0}


def write_experiment(path, **changes):
    data = {
        "title": "tiny table",
        "layout": "table",
        "config": TINY,
        "seeds": 2,
        "set": {"ppo.total_steps": 256, "run.eval_episodes": 4},
        "grid": {"reward.scheme": ["crowdnav_pp", "tgrf"]},
        "columns": {"tgrf": "With TGRF"},
        "rows": [{"name": "mlp", "label": "MLP", "paper": {"tgrf": PAPER}}],
    }
    data.update(changes)
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize("name", spec_lib.available())
def test_shipped_experiments_validate(name):
    exp = spec_lib.load(name)
    if exp.search:  # tests/test_search_experiment.py checks its rows
        return
    # a table reports mean ± std over seeds; a heat map may spend its runs on grid points instead (one seed)
    assert exp.rows and (exp.seeds >= 2 or exp.layout == "heatmap")
    for row in exp.rows:
        runs = spec_lib.sweep_spec(exp, row).runs()
        assert len(runs) == exp.seeds * math.prod(len(values) for _, values in row.grid)


def test_paper_tables_hold_every_row_of_the_paper():
    t1, t2 = spec_lib.load("table1"), spec_lib.load("table2")
    assert t1.row("const_vel").paper["tgrf"]["sr_mean"] == pytest.approx(87.909)
    assert t1.row("truth").paper["crowdnav_pp"]["sr_mean"] == pytest.approx(5.545)
    assert t2.row("no_pred").paper["crowdnav_pp"]["sr"] == pytest.approx(28.0)
    assert t1.row("gst").paper["tgrf"]["sr_mean"] == pytest.approx(94.091)
    assert t2.row("gst").paper["crowdnav_pp"]["sr_mean"] == pytest.approx(91.636)
    assert [r.name for r in t1.rows] == ["dsrnn", "no_pred", "const_vel", "truth", "gst"]
    assert [r.name for r in t2.rows] == ["dsrnn", "no_pred", "const_vel", "gst"]
    for exp in (t1, t2):
        for row in exp.rows:
            assert set(row.paper) == {"crowdnav_pp", "tgrf"}
            assert all(set(v) == set(spec_lib.PAPER_FIELDS) for v in row.paper.values())


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"seeds": 0}, "seeds = 0 must be an integer from 1 to 100"),
        ({"layout": "pie"}, "layout = 'pie' is not allowed"),
        ({"colour": 1}, "unknown key(s) ['colour']"),
        ({"grid": {}}, "grid must map at least one dotted field"),
        ({"rows": [{"name": "a", "set": {"ppo.lrr": 1}}]}, "row 'a': unknown config key 'ppo.lrr'"),
        ({"rows": [{"name": "a", "set": {"ppo.lr": -1}}]}, "row 'a': ppo.lr = -1"),
        ({"rows": [{"name": "a"}, {"name": "a"}]}, "name 'a' must be unique"),
        ({"rows": [{"name": "a", "paper": {"dsrnn": PAPER}}]}, "'dsrnn' is not a value of the compared axis"),
        ({"rows": [{"name": "a", "paper": {"tgrf": {"sr_meen": 1}}}]}, "unknown field(s) ['sr_meen']"),
        ({"rows": [{"name": "a", "grid": {"reward.h_disc": [1.0]}}]}, "must have the experiment's axes"),
        ({"grid": {"network.name": ["mlp", "dsrnn"]}, "rows": [{"name": "a"}]}, "network.name"),
        ({"compare": ["orca"]}, "compare: policies are compared on the rows' test episodes, and no row has a test"),
        (
            {"compare": ["orca", "nosuch"], "rows": [{"name": "a", "test": {"env.time_limit": 3}}]},
            "compare: unknown policy 'nosuch'; allowed: obstacles-mix-tgrf",
        ),
        ({"rows": [{"name": "a", "test": {"ppo.lr": 0.1}}]}, "rows[0].test: ppo.lr is not an env field"),
        ({"rows": [{"name": "a", "test": {}}]}, "rows[0].test must set at least one env field"),
        (
            {"rows": [{"name": "a", "test": {"env.scenario": "moon"}}]},
            "experiment 'exp', row 'a', test: env.scenario = 'moon'",
        ),
    ],
)
def test_bad_experiment_files_are_rejected_naming_the_field(tmp_path, changes, message):
    path = write_experiment(tmp_path / "exp.yaml", **changes)
    with pytest.raises(ConfigError) as e:
        spec_lib.load(str(path))
    assert message in str(e.value)


def test_cli_errors(tmp_path, capsys):
    assert main(["nosuch"]) == 2
    assert f"unknown experiment 'nosuch'; experiments: {', '.join(spec_lib.available())}" in capsys.readouterr().err
    assert main([str(tmp_path)]) == 2
    assert "is a directory" in capsys.readouterr().err
    path = write_experiment(tmp_path / "exp.yaml")
    assert main([str(path), "--rows", "nope"]) == 2
    assert "has no row 'nope'; rows: mlp" in capsys.readouterr().err
    assert main([str(path), "--steps", "0"]) == 2
    assert "--steps = 0 must be >= 1" in capsys.readouterr().err
    assert main([str(path), "--report-only", "--out", str(tmp_path / "none")]) == 2
    assert f"--out '{tmp_path / 'none'}' does not exist: no rows to report" in capsys.readouterr().err
    assert main([str(path), "--report-only", "--export-pretrained", "/proc/none"]) == 2
    assert "--export-pretrained '/proc/none' is not writable" in capsys.readouterr().err


def test_report_cells_from_evals(tmp_path):
    exp = spec_lib.load(str(write_experiment(tmp_path / "exp.yaml")))
    row_dir = tmp_path / "out" / "mlp"
    row_dir.mkdir(parents=True)
    fields = [
        "run",
        "point",
        "seed",
        "reward.scheme",
        "success_rate",
        "nav_time",
        "path_length",
        "itr_future",
        "itr_disc",
    ]
    rows = [
        ["a", 0, 0, "crowdnav_pp", 0.50, 20.0, 21.0, 6.0, 7.0],
        ["b", 0, 1, "crowdnav_pp", 0.70, 18.0, 19.0, 4.0, 5.0],
        ["c", 1, 0, "tgrf", 0.90, 16.0, 17.0, 2.0, 3.0],
        ["d", 1, 1, "tgrf", 0.80, 15.0, 16.0, 1.0, 2.0],
    ]
    with open(row_dir / "evals.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(fields)
        w.writerows(rows)
    (row_dir / "provenance.json").write_text(
        json.dumps(
            {
                "wall_s": 90.0,
                "invocations": [
                    {"commit": "aaa", "machine": "CPU, 16 cores, 1 x GPU", "exit_code": 130, "finished": "t1"},
                    {"commit": "bbb", "machine": "CPU, 2 cores", "exit_code": 130, "finished": "t2"},
                    {"commit": "ccc", "machine": "CPU, 16 cores, 1 x GPU", "exit_code": 0, "finished": "t3"},
                ],
            }
        )
    )
    records = report.collect(exp, tmp_path / "out")
    cnpp, tgrf = records
    assert cnpp["sr_mean"] == pytest.approx(60.0) and cnpp["sr_std"] == pytest.approx(14.142, abs=1e-3)
    assert cnpp["best_seed"] == 1 and cnpp["sr"] == pytest.approx(70.0) and cnpp["nt"] == 18.0
    assert tgrf["best_seed"] == 0 and tgrf["itr"] == 2.0 and tgrf["paper_sr_mean"] == 50.0
    table = report.format_table(exp, records)
    assert "| With TGRF | MLP | 85.0 ± 7.1 (50.0 ± 5.0) | 90.0 (55.0) | 16.00 (20.00) |" in table
    assert "| crowdnav_pp | MLP | 60.0 ± 14.1 |" in table
    assert cnpp["commit"] == "ccc"  # the CSV's commit: the last invocation's
    md = report.format_report(exp, tmp_path / "out", records)
    assert "| mlp | 1.5 min | 3 | aaa to ccc | CPU, 16 cores, 1 x GPU; CPU, 2 cores | t3 |" in md
    assert "Each cell: ours (the paper's)." in md
    # an experiment with no published values says nothing of the paper's cells
    own = spec_lib.load(str(write_experiment(tmp_path / "own.yaml", rows=[{"name": "mlp", "label": "MLP"}])))
    md = report.format_report(own, tmp_path / "out", report.collect(own, tmp_path / "out"))
    assert "the paper's" not in md and "SR mean ± sample std over seeds" in md


def test_report_header_names_every_compared_axis(tmp_path):
    exp = spec_lib.load(
        str(
            write_experiment(
                tmp_path / "exp.yaml",
                layout="heatmap",
                columns={},
                grid={"reward.h_disc": [0.625, 2.5], "reward.sigma_disc": [0.1, 0.5]},
                rows=[
                    {"name": "a", "label": "A"},
                    {"name": "b", "label": "B", "grid": {"reward.h_disc": [5.0], "reward.sigma_disc": [0.1]}},
                ],
            )
        )
    )
    md = report.format_report(exp, tmp_path / "out", [])
    assert "compared inside each row: `reward.h_disc` = 0.625, 2.5, 5.0 x `reward.sigma_disc` = 0.1, 0.5." in md
    for row in ("a", "b"):  # finished rows: the progress header is all that runs
        (tmp_path / "out" / row).mkdir(parents=True)
        (tmp_path / "out" / row / "evals.csv").write_text(
            "run,point,seed,reward.h_disc,reward.sigma_disc,success_rate\nr0,0,0,0.625,0.1,0.5\n"
        )
        (tmp_path / "out" / row / "provenance.json").write_text(FINISHED)
    lines = []
    assert runner.reproduce(exp, tmp_path / "out", log=lines.append) == 0
    assert "2 rows x 3 reward.h_disc x 2 reward.sigma_disc values x 2 seeds; 2 rows already done" in lines[0]


def test_row_states(tmp_path):
    row = tmp_path / "r"
    assert runner.row_state(row) == "new"
    row.mkdir()
    (row / "sweep.yaml").write_text("{}")
    assert runner.row_state(row) == "stale"
    (row / "checkpoints" / "4").mkdir(parents=True)
    assert runner.row_state(row) == "resumable"
    (row / "evals.csv").write_text("run,seed,success_rate\nr0,0,0.5\n")
    assert runner.row_state(row) == "damaged"  # no invocation recorded as finished
    (row / "provenance.json").write_text(FINISHED)
    assert runner.row_state(row) == "done"


FINISHED = json.dumps({"wall_s": 1.0, "invocations": [{"commit": "c", "exit_code": 0, "finished": "t"}]})
SWEEP_OF_TWO = "runs: [{name: r0}, {name: r1}]\n"
EVALS = "run,point,seed,reward.scheme,success_rate,nav_time\nr0,0,0,tgrf,0.5,{nt}\nr1,0,1,tgrf,{sr},20.0\n"


@pytest.mark.parametrize(
    "evals, sweep, provenance, problem",
    [
        (EVALS.format(nt="18.0", sr="0.7"), SWEEP_OF_TWO, FINISHED, None),
        (EVALS.format(nt="nan", sr="0.7"), SWEEP_OF_TWO, FINISHED, None),  # no success: no navigation time
        (EVALS.split("\n")[0] + "\n", SWEEP_OF_TWO, FINISHED, "evals.csv holds 0 runs, its sweep 2"),
        (EVALS.format(nt="18.0", sr="0.7"), "runs: [{name: r0}]\n", FINISHED, "evals.csv holds 2 runs, its sweep 1"),
        (EVALS.format(nt="18.0", sr="0.7x"), SWEEP_OF_TWO, FINISHED, "line 3: success_rate = '0.7x' is not a finite"),
        (EVALS.format(nt="18.0", sr=""), SWEEP_OF_TWO, FINISHED, "line 3: success_rate = '' is not a finite number"),
        (EVALS.format(nt="1x", sr="0.7"), SWEEP_OF_TWO, FINISHED, "line 2: nav_time = '1x' is not a number"),
        (
            EVALS.format(nt="18.0", sr="0.7").replace("r1,0,1", "r1,0,one"),
            SWEEP_OF_TWO,
            FINISHED,
            "line 3: seed = 'one' is not a whole number",
        ),
        (
            EVALS.format(nt="18.0", sr="0.7"),
            SWEEP_OF_TWO,
            FINISHED.replace('"exit_code": 0', '"exit_code": null'),
            "provenance.json does not record the invocation that finished it",
        ),
    ],
)
def test_a_row_is_done_only_with_whole_results_and_their_provenance(tmp_path, evals, sweep, provenance, problem):
    row = tmp_path / "mlp"
    (row / "checkpoints" / "4").mkdir(parents=True)
    (row / "sweep.yaml").write_text(sweep)
    (row / "evals.csv").write_text(evals)
    (row / "provenance.json").write_text(provenance)
    assert runner.row_state(row) == ("done" if problem is None else "damaged")
    if problem is not None:
        assert problem in runner.row_problem(row)


def test_a_damaged_row_is_reported_as_damaged_never_averaged(tmp_path):
    exp = spec_lib.load(str(write_experiment(tmp_path / "exp.yaml")))
    row = tmp_path / "out" / "mlp"
    row.mkdir(parents=True)
    (row / "sweep.yaml").write_text(SWEEP_OF_TWO)
    (row / "provenance.json").write_text(FINISHED)
    (row / "evals.csv").write_text(EVALS.format(nt="18.0", sr="abc"))  # nanmean would report seed 0 alone
    records = report.collect(exp, tmp_path / "out")
    assert all("sr_mean" not in r and "seeds" not in r for r in records)
    table = report.format_table(exp, records)
    assert (
        "damaged (evals.csv line 3: success_rate = 'abc' is not a finite number): rerun tgrf-reproduce exp --rows mlp"
    ) in table
    (row / "evals.csv").write_text(EVALS.format(nt="18.0", sr="0.7"))
    tgrf = [r for r in report.collect(exp, tmp_path / "out") if r["value"] == "tgrf"][0]
    assert tgrf["seeds"] == 2 and tgrf["sr_mean"] == pytest.approx(60.0)


@pytest.mark.parametrize(
    "name, text, message",
    [
        ("provenance.json", "{not json", "provenance.json' is damaged (JSONDecodeError"),
        ("provenance.json", '{"invocations": 3}', "provenance.json' is damaged (ValueError: no list of invocations)"),
        ("experiment.yaml", "rows: [unclosed", "experiment.yaml' is damaged (ParserError: while parsing"),
        (
            "experiment.yaml",
            "- a list\n",
            "experiment.yaml' is damaged (ValueError: not a mapping with a list of rows)",
        ),
    ],
)
def test_damaged_bookkeeping_files_are_named_not_tracebacks(tmp_path, capsys, name, text, message):
    write_experiment(tmp_path / "exp.yaml")
    out = tmp_path / "out"
    (out / "mlp").mkdir(parents=True)
    (out / "experiment.yaml").write_text(yaml.safe_dump(spec_lib.load(str(tmp_path / "exp.yaml")).to_dict()))
    (out / "mlp" / "sweep.yaml").write_text(SWEEP_OF_TWO)
    (out / "mlp" / "evals.csv").write_text(EVALS.format(nt="18.0", sr="0.7"))
    (out / ("mlp/" + name if name == "provenance.json" else name)).write_text(text)
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert main([str(tmp_path / "exp.yaml"), "--out", str(out), "--report-only"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("tgrf-reproduce: error: ") and message in err and len(err.strip().splitlines()) == 1
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before


def test_rows_without_their_experiment_file_are_not_mixed_with_another_budget(tmp_path, capsys):
    write_experiment(tmp_path / "exp.yaml")
    out = tmp_path / "out"
    (out / "mlp").mkdir(parents=True)
    (out / "mlp" / "sweep.yaml").write_text(SWEEP_OF_TWO)  # experiment.yaml deleted
    assert main([str(tmp_path / "exp.yaml"), "--out", str(out), "--steps", "512"]) == 2
    assert f"'{out}' holds rows (mlp) but no experiment.yaml, so their settings are unknown" in capsys.readouterr().err
    assert not (out / "experiment.yaml").exists()


def test_machine_names_the_gpus_the_driver_lists_unless_jax_is_kept_off_them(tmp_path, monkeypatch):
    for slot, model in enumerate(["NVIDIA H100 80GB HBM3", "NVIDIA H100 80GB HBM3", "NVIDIA H200"]):
        gpu = tmp_path / f"0000:0{slot}:00.0"
        gpu.mkdir()
        (gpu / "information").write_text(f"Model: \t\t {model}\nIRQ:   \t\t 42\n")
    monkeypatch.setattr(runner, "NVIDIA_DRIVER_GPUS", tmp_path)
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    monkeypatch.delenv("JAX_PLATFORMS", raising=False)
    assert runner.machine().endswith(" cores, 2 x NVIDIA H100 80GB HBM3, 1 x NVIDIA H200")
    monkeypatch.setenv("JAX_PLATFORMS", "cpu")
    assert runner.machine().endswith(" cores")
    monkeypatch.setenv("JAX_PLATFORMS", "cuda,cpu")
    assert runner.gpu_models() == ["NVIDIA H100 80GB HBM3"] * 2 + ["NVIDIA H200"]
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "")
    assert runner.gpu_models() == []
    monkeypatch.setattr(runner, "NVIDIA_DRIVER_GPUS", tmp_path / "absent")
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES")
    assert runner.gpu_models() == []


SWEEP_CHILD = """
import signal, sys, time
def stop(signum, frame):
    print("stopped at update 7, with a checkpoint", flush=True)
    sys.exit(130)
signal.signal(signal.SIGTERM, stop)
print("update 5", flush=True)
time.sleep(120)
"""


def test_commit_is_dirty_for_code_changes_only(tmp_path):
    """Rows write their results into the checkout they run from; only changes to what the training imports or
    reads (package, configs, pyproject.toml) make the recorded commit '+dirty'."""

    def git(*args):
        subprocess.run(
            ["git", "-C", str(tmp_path), "-c", "user.name=t", "-c", "user.email=t@t", *args],
            check=True,
            capture_output=True,
        )

    files = [
        "tgrf_jax/env.py",
        "configs/default.yaml",
        "pyproject.toml",
        "docs/results.md",
        "tgrf_jax/pretrained/old/meta.json",
    ]
    for name in files:
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text("0\n")
    git("init", "-q")
    git("add", ".")
    git("commit", "-qm", "init")
    clean = runner.source_commit(tmp_path)
    assert len(clean) == 12 and "+" not in clean

    (tmp_path / "docs/results.md").write_text("1\n")  # a row's report
    (tmp_path / "docs/new_row").mkdir()
    (tmp_path / "docs/new_row/evals.csv").write_text("1\n")
    (tmp_path / "tgrf_jax/pretrained/old/meta.json").write_text("1\n")  # a re-exported policy
    (tmp_path / "tgrf_jax/pretrained/new").mkdir()
    (tmp_path / "tgrf_jax/pretrained/new/meta.json").write_text("1\n")
    assert runner.source_commit(tmp_path) == clean

    for change in ("tgrf_jax/env.py", "configs/default.yaml", "pyproject.toml", "tgrf_jax/new_module.py"):
        (tmp_path / change).write_text("2\n")
        assert runner.source_commit(tmp_path) == clean + "+dirty", change
        git("checkout", "-q", "--", ".")
        (tmp_path / "tgrf_jax/new_module.py").unlink(missing_ok=True)
        assert runner.source_commit(tmp_path) == clean
    assert runner.source_commit(tmp_path / "docs" / "new_row" / "not_a_dir") == "unknown"


def test_an_interrupted_row_invocation_is_recorded(tmp_path, monkeypatch):
    # Ctrl-C reaches tgrf-reproduce alone (its sweep child is still training): the child is asked to stop with a
    # checkpoint, its last lines are logged, and the invocation is recorded with the child's own exit code and the
    # commit of the code it started with (the tree may move on while a row trains).
    real_popen = runner.subprocess.Popen
    commands, lines = [], []

    def sweep_child(cmd, **kwargs):
        commands.append(cmd)
        return real_popen([sys.executable, "-c", SWEEP_CHILD], **kwargs)

    monkeypatch.setattr(runner.subprocess, "Popen", sweep_child)
    monkeypatch.setattr(runner, "source_commit", lambda: f"commit after {len(lines)} lines")
    exp = spec_lib.load(str(write_experiment(tmp_path / "exp.yaml")))
    row_dir = tmp_path / "out" / "mlp"
    (row_dir / "checkpoints" / "50").mkdir(parents=True)
    (row_dir / "sweep.yaml").write_text("{}")

    def ctrl_c_at_first_line(line):
        lines.append(line)
        if len(lines) % 2:
            raise KeyboardInterrupt

    for layout in (None, "sequential"):  # the second resumes switching the row's layout
        with pytest.raises(KeyboardInterrupt):
            runner.run_row(exp, exp.rows[0], row_dir, ctrl_c_at_first_line, layout)
    prov = json.loads((row_dir / "provenance.json").read_text())
    assert [i["exit_code"] for i in prov["invocations"]] == [130, 130] and prov["wall_s"] > 0
    assert [i["commit"] for i in prov["invocations"]] == ["commit after 0 lines", "commit after 2 lines"]
    assert prov["invocations"][0]["command"].startswith("tgrf-sweep --resume")
    assert commands[0][-2:] == ["--resume", str(row_dir)]
    assert commands[1][-4:] == ["--resume", str(row_dir), "--layout", "sequential"]
    assert lines == ["  mlp | update 5", "  mlp | stopped at update 7, with a checkpoint"] * 2


def test_sigterm_to_reproduce_stops_the_sweep_with_a_checkpoint_and_records_it(tmp_path, monkeypatch):
    # `kill` or a scheduler sends SIGTERM to tgrf-reproduce itself: like Ctrl-C, its sweep is asked to stop after
    # the running chunk (not orphaned to die on a closed pipe) and the invocation is recorded.
    import signal

    real_popen = runner.subprocess.Popen
    children = []

    def sweep_child(cmd, **kwargs):
        children.append(real_popen([sys.executable, "-c", SWEEP_CHILD], **kwargs))
        return children[-1]

    monkeypatch.setattr(runner.subprocess, "Popen", sweep_child)
    monkeypatch.setattr(runner, "source_commit", lambda: "abc")
    exp = spec_lib.load(str(write_experiment(tmp_path / "exp.yaml")))
    out = tmp_path / "out"
    (out / "mlp" / "checkpoints" / "50").mkdir(parents=True)
    (out / "mlp" / "sweep.yaml").write_text("{}")
    (out / "experiment.yaml").write_text(yaml.safe_dump(exp.to_dict(), sort_keys=False))  # the row's settings
    lines = []

    def terminate_at_first_sweep_line(line):
        lines.append(line)
        if line == "  mlp | update 5":
            signal_this_thread(signal.SIGTERM)

    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(KeyboardInterrupt):
        runner.reproduce(exp, out, log=terminate_at_first_sweep_line)
    assert signal.getsignal(signal.SIGTERM) is before
    assert [child.returncode for child in children] == [130]
    assert lines[-2:] == [
        "  mlp | stopped at update 7, with a checkpoint",
        "[exp] row mlp interrupted; rerun the same command to resume",
    ]
    prov = json.loads((out / "mlp" / "provenance.json").read_text())
    assert [i["exit_code"] for i in prov["invocations"]] == [130]
    assert (out / "reproduce.log").read_text().endswith("row mlp interrupted; rerun the same command to resume\n")


TRAINING_CHILD = """
import pathlib, sys, time
from tgrf_jax.cli.common import progress_line
from tgrf_jax.train.stop import stop_requests
with stop_requests() as stop:
    for update in range(1, 600):
        time.sleep(0.1)
        progress_line(f"update {update}")
        if stop:
            pathlib.Path(sys.argv[1]).write_text(f"checkpoint at update {update} after {stop.signal_name}")
            progress_line("stopped with a checkpoint")
            sys.exit(130)
"""

REPRODUCE_PARENT = """
import pathlib, sys
from tgrf_jax.experiments import runner, spec
child, marker = sys.argv[3], sys.argv[4]
real_popen = runner.subprocess.Popen
runner.source_commit = lambda: "abc"
runner.subprocess.Popen = lambda cmd, **kwargs: real_popen([sys.executable, "-c", child, marker], **kwargs)
exp = spec.load(sys.argv[1])
runner.run_row(exp, exp.rows[0], pathlib.Path(sys.argv[2]), lambda line: print(line, flush=True))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the parent-death signal is Linux's prctl")
def test_a_sweep_whose_reproduce_is_killed_stops_with_a_checkpoint(tmp_path):
    # tgrf-reproduce killed outright (SIGKILL, the OOM killer): its sweep is told to stop after the running chunk,
    # and neither that signal nor its next progress line on the closed pipe kills it before the checkpoint.
    import signal
    import subprocess
    import time

    marker = tmp_path / "checkpoint"
    parent = subprocess.Popen(
        [
            sys.executable,
            "-c",
            REPRODUCE_PARENT,
            str(write_experiment(tmp_path / "exp.yaml")),
            str(tmp_path / "row"),
            TRAINING_CHILD,
            str(marker),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        for line in parent.stdout:
            if "| update 2" in line:
                break
        parent.send_signal(signal.SIGKILL)
        parent.wait(timeout=30)
        deadline = time.monotonic() + 60
        while not marker.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert marker.read_text().startswith("checkpoint at update ")
        assert marker.read_text().endswith("after SIGTERM")
    finally:
        parent.kill()


def test_reproduce_runs_rows_writes_the_table_and_skips_finished_rows(tmp_path):
    exp = spec_lib.load(str(write_experiment(tmp_path / "exp.yaml"))).shrunk(seeds=1)
    out = tmp_path / "out"
    lines = []
    assert runner.reproduce(exp, out, log=lines.append, export_to=tmp_path / "pretrained") == 0
    assert "1 rows x 2 reward.scheme values x 1 seeds; 0 rows already done" in lines[0]
    for scheme in ("crowdnav_pp", "tgrf"):
        meta = json.loads((tmp_path / "pretrained" / f"exp-mlp-{scheme}" / "meta.json").read_text())
        assert meta["reward.scheme"] == scheme and meta["seed"] == 0 and 0.0 <= meta["test"]["success_rate"] <= 1.0
    with open(out / "report.csv", newline="") as f:
        records = {r["value"]: r for r in csv.DictReader(f)}
    assert set(records) == {"crowdnav_pp", "tgrf"}
    for rec in records.values():
        assert rec["seeds"] == "1" and 0.0 <= float(rec["sr_mean"]) <= 100.0 and rec["commit"]
    assert records["tgrf"]["paper_sr"] == "55.0" and records["crowdnav_pp"]["paper_sr"] == ""
    md = (out / "report.md").read_text()
    assert "Rows finished: 1/1" in md and "(55.0)" in md
    # A finished experiment: nothing is trained again.
    wall = (out / "mlp" / "provenance.json").read_text()
    lines.clear()
    assert runner.reproduce(exp, out, log=lines.append) == 0
    assert (out / "mlp" / "provenance.json").read_text() == wall
    assert not any("row 1/1" in line for line in lines)
    # Run as a selection of a larger experiment's rows, the report still covers all of them.
    whole = dataclasses.replace(exp, rows=exp.rows + (dataclasses.replace(exp.rows[0], name="later", label="Later"),))
    assert runner.reproduce(whole.shrunk(rows=["mlp"]), out, log=lines.append, report_exp=whole) == 0
    md = (out / "report.md").read_text()
    assert "Rows finished: 1/2" in md and "(55.0)" in md and "| Later |" in md
    # --report-only exports the finished rows' policies when asked to.
    assert (
        main(
            [
                str(tmp_path / "exp.yaml"),
                "--seeds",
                "1",
                "--out",
                str(out),
                "--report-only",
                "--export-pretrained",
                str(tmp_path / "again"),
            ]
        )
        == 0
    )
    assert sorted(p.name for p in (tmp_path / "again").iterdir()) == ["exp-mlp-crowdnav_pp", "exp-mlp-tgrf"]
    # Other settings into the same directory are refused.
    with pytest.raises(ConfigError, match="holds results of this experiment with other settings"):
        runner.reproduce(exp.shrunk(steps=512), out)


def _flat(d, prefix=""):
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def test_regime_isolation_rows_each_put_back_one_setting_of_the_paper_regime():
    """Every row of `regime_isolate` is the paper regime's `truth_small` row with one setting (a group, for the
    batch shape) at the default, apart from the budget and the test schedule; the default really differs there."""
    regime = spec_lib.load("paper_regime")
    base = _flat(spec_lib.sweep_spec(regime, regime.row("truth_small")).base)
    default = _flat(spec_lib.sweep_spec(spec_lib.load("table1"), spec_lib.load("table1").row("truth")).base)
    schedule = {"ppo.total_steps", "run.eval_every", "run.checkpoint_every"}
    expected = {
        "norm_value": {"ppo.norm_value"},
        "log_std": {"network.init_log_std"},
        "goal_frame": {"network.frame"},
        "batch": {"ppo.num_envs", "ppo.num_steps", "ppo.update_epochs", "ppo.num_minibatches", "ppo.reset_ratio"},
    }
    isolate = spec_lib.load("regime_isolate")
    assert [r.name for r in isolate.rows] == list(expected)
    for row in isolate.rows:
        cfg = _flat(spec_lib.sweep_spec(isolate, row).base)
        changed = {k for k in base if cfg[k] != base[k]} - schedule
        assert changed == expected[row.name], row.name
        assert all(cfg[k] == default[k] != base[k] for k in changed), row.name
        assert cfg["ppo.num_envs"] * cfg["ppo.num_steps"] * (
            cfg["ppo.total_steps"] // (cfg["ppo.num_envs"] * cfg["ppo.num_steps"])
        ) == pytest.approx(3.0e6, rel=1e-3)


def test_rows_with_a_test_are_played_there_beside_the_compared_policies(tmp_path):
    path = write_experiment(
        tmp_path / "exp.yaml",
        seeds=1,
        grid={"reward.scheme": ["tgrf"]},
        compare=["orca", "table1-const_vel-tgrf"],
        rows=[{"name": "mlp", "label": "MLP", "test": {"env.time_limit": 2.0}}],
    )
    exp = spec_lib.load(str(path))
    out = tmp_path / "out"
    lines = []
    assert runner.reproduce(exp, out, log=lines.append, export_to=tmp_path / "pretrained") == 0
    row = out / "mlp"
    (run,) = [p for p in (row / "runs").iterdir()]
    tested = json.loads((run / "test_eval.json").read_text())
    final = json.loads((run / "eval.json").read_text())
    assert tested["episodes"] == final["episodes"] == 4 and tested["seed"] == final["seed"]
    # the tests play 2-second episodes: never a success (the goal is at least 8 m away), every episode a timeout
    assert tested["results"]["learned"]["timeout_rate"] + tested["results"]["learned"]["collision_rate"] == 1.0
    assert final["results"]["learned"]["timeout_rate"] < 1.0
    orca = json.loads((row / "compare" / "orca.json").read_text())["results"]["orca"]
    shipped = json.loads((row / "compare" / "table1-const_vel-tgrf.json").read_text())["results"]["learned"]
    assert orca["n_episodes"] == shipped["n_episodes"] == 4 and orca["success_rate"] == 0.0
    # the report's numbers are the tests', and the compared policies sit beside them
    with open(out / "report.csv", newline="") as f:
        (record,) = list(csv.DictReader(f))
    assert float(record["sr_mean"]) == 0.0
    md = (out / "report.md").read_text()
    assert (
        "## On the test episodes" in md and "| mlp | orca | 1 |" in md and "| mlp | table1-const_vel-tgrf | 1 |" in md
    )
    meta = json.loads((tmp_path / "pretrained" / "exp-mlp-tgrf" / "meta.json").read_text())
    assert meta["test"]["success_rate"] == 0.0
    prov = json.loads((row / "test_provenance.json").read_text())
    assert [e["exit_code"] for e in prov] == [0, 0, 0] and prov[1]["command"].startswith("tgrf-eval --policy orca")
    # an interrupted test stage resumes where it stopped: only the missing evaluation is played again
    (row / "compare" / "orca.json").unlink()
    lines.clear()
    assert runner.reproduce(exp, out, log=lines.append) == 0
    assert any("trained, not yet tested" in line for line in lines)
    assert [line.split("| ")[1] for line in lines if "| test " in line] == ["test 1/1: orca"]
    assert len(json.loads((row / "test_provenance.json").read_text())) == 4

    # A changed test keeps the trained runs: the earlier results move aside, every test plays again.
    trainings = len(json.loads((row / "provenance.json").read_text())["invocations"])
    retest = write_experiment(
        tmp_path / "exp.yaml",
        seeds=1,
        grid={"reward.scheme": ["tgrf"]},
        compare=["orca", "table1-const_vel-tgrf"],
        rows=[{"name": "mlp", "label": "MLP, 3 s", "test": {"env.time_limit": 3.0}}],
    )
    lines.clear()
    assert runner.reproduce(spec_lib.load(str(retest)), out, log=lines.append) == 0
    assert len(json.loads((row / "provenance.json").read_text())["invocations"]) == trainings
    assert any("its test settings changed; its 3 earlier test results" in line for line in lines)
    assert len([line for line in lines if "| test " in line]) == 3
    (folder,) = list((row / "superseded_tests").iterdir())
    assert sorted(str(p.relative_to(folder)) for p in folder.rglob("*.json")) == sorted(
        [f"runs/{run.name}/test_eval.json", "compare/orca.json", "compare/table1-const_vel-tgrf.json"]
    )
    prov = json.loads((row / "test_provenance.json").read_text())
    (moved,) = [e for e in prov if "superseded" in e]
    assert moved["test_before"] == ["env.time_limit=2.0"] and moved["test_now"] == ["env.time_limit=3.0"]
    assert all("env.time_limit=3.0" in e["command"] for e in prov[-3:])
    assert (run / "test_eval.json").is_file() and (row / "compare" / "orca.json").is_file()
    recorded = yaml.safe_load((out / "experiment.yaml").read_text())
    assert recorded["rows"][0]["test"] == ["env.time_limit=3.0"]
    # the same settings again: nothing moves, nothing plays
    lines.clear()
    assert runner.reproduce(spec_lib.load(str(retest)), out, log=lines.append) == 0
    assert not [line for line in lines if "| test " in line or "settings changed" in line]
    # a changed training setting is still refused
    retrain = write_experiment(
        tmp_path / "exp.yaml",
        seeds=1,
        grid={"reward.scheme": ["tgrf"]},
        compare=["orca", "table1-const_vel-tgrf"],
        rows=[{"name": "mlp", "label": "MLP", "set": {"ppo.lr": 0.001}, "test": {"env.time_limit": 3.0}}],
    )
    with pytest.raises(ConfigError, match="row mlp differ"):
        runner.reproduce(spec_lib.load(str(retrain)), out)
