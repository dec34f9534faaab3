"""A catalogue of bad inputs to the command-line tools: config keys, types and ranges, config files, grids, seeds,
output paths, run directories and checkpoints. Each must end the tool with exit status 2 and one error naming the
field or path (and what is allowed), before anything is compiled: no output written, no traceback.

The tools run in this process (`main(argv)`); a jax.monitoring listener counts compilations. Cases that read a
checkpoint trace the state's shapes (`jax.eval_shape`), so only they may trace; none may compile.
"""

import math
import pathlib
import re
import shutil

import jax
import pytest
from helpers import CompileCounter, flip_a_bit

from tgrf_jax.cli import (
    eval_main,
    predictor_main,
    render_main,
    reproduce_main,
    sweep_main,
    train_main,
)

ROOT = pathlib.Path(__file__).resolve().parents[1]
TINY = str(ROOT / "configs" / "tiny.yaml")


MAINS = {
    "tgrf-train": train_main,
    "tgrf-eval": eval_main,
    "tgrf-sweep": sweep_main,
    "tgrf-render": render_main,
    "tgrf-reproduce": reproduce_main,
    "tgrf-predictor": predictor_main,
}
# a polygon of 33 vertices (one beyond config.MAX_POLYGON_VERTICES), rounded to 3 decimals
_CIRCLE_33 = [(round(math.cos(2 * math.pi * k / 33), 3), round(math.sin(2 * math.pi * k / 33), 3)) for k in range(33)]
UNWRITABLE = "/sys/tgrf-out"  # the kernel refuses new files under /sys, even to root
FRESH = "{tmp}/fresh"  # an output path that must still not exist after the error


def train(*sets, out=FRESH):
    return ["tgrf-train", [TINY, *sum((["--set", s] for s in sets), []), "--out-dir", out]]


def sweep(*args, out=FRESH):
    return ["tgrf-sweep", [*args, "--out", out]]


def evaluate(*args):
    return ["tgrf-eval", [*args, "--episodes", "2", "--out", FRESH + "/eval.json"]]


def render(*args, out=FRESH):
    return ["tgrf-render", [*args, "--out", out]]


