"""Search experiments (`layout: search`, `tgrf-reproduce tune`): rows of kind grid, tune and random, the paired
sweep a random row trains, and the report that compares the procedures at equal env steps."""

import csv
import json
import math
import pathlib

import numpy as np
import pytest
import yaml

from tgrf_jax.config import ConfigError
from tgrf_jax.experiments import runner, search
from tgrf_jax.experiments import spec as spec_lib
from tgrf_jax.sweep import SweepSpec
from tgrf_jax.tune.objective import parse_objective
from tgrf_jax.tune.run import ancestry_schedule

ROOT = pathlib.Path(__file__).resolve().parents[1]
TINY = str(ROOT / "configs" / "tiny.yaml")
SPACE = ["reward.h_disc=0.625:5.0:log", "reward.sigma_disc=0.1:0.5:log"]
OBJECTIVE = "success - 0.5 * collision"
SET = {"ppo.total_steps": 256, "run.eval_episodes": 4}  # tiny: 2 updates of 128 env steps
FINISHED = json.dumps({"wall_s": 60.0, "invocations": [{"commit": "c", "exit_code": 0, "finished": "t"}]})


def write_experiment(path, **changes):
    data = {
        "title": "tiny search",
        "layout": "search",
        "config": TINY,
        "set": dict(SET),
        "space": list(SPACE),
        "objective": OBJECTIVE,
        "rows": [
            {"name": "grid", "label": "grid", "kind": "grid", "results": "grid_sweep"},
            {"name": "pbt", "label": "PBT", "kind": "tune", "population": 4, "set": {"run.seed": 0}},
            {"name": "rand", "label": "random", "kind": "random", "draws": 4, "set": {"run.seed": 0}},
        ],
    }
    data.update(changes)
    path.write_text(yaml.safe_dump(data))
    return path


