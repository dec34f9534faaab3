"""Sweep scaling: G runs as one tgrf-sweep (one vmapped program, runs split over the devices) versus the same G
runs trained one after another by tgrf-train's loop (`train_run`), for G = 1, 4, 16.

Every run has the same config and length (G seeds of one config; no final evaluation), so both sides train
exactly G x total_steps env steps and write the same artifacts (CSV, checkpoints, plots). Reported per G:

  * ``wall_s``: wall time of the whole thing (compilation, training, checkpoints, plots; Python start-up and
    imports excluded: the sequential runs share one process, as if each tgrf-train started warm)
  * ``train_s``: the timed training chunks only (compilation excluded) and ``sps``: env steps / train_s
  * ``compiles``: XLA backend compilations (jax.monitoring '/jax/core/compile/backend_compile_duration' events),
    ``program_compiles``: those that took >= 0.5 s (the training/init programs; the rest are tiny eager ops), and
    ``chunk_compiles``: compilations of the chunk (training) program, counted by the loops themselves
  * ``compile_s``: seconds spent in backend compilation

Each sequential run builds its own `make_trainer` and jits, so it compiles its own programs, as separate tgrf-train
invocations do. Jax's in-memory caches are cleared before each measurement.

    python -m benchmarks.sweep_scaling --quick --out bench_results/sweep_quick.json
    python -m benchmarks.sweep_scaling --out bench_results/sweep_full.json
    python -m benchmarks.sweep_scaling --config configs/default.yaml --set ppo.total_steps=38400 --sizes 1 4
"""

from __future__ import annotations

import argparse
import pathlib
import tempfile
import time

import jax
from jax import monitoring

from benchmarks.common import machine_info, write_json
from tgrf_jax import configure_cpu
from tgrf_jax import sweep as sweep_lib
from tgrf_jax.config import TrainConfig, apply_overrides, load_yaml
from tgrf_jax.sweep import program as sweep_program
from tgrf_jax.train.run_dir import train_run

ROOT = pathlib.Path(__file__).resolve().parents[1]
COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"
_compiles: list[float] = []


def _listener(event: str, duration: float, **_):
    if event == COMPILE_EVENT:
        _compiles.append(duration)


monitoring.register_event_duration_secs_listener(_listener)


def _fresh():
    sweep_program._TRAINERS.clear()
    jax.clear_caches()
    _compiles.clear()


def _compile_stats() -> dict:
    return {
        "compiles": len(_compiles),
        "program_compiles": sum(d >= 0.5 for d in _compiles),
        "compile_s": round(sum(_compiles), 2),
    }


def run_sweep_once(base: dict, g: int, workdir: pathlib.Path) -> dict:
    _fresh()
    spec = sweep_lib.SweepSpec(base, (), tuple(range(g)))
    t0 = time.perf_counter()
    res = sweep_lib.run_sweep(spec, workdir / f"sweep_{g}", log=lambda m: None)
    wall = time.perf_counter() - t0
    batch = spec.base_config.ppo.batch_size
    steps = g * res.updates * batch
    batched = next(iter(sweep_program._TRAINERS.values()))
    return {
        "mode": "sweep",
        "G": g,
        "devices": res.num_devices,
        "wall_s": round(wall, 2),
        "train_s": round(res.train_seconds, 3),
        "env_steps": steps,
        "sps": round(steps / res.train_seconds, 1),
        "chunk_compiles": len(batched.compiled),
        **_compile_stats(),
    }