CASES = {
    # ---- config keys
    "unknown key": (*train("ppo.lrr=1e-3"), "unknown config key 'ppo.lrr' (did you mean 'lr'?); valid keys: num_envs"),
    "unknown section": (*train("envv.dt=0.1"), "unknown config key 'envv' (did you mean 'env'?)"),
    "unknown env key": (*train("env.num_human=3"), "unknown config key 'env.num_human' (did you mean 'num_humans'?)"),
    "unknown reward key": (*train("reward.hdisc=1"), "unknown config key 'reward.hdisc' (did you mean 'h_disc'?)"),
    "unknown network key": (*train("network.sise=paper"), "unknown config key 'network.sise'"),
    "unknown run key": (*train("run.sed=3"), "unknown config key 'run.sed'"),
    "section given a value": (*train("ppo=3"), "ppo must be a mapping of PPOConfig fields"),
    "override without a value": (*train("ppo.lr"), "override 'ppo.lr' must look like section.field=value"),
    "eval: key of another tool": (
        *evaluate(TINY, "--set", "ppo.lr=0.1"),
        "only those can be overridden, not ['ppo.lr=0.1']",
    ),
    "eval: run dir override": (
        *evaluate("{run}", "--set", "run.seed=3"),
        "with a RUN_DIR only env.* and reward.* can be overridden",
    ),
    "eval: unknown section": (*evaluate("{tmp}/foo.yaml"), "unknown config section(s) ['foo']"),
    # ---- types
    "float for an integer": (*train("env.num_humans=2.5"), "env.num_humans = 2.5 must be an integer"),
    "word for an integer": (*train("ppo.num_steps=many"), "ppo.num_steps = 'many' must be an integer"),
    "word for a number": (*train("env.dt=fast"), "env.dt = 'fast' must be a number"),
    "word for a boolean": (*train("env.robot_visible=maybe"), "env.robot_visible = 'maybe' must be a boolean"),
    "boolean for an integer": (*train("ppo.num_envs=true"), "ppo.num_envs = True must be an integer"),
    "list for a string": (*train("run.name=[1,2]"), "run.name = [1, 2] must be a string"),
    "word for a reward": (*train("reward.h_disc=abc"), "reward.h_disc = 'abc' must be a number"),
    "number for a choice": (*train("env.human_policy=3"), "env.human_policy = 3 must be a string"),
    "choice misspelt": (
        *train("env.human_policy=sfm"),
        "env.human_policy = 'sfm' is not allowed; allowed: one of 'orca', 'social_force'",
    ),
    # ---- ranges
    "dt tiny": (*train("env.dt=1e-30"), "env.dt = 1e-30 is out of range; allowed: >= 0.01 and <= 1.0"),
    "dt zero": (*train("env.dt=0"), "env.dt = 0.0 is out of range; allowed: >= 0.01 and <= 1.0"),
    "dt negative": (*train("env.dt=-0.1"), "env.dt = -0.1 is out of range"),
    "dt large": (*train("env.dt=2"), "env.dt = 2.0 is out of range"),
    "dt nan": (*train("env.dt=.nan"), "env.dt = nan must be finite"),
    "time limit huge": (
        *train("env.time_limit=1e9"),
        "env.time_limit = 1000000000.0 is out of range; allowed: > 0.0 and <= 1000.0",
    ),
    "time limit under dt": (*train("env.time_limit=0.1"), "env.time_limit = 0.1 must be >= env.dt = 0.25"),
    "goal change interval huge": (*train("env.goal_change_interval=1e30"), "env.goal_change_interval = 1e+30 is out"),
    "too many humans": (*train("env.num_humans=101"), "env.num_humans = 101 is out of range; allowed: >= 0 and <= 100"),
    "scenario weights beyond float32": (
        *train("env.scenario=mix", "env.mix_scenarios=[circle_crossing,random]", "env.scenario_weights=[1e39,1]"),
        "env.scenario_weights = [1e+39, 1.0] has a weight beyond float32's range (inf); allowed: 2 finite, "
        "non-negative numbers, one per scenario of the mix (circle_crossing, random), at least one of them positive",
    ),
    "scenario weights zero in float32": (
        *train("env.scenario=mix", "env.mix_scenarios=[circle_crossing,random]", "env.scenario_weights=[1e-46,0]"),
        "env.scenario_weights = [1e-46, 0.0] are all zero (in float32); allowed: 2 finite, non-negative numbers",
    ),
    "eval: scenario weights beyond float32": (
        *evaluate(
            TINY,
            "--set",
            "env.scenario=mix",
            "--set",
            "env.mix_scenarios=[circle_crossing,random]",
            "--set",
            "env.scenario_weights=[1e39,1]",
        ),
        "env.scenario_weights = [1e+39, 1.0] has a weight beyond float32's range (inf)",
    ),
    "scenario weights without a mix": (
        *train("env.scenario_weights=[1e39,1]"),
        "env.scenario_weights = ['1e39', 1] is given but env.scenario = 'circle_crossing' is not 'mix', which "
        "alone reads it; allowed: null (or env.scenario: mix)",
    ),
    "mix scenarios without a mix": (
        *train("env.scenario=corridor", "env.mix_scenarios=[corridor,doorway]"),
        "env.mix_scenarios = ['corridor', 'doorway'] is given but env.scenario = 'corridor' is not 'mix'",
    ),
    "polygon of too many vertices": (
        *train("env.obstacles=[[" + ",".join(f"[{x},{y}]" for x, y in _CIRCLE_33) + "]]"),
        "has 33 vertices; allowed: at most 32",
    ),
    "too many obstacle slots": (
        *train("env.scenario=corridor", "env.obstacles=[" + ",".join(["[[0,0],[1,0]]"] * 25) + "]"),
        "env.obstacles has 25 polygons; allowed: at most 24 (32 obstacle slots in all, of which the scenario draws "
        "into 8)",
    ),
    "too many obstacle edges": (
        *train("env.scenario=corridor", "env.obstacles=[[" + ",".join(f"[{x},{y}]" for x, y in _CIRCLE_33[::2]) + "]]"),
        "env.obstacles makes 9 obstacle slots of 17 vertices (each slot holds as many as the longest polygon), 153 "
        "edge slots; allowed: at most 128",
    ),
    "negative humans": (*train("env.num_humans=-1"), "env.num_humans = -1 is out of range"),
    "no humans to predict": (
        *train("env.num_humans=0", "env.predictor=const_vel"),
        "env.predictor = 'const_vel' needs humans to predict, but env.num_humans = 0",
    ),
    "negative radius": (*train("env.robot_radius=-0.3"), "env.robot_radius = -0.3 is out of range; allowed: > 0.0"),
    "min above max": (*train("env.human_radius_min=0.6"), "env.human_radius_min = 0.6 must be <= env.human_radius_max"),
    "goal too far": (*train("env.min_start_goal_dist=100"), "env.min_start_goal_dist = 100.0 cannot be met"),
    "probability above 1": (*train("env.goal_change_prob=1.5"), "env.goal_change_prob = 1.5 is out of range"),
    "prediction horizon 0": (*train("env.pred_horizon=0"), "env.pred_horizon = 0 is out of range; allowed: >= 1"),
    "gst horizon": (*train("env.predictor=gst", "env.pred_horizon=4"), "env.pred_horizon = 4 must be 5"),
    "total steps 1e20": (
        *train("ppo.total_steps=1e20"),
        "ppo.total_steps = 100000000000000000000 is out of range; allowed: >= 1 and <= 10000000000",
    ),
    "updates beyond int32": (
        *train(
            "ppo.total_steps=1e10", "ppo.num_envs=1", "ppo.num_steps=1", "ppo.num_shards=1", "ppo.num_minibatches=1"
        ),
        "allowed: <= 2,147,483,647 (2,147,483,647 updates)",
    ),
    "less than one update": (*train("ppo.total_steps=10"), "ppo.total_steps = 10 is less than one update"),
    "learning rate 2": (*train("ppo.lr=2"), "ppo.lr = 2.0 is out of range; allowed: > 0.0 and <= 1.0"),
    "negative learning rate": (*train("ppo.lr=-1"), "ppo.lr = -1.0 is out of range; allowed: > 0.0 and <= 1.0"),
    "negative clip": (*train("ppo.clip_eps=-0.1"), "ppo.clip_eps = -0.1 is out of range; allowed: > 0.0"),
    "gamma above 1": (*train("ppo.gamma=1.5"), "ppo.gamma = 1.5 is out of range"),
    "envs not divisible": (*train("ppo.num_envs=10"), "ppo.num_envs = 10 must be divisible by ppo.num_shards"),
    "zero sigma": (*train("reward.sigma_disc=0"), "reward.sigma_disc = 0.0 is out of range; allowed: > 0.0"),
    "positive collision reward": (*train("reward.r_col=5"), "reward.r_col = 5.0 is out of range; allowed: <= 0.0"),
    "negative TGRF height": (*train("reward.h_disc=-1"), "reward.h_disc = -1.0 is out of range; allowed: >= 0.0"),
    "unknown scheme": (*train("reward.scheme=scan"), "reward.scheme = 'scan' is not allowed"),
    "network size": (
        *train("network.size=huge"),
        "network.size = 'huge' is not allowed; allowed: one of 'paper', 'small'",
    ),
    "network name": (
        *train("network.name=transformer"),
        "network.name = 'transformer' is not allowed; allowed: one of 'hh_attn', 'dsrnn', 'mlp'",
    ),
    "log std": (*train("network.init_log_std=9"), "network.init_log_std = 9.0 is out of range"),
    "negative seed": (*train("run.seed=-1"), "run.seed = -1 is out of range"),
    "eval episodes huge": (
        *train("run.eval_episodes=1e9"),
        "run.eval_episodes = 1000000000 is out of range; allowed: >= 0 and <= 10000000",
    ),
    "keep no checkpoint": (*train("run.keep_checkpoints=0"), "run.keep_checkpoints = 0 is out of range"),
    "render: episode too long": (
        *render("--policy", "orca", "--set", "env.time_limit=1e9"),
        "env.time_limit = 1000000000.0 is out of range; allowed: > 0.0 and <= 1000.0",
    ),
    "eval: dt tiny": (*evaluate("--policy", "straight", "--set", "env.dt=1e-30"), "env.dt = 1e-30 is out of range"),
    "eval: too many episodes": (
        "tgrf-eval",
        ["--episodes", "400000000"],
        "--episodes = 400000000 is out of range; allowed: 1 .. 10,000,000",
    ),
    # ---- config files
    "missing file": ("tgrf-train", ["{tmp}/nope.yaml"], "config file '{tmp}/nope.yaml' does not exist"),
    "directory as config": ("tgrf-train", ["{tmp}/adir"], "config file '{tmp}/adir' is a directory, not a YAML file"),
    "not UTF-8": ("tgrf-train", ["{tmp}/latin1.yaml"], "config file '{tmp}/latin1.yaml' is not UTF-8 text"),
    "duplicate key": ("tgrf-train", ["{tmp}/dup.yaml"], "found duplicate key 'ppo' (first given on line 1)"),
    "invalid YAML": ("tgrf-train", ["{tmp}/broken.yaml"], "config file '{tmp}/broken.yaml' is not valid YAML"),
    "list at the top": ("tgrf-train", ["{tmp}/list.yaml"], "'{tmp}/list.yaml' must hold a mapping at the top level"),
    "eval: missing file": (*evaluate("{tmp}/nope.yaml"), "config file '{tmp}/nope.yaml' does not exist"),
    "sweep: missing file": (
        "tgrf-sweep",
        ["{tmp}/nope.yaml", "--grid", "reward.h_disc=1,2"],
        "config file '{tmp}/nope.yaml' does not exist",
    ),
    # ---- grids and seeds
    "grid of a static field": (
        *sweep(TINY, "--grid", "ppo.num_envs=8,16"),
        "--grid ppo.num_envs: cannot be gridded: it is a static setting",
    ),
    "grid of a network size": (
        *sweep(TINY, "--grid", "network.size=small,paper"),
        "--grid network.size: cannot be gridded",
    ),
    "grid of the crowd size": (
        *sweep(TINY, "--grid", "env.num_humans=2,4"),
        "run one sweep per value instead. Griddable (traced) fields: ppo.lr, ppo.gamma",
    ),
    "grid of seeds": (
        *sweep(TINY, "--grid", "run.seed=0,1"),
        "--grid 'run.seed=0,1': seeds are not a grid axis; give them with --seeds N",
    ),
    "grid key misspelt": (
        *sweep(TINY, "--grid", "reward.h_dsc=1,2"),
        "unknown config key 'reward.h_dsc' (did you mean 'reward.h_disc'?)",
    ),
    "grid without values": (*sweep(TINY, "--grid", "reward.h_disc"), "must look like section.field=v1,v2"),
    "grid empty value": (*sweep(TINY, "--grid", "reward.h_disc=1,,2"), "--grid 'reward.h_disc=1,,2': empty value"),
    "grid repeated value": (
        *sweep(TINY, "--grid", "reward.h_disc=1,1.0"),
        "--grid reward.h_disc: repeated value(s) 1.0",
    ),
    "grid value out of range": (
        *sweep(TINY, "--grid", "reward.sigma_disc=0.2,-1"),
        "--grid reward.sigma_disc=-1: reward.sigma_disc = -1.0 is out of range",
    ),
    "grid dt tiny": (*sweep(TINY, "--grid", "env.dt=0.25,1e-30"), "--grid env.dt=1e-30: env.dt = 1e-30 is out"),
    "grid learning rate 2": (
        *sweep(TINY, "--grid", "ppo.lr=1e-3,2"),
        "--grid ppo.lr=2: ppo.lr = 2.0 is out of range; allowed: > 0.0 and <= 1.0",
    ),
    "grid word for a number": (
        *sweep(TINY, "--grid", "reward.h_disc=1,x"),
        "--grid reward.h_disc=x: reward.h_disc = 'x' must be a number",
    ),
    "sweep: unknown key": (*sweep(TINY, "--set", "ppo.lrr=1"), "unknown config key 'ppo.lrr' (did you mean 'lr'?)"),
    "grid axis twice": (
        *sweep(TINY, "--grid", "reward.h_disc=1", "--grid", "reward.h_disc=2"),
        "--grid reward.h_disc is given twice",
    ),
    "zero seeds": (*sweep(TINY, "--seeds", "0"), "--seeds 0: the number of seeds must be >= 1"),
    "negative seed in a list": (*sweep(TINY, "--seeds=-1,2"), "run.seed = -1 is out of range"),
    "repeated seed": (*sweep(TINY, "--seeds", "3,3"), "--seeds 3,3: repeated seed"),
    "seeds not a number": (*sweep(TINY, "--seeds", "abc"), "--seeds 'abc' must be a count"),
    "eval: negative seed": (*evaluate("--seed", "-1"), "--seed = -1 is out of range; allowed: 0 .. 2147483647"),
    "render: seed too large": (*render("--policy", "orca", "--seed", str(2**40)), f"--seed = {2**40} is out of range"),
    # ---- output paths and run directories
    "train: out-dir is a file": (
        *train(out="{tmp}/occupied"),
        "--out-dir '{tmp}/occupied' exists and is not a directory",
    ),
    "train: out-dir under a file": (
        *train(out="{tmp}/occupied/run"),
        "--out-dir '{tmp}/occupied/run' cannot be created: '{tmp}/occupied' is a file",
    ),
    "train: out-dir unwritable": (*train(out=UNWRITABLE), f"--out-dir '{UNWRITABLE}' is not writable"),
    "train: out-dir holds a run": (*train(out="{run}"), "run directory '{run}' already holds a run; use --resume"),
    "sweep: out is a file": (
        *sweep(TINY, out="{tmp}/occupied"),
        "--out '{tmp}/occupied' exists and is not a directory",
    ),
    "sweep: out unwritable": (*sweep(TINY, out=UNWRITABLE), f"--out '{UNWRITABLE}' is not writable"),
    "eval: out is a directory": (
        "tgrf-eval",
        ["--episodes", "2", "--out", "{tmp}/adir"],
        "--out '{tmp}/adir' is a directory; give a file name",
    ),
    "eval: out under a file": (
        "tgrf-eval",
        ["--episodes", "2", "--out", "{tmp}/occupied/e.json"],
        "cannot be created: '{tmp}/occupied' is a file",
    ),
    "eval: out unwritable": (
        "tgrf-eval",
        ["--episodes", "2", "--out", UNWRITABLE + "/e.json"],
        f"--out '{UNWRITABLE}/e.json' is not writable",
    ),
    "render: out is a file": (
        *render("--policy", "orca", out="{tmp}/occupied"),
        "--out '{tmp}/occupied' exists and is not a directory",
    ),
    "render: out unwritable": (*render("--policy", "orca", out=UNWRITABLE), f"--out '{UNWRITABLE}' is not writable"),
    "reproduce: out is a file": (
        "tgrf-reproduce",
        ["table1", "--out", "{tmp}/occupied"],
        "--out '{tmp}/occupied' is a file, not a directory",
    ),
    "reproduce: out unwritable": (
        "tgrf-reproduce",
        ["table1", "--out", UNWRITABLE],
        f"--out '{UNWRITABLE}' is not writable",
    ),
    "predictor: dataset unwritable": (
        "tgrf-predictor",
        ["collect", "--out", UNWRITABLE + "/d.npz"],
        f"--out '{UNWRITABLE}/d.npz' is not writable",
    ),
    "predictor: run dir is a file": (
        "tgrf-predictor",
        ["train", "--dataset", "{tmp}/d.npz", "--run-dir", "{tmp}/occupied"],
        "--run-dir '{tmp}/occupied' exists and is not a directory",
    ),
    "resume: not a run": ("tgrf-train", ["--resume", "{tmp}/adir"], "is not a tgrf-train run directory"),
    "resume: not a sweep": ("tgrf-sweep", ["--resume", "{tmp}/adir"], "is not a tgrf-sweep directory"),
    "sweep: resume with --grid": (
        "tgrf-sweep",
        ["--resume", "{tmp}/adir", "--grid", "reward.h_disc=1,2"],
        "--resume SWEEP_DIR takes no config file, --grid",
    ),
    "resume with --set": (
        "tgrf-train",
        ["--resume", "{run}", "--set", "ppo.lr=1e-3"],
        "--resume RUN_DIR takes no config file, --set or --out-dir",
    ),
    "from-step without resume": (
        "tgrf-train",
        [TINY, "--from-step", "4"],
        "--from-step N continues a run from one of its checkpoints: it needs --resume RUN_DIR",
    ),
    "resume of an edited config": (
        "tgrf-train",
        ["--resume", "{edited}"],
        "was edited since the run started; on --resume only ppo.total_steps may change",
    ),
    "eval: step of a config": (*evaluate(TINY, "--step", "3"), "--step selects a checkpoint of a RUN_DIR"),
    # ---- checkpoints
    "eval: no such step": (
        *evaluate("{run}", "--step", "5"),
        "checkpoint '{run}/checkpoints/5' does not exist (available steps: [0])",
    ),
    "eval: damaged": (*evaluate("{damaged}"), "checkpoint '{damaged}/checkpoints/0' (step 0) is damaged"),
    "eval: unreadable": (
        *evaluate("{garbage}"),
        "checkpoint '{garbage}/checkpoints/0' (step 0) is damaged: it cannot be read",
    ),
    "eval: network mismatch": (
        *evaluate("{mismatch}"),
        "checkpoint '{mismatch}/checkpoints/0' does not fit this config: opt_state: ",
    ),
    "eval: no checkpoints": (*evaluate("{nockpt}"), "checkpoint directory '{nockpt}/checkpoints' does not exist"),
    "render: damaged": (*render("{damaged}"), "checkpoint '{damaged}/checkpoints/0' (step 0) is damaged"),
    "render: network mismatch": (*render("{mismatch}"), "params: 10,565 values in the checkpoint, 140,549 here"),
    "train: resume damaged": (
        "tgrf-train",
        ["--resume", "{damaged}"],
        "checkpoint '{damaged}/checkpoints/0' (step 0) is damaged: its content does not match "
        "the checksum written with it; no earlier step is intact",
    ),
    "train: from an absent step": (
        "tgrf-train",
        ["--resume", "{run}", "--from-step", "3"],
        "--from-step 3: '{run}/checkpoints' holds no checkpoint of update 3; it holds: 0",
    ),
    "sweep: from an absent step": (
        "tgrf-sweep",
        ["--resume", "{sweep}", "--from-step", "3"],
        "--from-step 3: '{sweep}/checkpoints' holds no checkpoint of update 3; it holds: none",
    ),
    "sweep: negative from-step": (
        "tgrf-sweep",
        ["--resume", "{sweep}", "--from-step", "-1"],
        "--from-step = -1 must be >= 0",
    ),
    # ---- values, names and files that must be checked with a message, not trusted or left to a traceback
    "integer YAML key": ("tgrf-train", ["{tmp}/int_key.yaml"], "unknown config key '1'; valid keys: env"),
    "list nested 5000 deep": ("tgrf-train", ["{tmp}/deep.yaml"], "config file '{tmp}/deep.yaml' is nested too deeply"),
    "quoted number": (
        "tgrf-train",
        ["{tmp}/quoted.yaml"],
        "env.num_humans = '5' must be an integer (it is quoted text; give the number without quotes)",
    ),
    "comment in --set": (*train("ppo.lr=1 # c"), "override 'ppo.lr=1 # c': the value holds a YAML comment"),
    "run name of 5000 characters": (
        *train("run.name=" + "x" * 5000),
        "(5,000 chars) is not allowed; allowed: 1 to 200",
    ),
    "run name with a separator": (*train("run.name=a/b"), "run.name = 'a/b' is not allowed"),
    "run name escaping": (*train("run.name=../../escape"), "run.name = '../../escape' is not allowed"),
    "run name empty": (*train("run.name=''"), "run.name = '' is not allowed"),
    "a 10 MB value": (*train("env.human_policy=" + "z" * 10_000_000), "zzz... (10,000,002 characters) is not allowed"),
    "human radius 50 m": (
        *train("env.human_radius_min=50", "env.human_radius_max=100"),
        "env.human_radius_min = 50.0 is out of range; allowed: > 0.0 and <= 2.0",
    ),
    "goal tolerance 50 m": (
        *train("env.goal_tolerance=50"),
        "env.goal_tolerance = 50.0 is out of range; allowed: > 0.0 and <= 2.0",
    ),
    "sensor range 1e9": (
        *train("env.sensor_range=1.0e9"),
        "env.sensor_range = 1000000000.0 is out of range; allowed: >= 0.0 and <= 100.0",
    ),
    "train: resume without a digest": (
        "tgrf-train",
        ["--resume", "{nodigest}"],
        "checkpoint '{nodigest}/checkpoints/0' (step 0) is damaged: its checksum "
        "(digest/) is missing, so its content cannot be verified",
    ),
    "train: resume with a torn config.yaml": (
        "tgrf-train",
        ["--resume", "{tornconfig}"],
        (
            "config file '{tornconfig}/config.yaml' is not valid YAML: "
            "expected ',' or ']', but got '<stream end>' (line "
        ),
    ),
    "eval: a run with a torn config.yaml": (
        *evaluate("{tornconfig}"),
        "config file '{tornconfig}/config.yaml' is not valid YAML: expected ','",
    ),
    "train: resume with a binary config.yaml": (
        "tgrf-train",
        ["--resume", "{binconfig}"],
        "config file '{binconfig}/config.yaml' is not UTF-8 text",
    ),
    "train: resume headerless metrics": (
        "tgrf-train",
        ["--resume", "{headerless}"],
        "'{headerless}/metrics.csv' is damaged: line 1 is not its header",
    ),
    "train: resume non-UTF-8 metrics": (
        "tgrf-train",
        ["--resume", "{latin}"],
        "'{latin}/metrics.csv' is damaged: line 2 is not UTF-8 text",
    ),
    "eval: crowd size of a run": (
        *evaluate("{run}", "--set", "env.num_humans=3"),
        "was trained on observations of other shapes than these overrides give (env.num_humans: 2 -> 3)",
    ),
    "render: a LiDAR for a run without one": (
        *render("{run}", "--set", "env.lidar_rays=72"),
        "was trained on observations of other shapes than these overrides give (env.lidar_rays: 0 -> 72)",
    ),
    "eval: a pretrained policy's LiDAR removed": (
        *evaluate("--pretrained", "obstacles-random_obstacles-tgrf", "--set", "env.lidar_rays=0"),
        "pretrained obstacles-random_obstacles-tgrf was trained with env.lidar_rays = 72; these overrides make it "
        "env.lidar_rays = 0, which changes the shapes of its network's parameters",
    ),
    "eval: a pretrained policy's LiDAR halved": (
        *evaluate("--pretrained", "obstacles-random_obstacles-tgrf", "--set", "env.lidar_rays=36"),
        "was trained with env.lidar_rays = 72; these overrides make it env.lidar_rays = 36",
    ),
    "eval: a LiDAR for a pretrained policy without one": (
        *evaluate("--pretrained", "scenarios-mix-tgrf", "--set", "env.lidar_rays=72"),
        "pretrained scenarios-mix-tgrf was trained with env.lidar_rays = 0; these overrides make it "
        "env.lidar_rays = 72",
    ),
    "render: a pretrained policy's LiDAR removed": (
        *render("--pretrained", "obstacles-random_obstacles-tgrf", "--set", "env.lidar_rays=0"),
        "was trained with env.lidar_rays = 72; these overrides make it env.lidar_rays = 0",
    ),
    "eval: a suite over an earlier one": (
        "tgrf-eval",
        ["--policy", "orca", "--episodes", "2", "--suite", "{tmp}/earlier_suite"],
        "--suite '{tmp}/earlier_suite' holds an earlier suite (suite.md, suite.csv); give another directory, or "
        "--overwrite to replace it",
    ),
    "eval: --overwrite without a suite": (
        *evaluate("--policy", "orca", "--overwrite"),
        "--overwrite lets --suite DIR replace an earlier suite; no --suite given",
    ),
    "eval: --suite-rows without a suite": (
        *evaluate("--policy", "orca", "--suite-rows", "real"),
        "--suite-rows chooses the rows of --suite DIR; no --suite given",
    ),
    "eval: an unknown suite row": (
        *evaluate("--policy", "orca", "--suite", "{tmp}/rows", "--suite-rows", "zara3"),
        "--suite-rows: unknown row 'zara3'; allowed: synthetic, real, circle_crossing",
    ),
    "eval: the real scenes without their recordings": (
        *evaluate("--policy", "orca", "--suite", "{tmp}/real", "--suite-rows", "real"),
        "the suite's real scenes need the ETH/UCY recordings; 6 are missing",
    ),
    "sweep: 100000 seeds in a plan": (
        "tgrf-sweep",
        [TINY, "--seeds", "100000", "--print-plan"],
        "--seeds 100000: too many seeds; allowed: 1 .. 1,000",
    ),
    "sweep: resume of an edited grid": (
        "tgrf-sweep",
        ["--resume", "{regridded}"],
        "sweep.yaml' was edited: its grid and seeds give 3 runs",
    ),
    "reproduce: empty --rows": (
        "tgrf-reproduce",
        ["table1", "--rows", ",", "--out", FRESH],
        "--rows ',': empty row name",
    ),
    "reproduce: grid value with a comma": (
        "tgrf-reproduce",
        ["{tmp}/comma_exp.yaml", "--out", FRESH],
        "grid.reward.scheme: value 'crowdnav_pp,tgrf' is not allowed",
    ),
    "reproduce: paper value not a number": (
        "tgrf-reproduce",
        ["{tmp}/paper_exp.yaml", "--out", FRESH],
        "paper.tgrf.sr = 'high' must be a finite number",
    ),
    "reproduce: rows without experiment.yaml": (
        "tgrf-reproduce",
        ["table1", "--out", "{tmp}/orphan_rows"],
        "holds rows (mlp) but no experiment.yaml",
    ),
    "reproduce: damaged experiment.yaml": (
        "tgrf-reproduce",
        ["table1", "--out", "{tmp}/bad_exp_out"],
        "experiment.yaml' is damaged",
    ),
    "predictor: batch of 1e8 windows": (
        "tgrf-predictor",
        ["train", "--dataset", "{tmp}/d.npz", "--run-dir", FRESH, "--batch-size", "100000000"],
        "batch_size = 100,000,000 is out of range; allowed: 1 .. 65,536",
    ),
    "predictor: float visible": (
        "tgrf-predictor",
        ["train", "--dataset", "{tmp}/float_visible.npz", "--run-dir", FRESH],
        "visible has dtype float32; expected boolean",
    ),
    "predictor: metadata without crowd": (
        "tgrf-predictor",
        ["train", "--dataset", "{tmp}/no_crowd.npz", "--run-dir", FRESH],
        "its metadata has no config with a crowd name",
    ),
    "predictor: 3-D human_pos": (
        "tgrf-predictor",
        ["train", "--dataset", "{tmp}/flat.npz", "--run-dir", FRESH],
        "human_pos has shape (5, 40, 3); expected (envs, steps, humans, 2)",
    ),
    "predictor: NaN positions": (
        "tgrf-predictor",
        ["train", "--dataset", "{tmp}/nan.npz", "--run-dir", FRESH],
        "human_pos holds 1 non-finite values (NaN or inf)",
    ),
    "predictor: state dict is a dataset": (
        "tgrf-predictor",
        ["eval", "--dataset", "{tmp}/d.npz", "--torch-state-dict", "{tmp}/d.npz"],
        "--torch-state-dict '{tmp}/d.npz' is not a state dict of numeric arrays",
    ),
    "predictor: NaN parameters": (
        "tgrf-predictor",
        ["eval", "--dataset", "{tmp}/d.npz", "--params", "{tmp}/nan_params.npz"],
        "hold 1 non-finite values",
    ),
    "predictor: corrupt run.json": (
        "tgrf-predictor",
        ["train", "--dataset", "{tmp}/d.npz", "--run-dir", "{tmp}/pred_badjson"],
        "run.json' is damaged",
    ),
    "predictor: a tgrf-train run dir": (
        "tgrf-predictor",
        ["train", "--dataset", "{tmp}/d.npz", "--run-dir", "{run}"],
        "holds config.yaml but no run.json: it is not a tgrf-predictor run",
    ),
    "predictor: --updates below progress": (
        "tgrf-predictor",
        ["train", "--dataset", "{tmp}/d.npz", "--run-dir", "{tmp}/pred_run", "--updates", "20"],
        "--updates 20 is below the progress of '{tmp}/pred_run': its checkpoint of update 40 would be labelled 20",
    ),
}
X64 = {
    "train: 64-bit JAX": ("tgrf-train", [TINY], "JAX_ENABLE_X64 is on"),
    "eval: 64-bit JAX": ("tgrf-eval", ["--episodes", "2"], "JAX_ENABLE_X64 is on"),
}