def write_grid(sweep_dir, success=(0.5, 0.6, 0.7, 0.8), overrides=(), seeds=1):
    """A finished 2 x 2 grid over the space as tgrf-sweep leaves it, with the given success rates (later seeds
    0.01 lower) and no collisions but at the first point (40%), without training it."""
    items = [f"{k}={v}" for k, v in SET.items()] + list(overrides)
    spec = SweepSpec.create(TINY, ["reward.h_disc=0.625,5.0", "reward.sigma_disc=0.1,0.5"], seeds, items)
    sweep_dir.mkdir(parents=True)
    (sweep_dir / "sweep.yaml").write_text(yaml.safe_dump(spec.to_dict(), sort_keys=False))
    fields = ["run", "point", "seed", "reward.h_disc", "reward.sigma_disc", "success_rate", "collision_rate"]
    with open(sweep_dir / "evals.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(fields)
        for r in spec.runs():
            sr = success[r.point] - 0.01 * (r.seed - spec.seeds[0])
            w.writerow([r.name, r.point, r.seed, *r.values.values(), sr, 0.4 if r.point == 0 else 0.0])
    (sweep_dir / "provenance.json").write_text(FINISHED)
    return spec


# --------------------------------------------------------------------------------------------- paired sweeps


def test_paired_axes_make_one_point_per_index():
    spec = SweepSpec.create(TINY, ["reward.h_disc=1,1,2", "reward.sigma_disc=0.1,0.2,0.1"], 1, paired=True)
    assert spec.points() == [
        {"reward.h_disc": 1.0, "reward.sigma_disc": 0.1},
        {"reward.h_disc": 1.0, "reward.sigma_disc": 0.2},
        {"reward.h_disc": 2.0, "reward.sigma_disc": 0.1},
    ]
    assert SweepSpec.from_dict(spec.to_dict()) == spec and spec.to_dict()["paired"] is True
    assert "paired" not in SweepSpec.create(TINY, ["reward.h_disc=1,2"], 1).to_dict()  # sweep.yaml as before


@pytest.mark.parametrize(
    "grid, message",
    [
        (["reward.h_disc=1,2", "reward.sigma_disc=0.1"], "reward.h_disc has 2, reward.sigma_disc has 1"),
        (["reward.h_disc=1,1", "reward.sigma_disc=0.1,0.1"], "the point h_disc=1, sigma_disc=0.1 is given twice"),
        ([], "give at least one --grid"),
    ],
)
def test_paired_axes_refuse_what_makes_no_points(grid, message):
    with pytest.raises(ConfigError, match=message):
        SweepSpec.create(TINY, grid, 1, paired=True)


# --------------------------------------------------------------------------------------------- the experiment file


def test_the_shipped_tune_experiment():
    exp = spec_lib.load("tune")
    assert exp.search and [r.kind for r in exp.rows] == ["grid"] + ["tune"] * 3 + ["random"] * 3
    assert exp.row("grid").results == str(ROOT / "docs" / "reproduction" / "sensitivity" / "const_vel")
    assert search.check_grid(exp, exp.row("grid")) is None  # the sensitivity map: same settings and budget
    for k in (1, 2, 3):
        pbt, rand = exp.row(f"pbt_{k}"), exp.row(f"random_{k}")
        tune = spec_lib.tune_spec(exp, pbt)
        assert tune.population == rand.members == 16
        # random repeat k starts where PBT repeat k starts, and trains 16 runs of the default budget each
        start = tune.initial_values()
        assert [list(v) for _, v in rand.grid] == [list(map(float, start[:, j])) for j in range(2)]
        sweep = spec_lib.sweep_spec(exp, rand)
        assert sweep.paired and len(sweep.runs()) == 16 and sweep.base_config.ppo.total_steps == 5_990_400
        for config in (tune.base_config, sweep.base_config):
            assert (config.run.eval_every, config.run.curve_episodes) == (156, config.run.eval_episodes)
    seeds = {spec_lib.row_config(exp, r).run.seed for r in exp.rows if r.kind == "tune"}
    assert len(seeds) == 3
    cmd = spec_lib.row_command(exp, exp.row("pbt_1"))
    assert cmd[:3] == ["tgrf-tune", "--space", SPACE[0]] and cmd[cmd.index("--objective") + 1] == OBJECTIVE
    assert "--paired" in spec_lib.row_command(exp, exp.row("random_1"))


def test_random_draws_are_deterministic_seeded_and_within_the_space(tmp_path):
    exp = spec_lib.load(str(write_experiment(tmp_path / "exp.yaml")))
    again = spec_lib.load(str(write_experiment(tmp_path / "again.yaml")))
    assert exp.row("rand").grid == again.row("rand").grid
    other = spec_lib.load(
        str(
            write_experiment(
                tmp_path / "other.yaml",
                rows=[{"name": "rand", "kind": "random", "draws": 4, "set": {"run.seed": 1}}],
            )
        )
    )
    assert other.row("rand").grid != exp.row("rand").grid
    (h_name, h), (s_name, s) = exp.row("rand").grid
    assert (h_name, s_name) == ("reward.h_disc", "reward.sigma_disc")
    assert all(0.625 <= v <= 5.0 for v in h) and all(0.1 <= v <= 0.5 for v in s)


def test_a_shortened_search_keeps_its_tests_every_tenth_and_its_interval_fitting(tmp_path):
    exp = spec_lib.load(str(write_experiment(tmp_path / "exp.yaml"))).shrunk(steps=128 * 20)
    assert spec_lib.tune_spec(exp, exp.row("pbt")).interval == 2
    assert spec_lib.row_config(exp, exp.row("rand")).run.eval_every == 2
    fixed = write_experiment(
        tmp_path / "fixed.yaml", rows=[{"name": "pbt", "kind": "tune", "population": 4, "interval": 1}]
    )
    with pytest.raises(ConfigError, match=r"row 'pbt': --interval 1: allowed 1 \.\. 0"):
        spec_lib.load(str(fixed)).shrunk(steps=128)
    with pytest.raises(ConfigError, match="--seeds: experiment 'exp' compares searches"):
        exp.shrunk(seeds=2)


TUNE_ROW = {"name": "a", "kind": "tune", "population": 4}


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"space": "reward.h_disc=1:2"}, "space must be a list of FIELD=LO:HI[:log] items"),
        ({"space": ["reward.h_dsic=1:2"]}, "space: --space reward.h_dsic: unknown config key"),
        ({"objective": 3}, "objective must be an expression over test metrics"),
        ({"objective": "succes"}, "objective: --objective 'succes': unknown metric"),
        ({"objective": "success + spl"}, "objective: 'spl' is not recorded by the tests during training"),
        ({"seeds": 2}, "seeds is not used by a search experiment"),
        ({"grid": {"reward.h_disc": [1.0]}}, "grid is not used by a search experiment"),
        ({"rows": [{"name": "a"}]}, "rows[0]: kind is missing; allowed: grid, tune, random"),
        ({"rows": [{"name": "a", "kind": "sweep"}]}, "rows[0]: kind = 'sweep' is not allowed"),
        ({"rows": [{"name": "a", "kind": "tune"}]}, "rows[0]: population is missing"),
        ({"rows": [{**TUNE_ROW, "population": 0}]}, "population = 0 must be an integer from 1 to 1,000"),
        ({"rows": [{**TUNE_ROW, "population": 1}]}, "row 'a': --population 1"),
        ({"rows": [{**TUNE_ROW, "draws": 4}]}, "unknown key(s) ['draws'] for a tune row"),
        ({"rows": [{"name": "a", "kind": "random", "draws": "x"}]}, "draws = 'x' must be an integer"),
        ({"rows": [{"name": "a", "kind": "grid"}]}, "results is missing"),
        ({"rows": [{"name": "a", "kind": "grid", "results": "x", "set": {}}]}, "unknown key(s) ['set']"),
        (
            {"rows": [{"name": "a", "kind": "grid", "results": "x"}, {"name": "b", "kind": "grid", "results": "y"}]},
            "rows a, b are all of kind grid",
        ),
        ({"rows": [{**TUNE_ROW, "set": {"ppo.lr": 0.002}}]}, "row 'a' sets ppo.lr; the rows of a search"),
        ({"rows": [{**TUNE_ROW, "set": {"ppo.lrr": 0.001}}]}, "unknown config key 'ppo.lrr'"),
    ],
)
def test_bad_search_experiments_are_refused_naming_the_field(tmp_path, changes, message):
    path = write_experiment(tmp_path / "exp.yaml", **changes)
    with pytest.raises(ConfigError) as e:
        spec_lib.load(str(path))
    assert message in str(e.value)


