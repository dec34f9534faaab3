"""Start-up and evaluation cost, optionally of several checkouts of tgrf-jax side by side in one run.

Two measurements, each in a fresh process with the compilation cache off (so every program is compiled):

  * ``train``: `tgrf-train` on a config (the embedded default unless `--config`), stopped by SIGTERM after
    `--updates` updates. Reports the time from process start to the first progress line (time to first update,
    imports and compilation included), the number of training programs compiled and their compile seconds as
    the run prints them. Its log, checkpoint and evaluation periods are set to differ (`--periods`), so a trainer
    that compiles one program per chunk length shows it.
  * ``eval``: a 500-episode evaluation of a shipped policy (`--pretrained`, one per predictor asked for): the
    first call (compilation included) and a second, timed call, with the success rate of each so that two
    checkouts can be compared on equal metrics.

`--code DIR` (repeatable) measures another checkout too (e.g. a `git worktree` of an older commit): its
`tgrf_jax` is put first on the subprocess's PYTHONPATH. Without it only this checkout is measured.

    python -m benchmarks.startup_and_eval --out bench_results/startup_and_eval.json
    git worktree add /tmp/base v0.3.0 && python -m benchmarks.startup_and_eval --code /tmp/base --code .
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import re
import signal
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]

EVAL_PROBE = r"""
import json, sys, time
t0 = time.perf_counter()
import jax
from tgrf_jax import configure_cpu
configure_cpu()
from tgrf_jax import pretrained
from tgrf_jax.env import CrowdNavEnv
from tgrf_jax.evaluate import evaluate
try:
    from tgrf_jax.policies import LearnedPolicy, make_network_for
except ImportError:  # checkouts before the policies package
    from tgrf_jax.train.policy import LearnedPolicy
    from tgrf_jax.train.ppo import make_network_for

name, episodes = sys.argv[1], int(sys.argv[2])
policy = pretrained.load(name)
config, params = (policy.config, policy.params) if hasattr(policy, "config") else policy[:2]
env = CrowdNavEnv(config.env, config.reward)
learned = LearnedPolicy(make_network_for(config), params)
out = {"policy": name, "predictor": config.env.predictor, "import_s": time.perf_counter() - t0}
for label in ("first", "second"):
    c0 = time.perf_counter()
    r = evaluate(env, learned, jax.random.key(0), episodes)
    out[f"{label}_s"] = time.perf_counter() - c0
    out[f"{label}_success_rate"] = r.success_rate
    out[f"{label}_itr_future"] = r.itr_future