@pytest.fixture(scope="module")
def places(tmp_path_factory):
    """Files and directories the cases name: bad config files, a file where a directory belongs, and tiny run
    directories with their initial checkpoint (intact, a flipped bit, overwritten, not fitting its config, without
    checkpoints, config edited) and a sweep stopped before its first checkpoint."""
    import yaml

    from tgrf_jax.config import TrainConfig
    from tgrf_jax.sweep.grid import SweepSpec
    from tgrf_jax.train.run_dir import train_run

    tmp = tmp_path_factory.mktemp("bad_inputs")
    (tmp / "adir").mkdir()
    (tmp / "occupied").write_text("a file")
    (tmp / "latin1.yaml").write_bytes("env:\n  dt: 0.25  # Schrittl\xe4nge\n".encode("latin-1"))
    (tmp / "dup.yaml").write_text("ppo:\n  lr: 1.0e-4\nppo:\n  num_envs: 8\n")
    (tmp / "broken.yaml").write_text("env: [unclosed\n")
    (tmp / "list.yaml").write_text("- env\n- ppo\n")
    (tmp / "foo.yaml").write_text("foo:\n  x: 1\nenv:\n  num_humans: 2\n")
    config = TrainConfig.from_yaml(TINY, ["run.eval_episodes=0"])
    train_run(config, tmp / "run", log=lambda m: None, stop_after_updates=0)  # config + the initial checkpoint
    for name in ("damaged", "garbage", "mismatch", "nockpt", "edited"):
        shutil.copytree(tmp / "run", tmp / name)
    flip_a_bit(tmp / "damaged" / "checkpoints" / "0")
    for f in (tmp / "garbage" / "checkpoints" / "0").rglob("*"):
        if f.is_file():
            f.write_text("garbage")
    text = (tmp / "run" / "config.yaml").read_text()
    (tmp / "mismatch" / "config.yaml").write_text(text.replace("size: small", "size: paper"))
    shutil.rmtree(tmp / "nockpt" / "checkpoints")
    (tmp / "edited" / "config.yaml").write_text(text.replace("lr: 0.001", "lr: 0.002"))
    _files_named_by_cases(tmp, text)
    # what a sweep killed before its first checkpoint leaves
    spec = SweepSpec.create(TINY, ["reward.h_disc=1,2"])
    (tmp / "sweep").mkdir()
    (tmp / "sweep" / "config.yaml").write_text(spec.base_config.to_yaml())
    (tmp / "sweep" / "sweep.yaml").write_text(yaml.safe_dump(spec.to_dict(), sort_keys=False))
    return tmp