@pytest.mark.parametrize("key", ["space", "objective"])
def test_a_search_experiment_needs_its_space_and_objective(tmp_path, key):
    path = write_experiment(tmp_path / "exp.yaml")
    data = yaml.safe_load(path.read_text())
    del data[key]
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=f"a search experiment \\(layout: search\\) needs {key}"):
        spec_lib.load(str(path))


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"space": list(SPACE)}, "space belongs to a search experiment"),
        ({"rows": [{"name": "a", "kind": "tune", "population": 4}]}, "kind = 'tune' belongs to a search experiment"),
    ],
)
def test_search_settings_are_refused_elsewhere(tmp_path, changes, message):
    data = {
        "layout": "table",
        "config": TINY,
        "seeds": 1,
        "grid": {"reward.scheme": ["tgrf"]},
        "rows": [{"name": "a"}],
        **changes,
    }
    (tmp_path / "exp.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=message):
        spec_lib.load(str(tmp_path / "exp.yaml"))


def test_the_grid_must_be_a_finished_sweep_of_the_same_problem(tmp_path):
    exp = spec_lib.load(str(write_experiment(tmp_path / "exp.yaml")))
    row = exp.row("grid")
    with pytest.raises(ConfigError, match="is not a tgrf-sweep directory"):
        search.check_grid(exp, row)
    write_grid(tmp_path / "grid_sweep")
    assert search.check_grid(exp, row) is None
    note = search.check_grid(exp.shrunk(steps=512), exp.shrunk(steps=512).row("grid"))
    assert note == (
        "The grid's runs trained 256 env steps each, this experiment's rows 512: the procedures did not spend "
        "equal env steps."
    )
    (tmp_path / "grid_sweep" / "evals.csv").write_text("run,seed,success_rate\n")
    with pytest.raises(ConfigError, match="is not a finished sweep: evals.csv holds 0 runs, its sweep 4"):
        search.check_grid(exp, row)
    for overrides, message in (
        (["ppo.lr=0.01"], "ppo.lr = 0.01 there, 0.001 here"),
        (["run.eval_seed=3"], "run.eval_seed = 3 there, 0 here"),
    ):
        write_grid(tmp_path / "other" / message[:6], overrides=overrides)
        moved = write_experiment(
            tmp_path / "moved.yaml", rows=[{"name": "grid", "kind": "grid", "results": f"other/{message[:6]}"}]
        )
        exp2 = spec_lib.load(str(moved))
        with pytest.raises(ConfigError, match=message):
            search.check_grid(exp2, exp2.row("grid"))


def test_a_grid_outside_the_space_is_refused(tmp_path):
    write_grid(tmp_path / "grid_sweep")
    exp = spec_lib.load(
        str(write_experiment(tmp_path / "exp.yaml", space=["reward.h_disc=1:5:log", "reward.sigma_disc=0.1:0.5"]))
    )
    with pytest.raises(ConfigError, match=r"its reward.h_disc = 0.625 lies outside the space \(reward.h_disc=1.0"):
        search.check_grid(exp, exp.row("grid"))


# --------------------------------------------------------------------------------------------- the maths


def curve_rows(scores_by_update, steps_per_update=100):
    """Eval-curve rows whose objective (collision 0) is the given success rate, member by member."""
    return [
        {"run": f"m{i}", "update": u, "env_steps": u * steps_per_update, "success_rate": sr, "collision_rate": 0.0}
        for u, scores in scores_by_update.items()
        for i, sr in enumerate(scores)
    ]


def test_best_curve_steps_to_reach_and_the_grid_best():
    objective = parse_objective(OBJECTIVE)
    rows = curve_rows({1: [0.1, 0.3], 2: [0.5, 0.2], 3: [0.4, 0.9]})
    rows.append({"run": "m0", "update": 4, "env_steps": 400, "success_rate": 1.0, "collision_rate": 0.0})  # cut
    curve = search.best_curve(rows, objective, members=2)
    assert curve == ((200, 0.3), (400, 0.5), (600, 0.9))  # env steps of both members; the cut test left out
    assert search.steps_to_reach(curve, 0.5) == 400  # reaching counts: at least as good
    assert search.steps_to_reach(curve, 0.3) == 200
    assert search.steps_to_reach(curve, 0.95) is None

    def repeat(kind, name, values):
        members = tuple(search.Member(f"r{i}", v, {}, v, 0.0) for i, v in enumerate(values))
        return search.Repeat(name, name, name, kind, 100, members, ((100 * len(values), max(values)),))

    grid = [repeat("grid", "g0", [0.2, 0.7]), repeat("grid", "g1", [0.8, -math.inf])]
    tunes = [repeat("tune", "p1", [0.9, 0.1]), repeat("tune", "p2", [0.6, 0.5])]
    target, holder = search.grid_best(grid + tunes)
    assert target == 0.8 and holder.name == "g1" and holder.best.name == "r0"
    s = search.summary(tunes, target)
    assert s["repeats"] == 2 and s["env_steps"] == [200] and s["best"] == 0.9
    assert s["best_mean"] == pytest.approx(0.75) and s["best_std"] == pytest.approx(np.std([0.9, 0.6], ddof=1))
    assert s["to_target"] == [200, None]
    assert search.grid_best(tunes) is None


def write_tune(row_dir, exp, row, finals, curves, lineage, pick=0):
    """A finished tune row as tgrf-tune leaves it: tune.yaml, each member's eval.json and final config.yaml,
    eval_curves.csv, lineage.csv, the schedule of its pick (member `pick`) and tune.md."""
    spec = spec_lib.tune_spec(exp, row)
    row_dir.mkdir(parents=True)
    (row_dir / "tune.yaml").write_text(yaml.safe_dump(spec.to_dict(), sort_keys=False))
    steps = spec.base_config.ppo.num_updates * spec.base_config.ppo.batch_size
    for m, (sr, h) in zip(spec.members(), finals):
        (row_dir / "runs" / m.name).mkdir(parents=True)
        payload = {"results": {"learned": {"success_rate": sr, "collision_rate": 0.0}}, "env_steps": steps}
        (row_dir / "runs" / m.name / "eval.json").write_text(json.dumps(payload))
        config = m.config.to_dict()
        config["reward"]["h_disc"] = h
        (row_dir / "runs" / m.name / "config.yaml").write_text(yaml.safe_dump(config))
    fields = ["run", "update", "env_steps", "success_rate", "collision_rate"]
    with open(row_dir / "eval_curves.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        w.writerows(curve_rows(curves, steps_per_update=128))
    names = [d.name for d in spec.dims]
    with open(row_dir / "lineage.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["update", "member", "score", "donor", *names])
        w.writeheader()
        w.writerows(lineage)
    schedule = ancestry_schedule(spec, lineage, pick)
    with open(row_dir / "schedule.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["update", "member", *names])
        w.writeheader()
        w.writerows(schedule)
    (row_dir / "tune.md").write_text("# Tune\n")
    (row_dir / "provenance.json").write_text(FINISHED)
    return spec


def write_random(row_dir, exp, row, finals, curves):
    spec = spec_lib.sweep_spec(exp, row)
    row_dir.mkdir(parents=True)
    (row_dir / "sweep.yaml").write_text(yaml.safe_dump(spec.to_dict(), sort_keys=False))
    names = [a.name for a in spec.axes]
    with open(row_dir / "evals.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["run", "point", "seed", *names, "success_rate", "collision_rate"])
        for r, sr in zip(spec.runs(), finals):
            w.writerow([r.name, r.point, r.seed, *r.values.values(), sr, 0.0])
    rows = curve_rows(curves, steps_per_update=128)
    for r in rows:
        r["run"] = spec.runs()[int(r["run"][1:])].name
    with open(row_dir / "eval_curves.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    (row_dir / "provenance.json").write_text(FINISHED)


def test_the_report_compares_the_procedures_at_equal_env_steps(tmp_path):
    exp = spec_lib.load(str(write_experiment(tmp_path / "exp.yaml")))
    out = tmp_path / "out"
    # the grid: the best run scores 0.8 (its last point; the first scores 0.95 - 0.5 * 0.4)
    write_grid(tmp_path / "grid_sweep", success=(0.95, 0.6, 0.7, 0.8))
    out.mkdir()
    search.write(exp, out)
    md = (out / "report.md").read_text()
    assert "Rows finished: 1/3" in md and "**The grid's best**: 0.8000 (grid: h_disc = 5, sigma_disc = 0.5)" in md
    assert "| pbt | PBT | … |" in md and "| PBT | 0/1 | … |" in md

    # PBT reaches 0.8 at its second test (2 updates x 128 env steps x 4 members); random search never does
    lineage = [
        {
            "update": 1,
            "member": i,
            "score": 0.1 * i,
            "donor": 3 if i == 0 else i,
            "reward.h_disc": h,
            "reward.sigma_disc": 0.2,
        }
        for i, h in enumerate([4.0, 1.0, 2.0, 3.0])
    ]
    write_tune(
        out / "pbt",
        exp,
        exp.row("pbt"),
        [(0.85, 4.0), (0.5, 1.0), (0.6, 2.0), (0.7, 3.0)],
        {1: [0.2, 0.3, 0.4, 0.5], 2: [0.85, 0.5, 0.6, 0.7]},
        lineage,
        pick=3,  # PBT's own pick, on its selection episodes, is not the best member on the test
    )
    write_random(out / "rand", exp, exp.row("rand"), [0.3, 0.4, 0.5, 0.6], {1: [0.1] * 4, 2: [0.3, 0.4, 0.5, 0.6]})
    paths = search.write(exp, out)
    assert {p.name for p in paths} == {"report.md", "report.csv", "best_objective.png", "pbt_schedule.png"}
    with open(out / "report.csv", newline="") as f:
        recs = {r["repeat"]: r for r in csv.DictReader(f)}
    assert list(recs) == ["grid", "pbt", "rand"]
    grid, pbt, rand = recs["grid"], recs["pbt"], recs["rand"]
    assert grid["procedure"] == "grid" and grid["env_steps"] == str(4 * 256) and grid["reached_grid_best"] == "True"
    assert float(grid["best_objective"]) == pytest.approx(0.8) and grid["env_steps_to_grid_best"] == str(4 * 256)
    assert pbt["procedure"] == "pbt" and float(pbt["best_objective"]) == pytest.approx(0.85)
    assert pbt["best_member"] == "m000" and float(pbt["reward.h_disc"]) == 4.0  # its value at the end
    assert pbt["own_pick"] == "m003" and float(pbt["own_pick_objective"]) == pytest.approx(0.7)
    assert grid["own_pick"] == "" and rand["own_pick_objective"] == ""
    assert pbt["env_steps_to_grid_best"] == str(2 * 128 * 4) and pbt["row_wall_s"] == "60.0"
    assert rand["reached_grid_best"] == "False" and rand["env_steps_to_grid_best"] == ""
    assert float(rand["best_objective"]) == pytest.approx(0.6) and rand["members"] == "4"
    md = (out / "report.md").read_text()
    assert "Rows finished: 3/3" in md
    assert "| PBT | 1/1 | 1,024 | 0.8500 | 0.8500 | 0.7000 | 1/1 | 1,024 |" in md
    assert "| random | 1/1 | 1,024 | 0.6000 | 0.6000 | – | 0/1 | not reached |" in md
    assert "| 0.8500 | m000 | 4 | " in md and "| 85.0 | 0.0 | m003: 0.7000 | 1,024 |" in md
    # the schedule is the pick's: m003 kept its own values at update 1, from its own draw
    start = spec_lib.tune_spec(exp, exp.row("pbt")).members()[3].values
    assert "## The schedule PBT found" in md and "pbt (m003: 0.7000)" in md
    assert f"| 0 | m003 | {start['reward.h_disc']:.4g} |" in md and "| 1 | m003 | 3 | 0.2 |" in md
    assert "| 1 | m000 |" not in md and "![the schedule of the best PBT repeat](pbt_schedule.png)" in md

    # a damaged row is named, never reported
    (out / "rand" / "evals.csv").write_text("run,seed,success_rate\nx,0,abc\n")
    search.write(exp, out)
    assert (
        "| rand | random | damaged (evals.csv holds 1 runs, its sweep 4): rerun tgrf-reproduce exp --rows rand"
        in (out / "report.md").read_text()
    )


def test_tune_rows_are_done_with_their_results_and_provenance(tmp_path):
    row = tmp_path / "pbt"
    assert runner.row_state(row, "tune") == "new"
    row.mkdir()
    (row / "tune.yaml").write_text("members: [{name: m000}]\n")
    assert runner.row_state(row, "tune") == "stale"
    (row / "checkpoints" / "0").mkdir(parents=True)
    assert runner.row_state(row, "tune") == "resumable"
    (row / "tune.md").write_text("# Tune\n")
    assert runner.row_state(row, "tune") == "damaged"
    assert "schedule.csv is missing or does not name one of the 1 members last" in runner.row_problem(row, "tune")
    (row / "schedule.csv").write_text("update,member,reward.h_disc\n0,1,2.5\n")  # no member 1 in a population of 1
    assert "schedule.csv is missing" in runner.row_problem(row, "tune")
    (row / "schedule.csv").write_text("update,member,reward.h_disc\n0,0,2.5\n")
    assert "runs/m000/eval.json is missing or damaged" in runner.row_problem(row, "tune")
    (row / "runs" / "m000").mkdir(parents=True)
    (row / "runs" / "m000" / "eval.json").write_text(json.dumps({"results": {"learned": {"success_rate": 0.5}}}))
    assert runner.row_problem(row, "tune").startswith("provenance.json does not record")
    (row / "provenance.json").write_text(FINISHED)
    assert runner.row_state(row, "tune") == "done"
    assert runner.row_state(tmp_path / "anything", "grid") == "read"


# --------------------------------------------------------------------------------------------- end to end


@pytest.mark.slow  # trains a tune and a random search: training runs, kept out of CI
def test_a_shrunk_search_runs_end_to_end_and_skips_what_is_done(tmp_path):
    exp = spec_lib.load(str(write_experiment(tmp_path / "exp.yaml")))
    write_grid(tmp_path / "grid_sweep")
    out, lines = tmp_path / "out", []
    assert runner.reproduce(exp.shrunk(rows=["grid", "pbt"]), out, log=lines.append, report_exp=exp) == 0
    assert "grid row grid read from" in lines[0] and "1 tune row x 4 members" in lines[0]
    assert runner.row_state(out / "pbt", "tune") == "done" and runner.row_state(out / "rand", "random") == "new"
    assert "Rows finished: 2/3" in (out / "report.md").read_text()
    lines.clear()
    assert runner.reproduce(exp, out, log=lines.append) == 0
    assert "2 rows already done" in lines[0] and not any("row 1/" in line or "(pbt)" in line for line in lines[1:])
    assert runner.row_state(out / "rand", "random") == "done"
    prov = json.loads((out / "pbt" / "provenance.json").read_text())
    assert prov["invocations"][0]["command"].startswith(
        "tgrf-tune configs/tiny.yaml --space reward.h_disc=0.625:5.0:log"
    )
    with open(out / "report.csv", newline="") as f:
        recs = {r["repeat"]: r for r in csv.DictReader(f)}
    assert set(recs) == {"grid", "pbt", "rand"}
    for rec in recs.values():
        assert rec["env_steps"] == str(4 * 256) and -0.5 <= float(rec["best_objective"]) <= 1.0
    assert (out / "best_objective.png").is_file() and (out / "pbt_schedule.png").is_file()
    # every procedure was tested on the same episodes: the random row's sweep and the tune test as the grid
    tune_cfg = yaml.safe_load((out / "pbt" / "config.yaml").read_text())["run"]
    sweep_cfg = yaml.safe_load((out / "rand" / "config.yaml").read_text())["run"]
    for run in (tune_cfg, sweep_cfg):
        assert (run["eval_every"], run["curve_episodes"], run["eval_episodes"], run["eval_seed"]) == (1, 4, 4, 0)