print("RESULT " + json.dumps(out), flush=True)
"""

COMPILED = re.compile(r"compiled (?:a (\d+)-update chunk|the training program).* in ([\d.]+) s")
PROGRESS = re.compile(r"^\[[^\]]*steps[^\]]*update (\d+)\] ([\d,]+) steps/s")


def _env(code: pathlib.Path) -> dict:
    env = dict(os.environ, TGRF_JAX_COMPILE_CACHE="off", PYTHONUNBUFFERED="1")
    env["PYTHONPATH"] = os.pathsep.join([str(code), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    return env


def measure_train(code: pathlib.Path, config: str | None, updates: int, periods: tuple[int, int, int]) -> dict:
    """Time to first update and compilations of a tgrf-train run stopped after `updates` updates."""
    log_every, checkpoint_every, eval_every = periods
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [
            sys.executable,
            "-m",
            "tgrf_jax.cli.train",
            *([config] if config else []),
            "--set",
            f"run.log_every={log_every}",
            "--set",
            f"run.checkpoint_every={checkpoint_every}",
            "--set",
            f"run.eval_every={eval_every}",
            "--set",
            "run.curve_episodes=20",
            "--out-dir",
            str(pathlib.Path(tmp) / "run"),
        ]
        t0 = time.perf_counter()
        proc = subprocess.Popen(
            cmd, cwd=tmp, env=_env(code), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
        )
        first_update_s, compiles, lines, last_update, sps = None, [], [], 0, []
        for line in proc.stdout:
            lines.append(line.rstrip())
            if m := COMPILED.search(line):
                compiles.append(float(m.group(2)))
            if m := PROGRESS.search(line):
                last_update = int(m.group(1))
                sps.append(float(m.group(2).replace(",", "")))
                if first_update_s is None:
                    first_update_s = time.perf_counter() - t0
                if last_update >= updates and proc.poll() is None:
                    proc.send_signal(signal.SIGTERM)  # stops after the running chunk, with a checkpoint
        proc.wait()
    if first_update_s is None:
        raise RuntimeError(f"{code}: tgrf-train printed no progress line:\n" + "\n".join(lines[-30:]))
    # the first chunk's rate includes warm-up effects; the median of the others is the training rate
    rates = sorted(sps[1:]) or sps
    return {
        "time_to_first_update_s": first_update_s,
        "programs_compiled": len(compiles),
        "compile_s": compiles,
        "updates": last_update,
        "train_sps_median": rates[len(rates) // 2],
        "wall_s": time.perf_counter() - t0,
    }


def measure_eval(code: pathlib.Path, policy: str, episodes: int) -> dict:
    out = subprocess.run(
        [sys.executable, "-c", EVAL_PROBE, policy, str(episodes)],
        cwd=tempfile.gettempdir(),
        env=_env(code),
        capture_output=True,
        text=True,
        timeout=3600,
    )
    for line in out.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[len("RESULT ") :])
    raise RuntimeError(f"{code}: evaluation probe failed:\n{out.stdout[-2000:]}\n{out.stderr[-3000:]}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--code", action="append", type=pathlib.Path, help="a checkout to measure (repeatable; default: this one)"
    )
    p.add_argument("--config", help="tgrf-train config file (default: the embedded default)")
    p.add_argument("--updates", type=int, default=12, help="updates before the run is stopped (default 12)")
    p.add_argument("--periods", default="5,6,4", help="log_every,checkpoint_every,eval_every (default 5,6,4)")
    p.add_argument(
        "--pretrained",
        action="append",
        help="shipped policies to evaluate (default: table1-const_vel-tgrf and table1-truth-tgrf)",
    )
    p.add_argument("--episodes", type=int, default=500)
    p.add_argument("--skip", choices=("train", "eval"), action="append", default=[])
    p.add_argument("--out", help="JSON file for the results")
    args = p.parse_args(argv)
    periods = tuple(int(x) for x in args.periods.split(","))
    if len(periods) != 3 or min(periods) < 1:
        p.error(f"--periods {args.periods!r}: three positive integers log_every,checkpoint_every,eval_every")
    codes = [c.resolve() for c in (args.code or [ROOT])]
    for code in codes:
        if not (code / "tgrf_jax" / "__init__.py").is_file():
            p.error(f"--code {code}: no tgrf_jax package there")
    policies = args.pretrained or ["table1-const_vel-tgrf", "table1-truth-tgrf"]

    sys.path.insert(0, str(ROOT))
    from benchmarks.common import machine_info, write_json

    results = {
        "machine": machine_info(),
        "date": time.strftime("%Y-%m-%d"),
        "updates": args.updates,
        "periods": dict(zip(("log_every", "checkpoint_every", "eval_every"), periods)),
        "episodes": args.episodes,
        "codes": {},
    }
    for code in codes:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=code, capture_output=True, text=True
        ).stdout.strip()
        entry = results["codes"][str(code)] = {"commit": commit}
        if "train" not in args.skip:
            entry["train"] = t = measure_train(code, args.config, args.updates, periods)
            print(
                f"{code} ({commit}) train: first update after {t['time_to_first_update_s']:.1f} s; "
                f"{t['programs_compiled']} training program(s) compiled "
                f"({', '.join(f'{s:.1f}' for s in t['compile_s'])} s); "
                f"{t['train_sps_median']:,.0f} env-steps/s (median over chunks)",
                flush=True,
            )
        if "eval" not in args.skip:
            entry["eval"] = []
            for policy in policies:
                e = measure_eval(code, policy, args.episodes)
                entry["eval"].append(e)
                print(
                    f"{code} ({commit}) eval {policy}: {args.episodes} episodes in {e['second_s']:.2f} s "
                    f"(first call {e['first_s']:.1f} s with compilation); success {e['second_success_rate']:.3f}",
                    flush=True,
                )
    write_json(args.out, results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