RUN_DIRS = (
    "run",
    "damaged",
    "garbage",
    "mismatch",
    "nockpt",
    "edited",
    "sweep",
    "nodigest",
    "headerless",
    "latin",
    "regridded",
    "truncated",
    "truncated_meta",
    "tornconfig",
    "binconfig",
)


def _files_named_by_cases(tmp, config_text):
    """Files for the cases above: config and experiment files, run directories with damaged bookkeeping, predictor
    datasets, parameters and run directories."""
    import json

    import numpy as np
    import yaml

    from tgrf_jax.env.gst import model as gst_model
    from tgrf_jax.env.gst import weights as weights_lib
    from tgrf_jax.predictor import data as data_lib
    from tgrf_jax.predictor import train as predictor_train
    from tgrf_jax.storage.checkpoint import Checkpointer
    from tgrf_jax.sweep.grid import SweepSpec

    (tmp / "int_key.yaml").write_text("1: 2\n")
    (tmp / "deep.yaml").write_text("env: " + "[" * 5000 + "]" * 5000 + "\n")
    (tmp / "quoted.yaml").write_text("env:\n  num_humans: '5'\n")
    for name in ("nodigest", "headerless", "latin", "truncated", "truncated_meta", "tornconfig", "binconfig"):
        shutil.copytree(tmp / "run", tmp / name)
    # a crash or a full disk mid-copy: the step's largest array data file cut to nothing (chosen among tensorstore's
    # data files only: in a tiny run the JSON metadata can be the largest file); or an array's metadata (whose read
    # error carries tensorstore's whole store spec)
    data_files = [
        f for f in (tmp / "truncated" / "checkpoints" / "0" / "default").glob("ocdbt.process_*/d/*") if f.is_file()
    ]
    assert data_files, "the checkpoint layout has no tensorstore data files to truncate"
    max(data_files, key=lambda f: f.stat().st_size).write_bytes(b"")
    meta_files = [f for f in (tmp / "truncated_meta" / "checkpoints" / "0" / "default" / "d").iterdir()]
    max(meta_files, key=lambda f: f.stat().st_size).write_bytes(b"")
    (tmp / "tornconfig" / "config.yaml").write_text(config_text[: config_text.index("ppo:") + 4] + " [torn\n")
    (tmp / "binconfig" / "config.yaml").write_bytes(b"\xff\xfe\x00" + config_text.encode())
    shutil.rmtree(tmp / "nodigest" / "checkpoints" / "0" / "digest")
    (tmp / "headerless" / "metrics.csv").write_text("2,128,0.5\n")
    (tmp / "latin" / "metrics.csv").write_bytes(("update,env_steps\n2,1\xe9\n").encode("latin-1"))
    spec = SweepSpec.create(TINY, ["reward.h_disc=1,2"])
    (tmp / "regridded").mkdir()
    (tmp / "regridded" / "config.yaml").write_text(spec.base_config.to_yaml())
    edited = spec.to_dict()
    edited["grid"]["reward.h_disc"] = [1.0, 2.0, 3.0]
    (tmp / "regridded" / "sweep.yaml").write_text(yaml.safe_dump(edited, sort_keys=False))
    (tmp / "comma_exp.yaml").write_text(
        "config: " + TINY + "\ngrid: {reward.scheme: ['crowdnav_pp,tgrf']}\nrows: [{name: a}]\n"
    )
    (tmp / "paper_exp.yaml").write_text(
        "config: " + TINY + "\ngrid: {reward.scheme: [tgrf]}\nrows: [{name: a, paper: {tgrf: {sr: high}}}]\n"
    )
    (tmp / "orphan_rows" / "mlp").mkdir(parents=True)
    (tmp / "orphan_rows" / "mlp" / "sweep.yaml").write_text("{}\n")
    (tmp / "bad_exp_out").mkdir()
    (tmp / "earlier_suite").mkdir()
    for name in ("suite.md", "suite.csv"):
        (tmp / "earlier_suite" / name).write_text("an earlier suite's table\n")
    (tmp / "bad_exp_out" / "experiment.yaml").write_text("rows: [unclosed\n")

    rng = np.random.default_rng(0)
    arrays = dict(
        robot_pos=np.zeros((5, 40, 2), np.float32),
        human_pos=rng.uniform(-3, 3, (5, 40, 3, 2)).astype(np.float32),
        visible=np.ones((5, 40, 3), bool),
        seg=np.zeros((5, 40, 3), np.int16),
    )
    dataset = {"arrays": arrays, "config": {"crowd": "orca", "seed": 0}}
    data_lib.save_dataset(tmp / "d.npz", dataset)

    def variant(name, meta=None, **changes):
        payload = {"format": 1, "config": dataset["config"]} if meta is None else meta
        np.savez(tmp / name, meta=np.array(json.dumps(payload)), **{**arrays, **changes})

    variant("float_visible.npz", visible=arrays["visible"].astype(np.float32))
    variant("no_crowd.npz", meta={"format": 1, "config": {"seed": 0}})
    variant("flat.npz", human_pos=arrays["human_pos"][..., 0])
    nan = arrays["human_pos"].copy()
    nan[1, 2, 0, 1] = np.nan
    variant("nan.npz", human_pos=nan)
    params = jax.tree_util.tree_map(np.array, gst_model.init_params(jax.random.key(0)))  # writable copies
    leaf = jax.tree_util.tree_leaves(params)[0]
    leaf.flat[0] = np.nan
    weights_lib.save_params(tmp / "nan_params.npz", params, {})
    (tmp / "pred_badjson").mkdir()
    (tmp / "pred_badjson" / "run.json").write_text("{torn")
    loaded = data_lib.load_dataset(tmp / "d.npz")
    meta = predictor_train._run_meta(predictor_train.TrainConfig(updates=40), loaded)
    (tmp / "pred_run").mkdir()
    (tmp / "pred_run" / "run.json").write_text(json.dumps(meta))
    ckpt = Checkpointer(tmp / "pred_run" / "checkpoints")
    ckpt.save(40, {"step": np.int32(40)})
    ckpt.close()