def run_sequential(base: dict, g: int, workdir: pathlib.Path) -> dict:
    _fresh()
    t0 = time.perf_counter()
    train_s, steps, chunk_compiles = 0.0, 0, 0
    for seed in range(g):
        cfg = TrainConfig.from_dict(apply_overrides(base, [f"run.seed={seed}"]))
        res = train_run(cfg, workdir / f"seq_{g}_{seed}", log=lambda m: None)
        train_s += res.train_seconds
        steps += res.updates * cfg.ppo.batch_size
        chunk_compiles += res.compiled_chunks
    wall = time.perf_counter() - t0
    return {
        "mode": "sequential",
        "G": g,
        "devices": 1,
        "wall_s": round(wall, 2),
        "train_s": round(train_s, 3),
        "env_steps": steps,
        "sps": round(steps / train_s, 1),
        "chunk_compiles": chunk_compiles,
        **_compile_stats(),
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--quick",
        action="store_true",
        help="G = 1 and 16 only, sequential runs measured for G = 1 only (G = 16 estimated as 16 x "
        "that); about a minute on 2 cores",
    )
    parser.add_argument("--out", help="write results as JSON")
    parser.add_argument("--config", default=str(ROOT / "configs" / "tiny.yaml"), help="run config (default: tiny)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--sizes", type=int, nargs="*", help="numbers of runs G (default: 1 4 16; quick: 1 16)")
    args = parser.parse_args(argv)
    configure_cpu()  # 512-bit vectors on AVX-512, as the command-line tools use (XLA_FLAGS chooses devices)
    args.sizes = args.sizes or ([1, 16] if args.quick else [1, 4, 16])

    data = apply_overrides(load_yaml(args.config), ["run.eval_episodes=0", *args.overrides])
    base = TrainConfig.from_dict(data).to_dict()
    cfg = TrainConfig.from_dict(base)
    print(
        f"config {args.config} {' '.join(args.overrides)}: {cfg.env.num_humans} {cfg.env.human_policy} humans, "
        f"{cfg.network.name}/{cfg.network.size}, {cfg.ppo.num_envs} envs x {cfg.ppo.num_steps} steps, "
        f"{cfg.ppo.num_updates} updates per run; {len(jax.devices())} {jax.default_backend()} device(s)",
        flush=True,
    )
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        seq_one = None
        for g in args.sizes:
            s = run_sweep_once(base, g, tmp)
            results.append(s)
            if args.quick and g > 1 and seq_one is not None:
                q = {
                    k: seq_one[k] * g
                    for k in ("wall_s", "train_s", "env_steps", "chunk_compiles", "program_compiles", "compile_s")
                }
                # the small eager compilations of the first run are cached for the later ones
                q["compiles"] = seq_one["compiles"] + (g - 1) * seq_one["program_compiles"]
                q.update(mode="sequential", G=g, devices=1, sps=seq_one["sps"], estimated=True)
                q = {k: (round(v, 3) if isinstance(v, float) else v) for k, v in q.items()}
            else:
                q = run_sequential(base, g, tmp)
                if g == 1:
                    seq_one = q
            results.append(q)
            print(
                f"G={g:>3}: sweep {s['wall_s']:7.1f} s wall ({s['train_s']:6.2f} s training, {s['sps']:>10,.0f} "
                f"steps/s, {s['chunk_compiles']} chunk compile(s), {s['program_compiles']} program compiles) | "
                f"sequential {q['wall_s']:7.1f} s wall ({q['train_s']:6.2f} s training, {q['sps']:>10,.0f} "
                f"steps/s, {q['chunk_compiles']} chunk compile(s), {q['program_compiles']} program compiles)"
                f"{' [estimated: G x the G=1 run]' if q.get('estimated') else ''}",
                flush=True,
            )
    print()
    print(
        "| G | mode | wall s | train s | env steps | steps/s | chunk compiles | program compiles (>=0.5 s) | "
        "all compiles | compile s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in results:
        mode = r["mode"] + (" (estimated)" if r.get("estimated") else "")
        print(
            f"| {r['G']} | {mode} | {r['wall_s']:.1f} | {r['train_s']:.2f} | {r['env_steps']:,} | {r['sps']:,.0f} | "
            f"{r['chunk_compiles']} | {r['program_compiles']} | {r['compiles']} | {r['compile_s']:.1f} |"
        )
    write_json(
        args.out,
        {
            "machine": machine_info(),
            "benchmark": "sweep_scaling",
            "quick": args.quick,
            "config": args.config,
            "overrides": args.overrides,
            "results": results,
        },
    )


if __name__ == "__main__":
    main()