def _run(places, capsys, tool, argv, expected):
    def fmt(text):
        for name in RUN_DIRS:
            text = text.replace("{" + name + "}", str(places / name))
        return text.replace("{tmp}", str(places))

    # a checkpoint's or parameter file's shapes are traced against the model's
    reads_params = {"--params", "--pretrained"} & set(argv)
    reads_checkpoints = any("{" + name + "}" in a for a in argv for name in RUN_DIRS) or bool(reads_params)
    argv = [fmt(a) for a in argv]
    with CompileCounter() as counter:
        code = MAINS[tool](argv)
    out = capsys.readouterr()
    assert code == 2, out
    assert out.err.startswith(f"{tool}: error: ") and fmt(expected) in out.err, out.err
    assert "Traceback" not in out.err and "Event loop" not in out.err
    assert all(line.startswith(f"{tool}: ") for line in out.err.splitlines()), out.err  # no continuation lines
    assert len(out.err) < 2000, len(out.err)  # one line: no value echoed whole
    assert counter.compiles == 0
    if not reads_checkpoints:
        assert counter.traces == 0
    assert not (places / "fresh").exists()


@pytest.mark.parametrize("case", list(CASES))
def test_bad_input_is_named_before_anything_compiles(case, places, capsys):
    _run(places, capsys, *CASES[case])


@pytest.mark.parametrize("case", list(X64))
def test_64_bit_jax_is_refused_in_one_line(case, places, capsys):
    jax.config.update("jax_enable_x64", True)
    try:
        _run(places, capsys, *X64[case])
    finally:
        jax.config.update("jax_enable_x64", False)


@pytest.mark.parametrize(
    "tool, argv, error",
    [
        (
            "train",
            ["--resume", "{damaged}"],
            "tgrf-train: error: checkpoint '{damaged}/checkpoints/0' (step 0) is "
            "damaged: its content does not match the checksum written with it; no earlier step is intact",
        ),
        (
            "eval",
            ["{garbage}"],
            "tgrf-eval: error: checkpoint '{garbage}/checkpoints/0' (step 0) is damaged: it cannot "
            "be read (JSONDecodeError: Expecting value: line 1 column 1 (char 0)); no earlier step is intact",
        ),
        # a truncated data file: orbax's restore fails while tensorstore still has reads in flight, which completed
        # into a closed event loop and printed hundreds of tracebacks around the error; tensorstore's kilobytes of
        # store spec are cut from the reason
        (
            "train",
            ["--resume", "{truncated}"],
            re.compile(
                r"tgrf-train: error: checkpoint '{truncated}/checkpoints/0' \(step 0\) is damaged: it cannot be read "
                r"\(ValueError: .{20,330}\); no earlier step is intact"
            ),
        ),
        (
            "eval",
            ["{truncated_meta}"],
            re.compile(
                r"tgrf-eval: error: checkpoint '{truncated_meta}/checkpoints/0' \(step 0\) is damaged: it cannot be "
                r"read \(ValueError: .{20,330}\); no earlier step is intact"
            ),
        ),
    ],
)
def test_a_damaged_checkpoint_ends_the_process_with_its_error_alone(places, tool, argv, error):
    """The whole stderr of a process stopped by a damaged checkpoint: the error; no log lines of orbax's, nothing
    from its event loop at exit."""
    import os
    import subprocess
    import sys

    def fmt(text, quote=lambda path: path):
        for name in ("damaged", "garbage", "truncated", "truncated_meta"):
            text = text.replace("{" + name + "}", quote(str(places / name)))
        return text

    env = dict(
        os.environ,
        JAX_PLATFORMS="cpu",
        TGRF_JAX_COMPILE_CACHE="off",
        PYTHONPATH=f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
    )
    out = subprocess.run(
        [sys.executable, "-m", f"tgrf_jax.cli.{tool}", *map(fmt, argv)],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 2
    if isinstance(error, re.Pattern):
        lines = out.stderr.splitlines()
        assert len(lines) == 1 and re.fullmatch(fmt(error.pattern, re.escape), lines[0]), out.stderr[-3000:]
    else:
        assert out.stderr.splitlines() == [fmt(error)]
