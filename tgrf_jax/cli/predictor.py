"""`tgrf-predictor collect | train | eval`: datasets, training and held-out evaluation of the GST predictor.

    tgrf-predictor collect --crowd orca --out data/gst_orca.npz
    tgrf-predictor train --dataset data/gst_orca.npz --run-dir runs/gst_orca
    tgrf-predictor eval --dataset data/gst_orca.npz --params runs/gst_orca/gst.npz
    tgrf-predictor eval --dataset data/gst_orca.npz --pretrained orca

Every option is checked before anything is compiled; a bad value, a missing or corrupt dataset, or a missing or
incompatible parameter file / checkpoint stops with a message naming the option or path.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import math
import pathlib
import platform
import subprocess
import sys

from tgrf_jax.cli.common import Recovery, check_jax, check_writable, command_line
from tgrf_jax.env.gst import weights as weights_lib
from tgrf_jax.predictor import data as data_lib
from tgrf_jax.predictor import train as train_lib
from tgrf_jax.storage.checkpoint import CheckpointError
from tgrf_jax.storage.files import write_atomic


def _commit() -> str:
    try:
        root = pathlib.Path(__file__).resolve().parents[2]
        return subprocess.run(
            ["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _provenance() -> dict:
    return {
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "commit": _commit(),
        "machine": platform.processor() or platform.machine(),
        "command": "tgrf-predictor " + " ".join(sys.argv[1:]),
    }


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="tgrf-predictor", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True)
    c = sub.add_parser("collect", help="collect a dataset from the JAX simulator")
    defaults = data_lib.CollectConfig()
    c.add_argument("--crowd", choices=data_lib.CROWDS, default=defaults.crowd)
    c.add_argument("--envs", type=int, default=defaults.num_envs, help="parallel envs, one long episode each")
    c.add_argument("--steps", type=int, default=defaults.steps, help="frames per env")
    c.add_argument("--seed", type=int, default=defaults.seed)
    c.add_argument("--out", required=True, help="dataset path (.npz; the config goes beside it as .json)")
    c.add_argument(
        "--recordings",
        nargs="+",
        metavar="NAME",
        help="make the dataset from recorded pedestrians instead of the simulator: catalogue names as "
        "env.replay_files takes them (eth-ucy, a fold such as zara1, a file such as ucy/crowds_zara03.txt), read "
        "in the data directory (tgrf-data fetch eth-ucy), cut into envs of --chunk-steps steps",
    )
    c.add_argument(
        "--chunk-steps",
        type=int,
        default=data_lib.CHUNK_STEPS,
        help=f"--recordings: steps per env (default {data_lib.CHUNK_STEPS}, 50 s)",
    )

    t = sub.add_parser("train", help="train on a dataset, resuming from --run-dir's checkpoints")
    tdef = train_lib.TrainConfig()
    t.add_argument("--dataset", required=True)
    t.add_argument("--run-dir", required=True, help="checkpoints, run.json and the exported gst.npz go here")
    for name in ("updates", "batch_size", "decay_every", "seed", "log_every", "checkpoint_every", "eval_windows"):
        t.add_argument("--" + name.replace("_", "-"), type=int, default=getattr(tdef, name))
    t.add_argument("--lr", type=float, default=tdef.lr)
    t.add_argument("--decay-rate", type=float, default=tdef.decay_rate)
    t.add_argument(
        "--cv-prior",
        action=argparse.BooleanOptionalAction,
        default=tdef.cv_prior,
        help="predict corrections to constant velocity (--no-cv-prior: the released model exactly)",
    )
    t.add_argument(
        "--mean-loss",
        choices=train_lib.MEAN_LOSSES,
        default=tdef.mean_loss,
        help="what fits the predicted means: ade (their displacement error; the NLL fits only the "
        "spreads) or nll (CrowdNav++ GST's loss for everything)",
    )
    t.add_argument(
        "--dropout", type=float, default=tdef.dropout, help="training-time dropout rate (CrowdNav++'s GST: 0.1)"
    )
    t.add_argument("--export", help="also write the trained parameters here (.npz + .json)")
    t.add_argument("--fresh", action="store_true", help="ignore existing checkpoints (the run dir must be new)")
    t.add_argument(
        "--from-step",
        type=int,
        metavar="N",
        help="continue from checkpoint N instead of the latest (a damaged one, say); the later "
        "checkpoints are deleted and their updates trained again",
    )

    e = sub.add_parser("eval", help="held-out ADE / FDE / NLL against constant velocity")
    e.add_argument("--dataset", required=True)
    which = e.add_mutually_exclusive_group(required=True)
    which.add_argument("--params", help="parameters written by `train` (.npz)")
    which.add_argument("--pretrained", choices=tuple(weights_lib.PRETRAINED), help="the shipped parameters")
    which.add_argument(
        "--torch-state-dict",
        help=".npz of the reference's state-dict arrays (names as in the reference fixture, 'w/' prefix optional)",
    )
    e.add_argument("--windows", type=int, default=tdef.eval_windows, help="held-out windows evaluated (spread evenly)")
    e.add_argument(
        "--all-envs",
        action="store_true",
        help="evaluate windows from every env of the dataset, not only its held-out last 20%% (a dataset of a "
        "held-out scene)",
    )
    e.add_argument("--out", help="write the metrics as JSON here")
    return parser


def _load_params(args):
    if args.params:
        return weights_lib.load_params(args.params)[0], args.params
    if args.pretrained:
        return weights_lib.pretrained(args.pretrained), f"pretrained:{args.pretrained}"
    path = pathlib.Path(args.torch_state_dict)
    if not path.is_file():
        raise weights_lib.WeightsError(f"state dict {str(path)!r} does not exist")
    import numpy as np

    try:
        with np.load(path) as arrays:
            return weights_lib.from_torch_state_dict({k: arrays[k] for k in arrays.files}), str(path)
    except weights_lib.WeightsError as e:
        raise weights_lib.WeightsError(f"--torch-state-dict {str(path)!r}: {e}") from None
    except Exception as e:  # numpy raises several types for files that are no .npz of arrays
        raise weights_lib.WeightsError(
            f"--torch-state-dict {str(path)!r} is not a state dict of numeric arrays "
            f"({type(e).__name__}: {str(e)[:80]})"
        ) from None


def _check_finite_params(params, source: str) -> None:
    import jax
    import numpy as np

    bad = sum(int(np.size(x) - np.count_nonzero(np.isfinite(x))) for x in jax.tree_util.tree_leaves(params))
    if bad:
        raise weights_lib.WeightsError(
            f"predictor parameters {source!r} hold {bad:,} non-finite values (NaN or inf); train them again"
        )


def _check_outputs(args) -> None:
    """Every output path, before any collection, training or evaluation."""
    check_jax()
    if args.command == "collect":
        check_writable(args.out, "--out", directory=False)
    elif args.command == "train":
        check_writable(args.run_dir, "--run-dir", directory=True)
        if args.export:
            check_writable(args.export, "--export", directory=False)
    elif args.out:
        check_writable(args.out, "--out", directory=False)


# DatasetError, WeightsError and TrainingError are ValueErrors; so is the ConfigError of a checked option
def _collect_recordings(args) -> int:
    from tgrf_jax.config import ConfigError
    from tgrf_jax.env.replay import catalogue_entries
    from tgrf_jax.pedestrians import default_data_dir

    specs = []
    for name in args.recordings:
        try:
            specs += [entry.spec() for entry in catalogue_entries(name)]
        except KeyError:
            raise ConfigError(
                f"--recordings {name!r} is not a catalogue name; allowed: eth-ucy, a fold (eth, hotel, univ, zara1, "
                "zara2) or a file of the catalogue (tgrf-data list)"
            ) from None
    missing = [str(s.path) for s in specs if not pathlib.Path(s.path).is_file()]
    if missing:
        raise ConfigError(
            f"--recordings: {len(missing)} file(s) are not in the data directory {str(default_data_dir())!r} "
            f"(first: {missing[0]}); `tgrf-data fetch eth-ucy` downloads them"
        )
    print(f"making a dataset of {len(specs)} recording(s), envs of {args.chunk_steps} steps", flush=True)
    dataset = data_lib.recorded(specs, chunk_steps=args.chunk_steps)
    path = data_lib.save_dataset(pathlib.Path(args.out), dataset)
    shape = dataset["arrays"]["visible"].shape
    print(f"wrote {path} ({shape[0]} envs x {shape[1]} steps x {shape[2]} people slots)")
    return 0


@command_line("tgrf-predictor", bad_input=(ValueError,))
def main(argv: list[str] | None, recovery: Recovery) -> int:
    args = _parser().parse_args(argv)
    _check_outputs(args)
    if args.command == "collect" and args.recordings:
        return _collect_recordings(args)
    if args.command == "collect":
        config = data_lib.CollectConfig(crowd=args.crowd, num_envs=args.envs, steps=args.steps, seed=args.seed)
        out = pathlib.Path(args.out)
        print(
            f"collecting {config.frames:,} frames ({config.num_envs} envs x {config.steps} steps) of "
            f"{config.crowd} crowds, seed {config.seed}",
            flush=True,
        )
        dataset = data_lib.collect(config, log=lambda s: print(s, flush=True))
        path = data_lib.save_dataset(out, dataset)
        print(f"wrote {path} ({config.frames:,} frames in {dataset['collect_seconds']:.1f} s)")
        return 0
    if args.command == "train":
        config = train_lib.TrainConfig(
            **{f.name: getattr(args, f.name) for f in dataclasses.fields(train_lib.TrainConfig)}
        )
        dataset = data_lib.load_dataset(args.dataset)
        run_dir = pathlib.Path(args.run_dir)
        if args.fresh and (run_dir / "checkpoints").exists():
            raise CheckpointError(f"--fresh: run directory {str(run_dir)!r} already holds checkpoints")
        if args.from_step is not None and (args.fresh or args.from_step < 0):
            raise ValueError(
                f"--from-step {args.from_step}: give a checkpoint (update >= 0) of an existing run, without --fresh"
            )
        restart_flags = [
            f for f, given in (("--fresh", args.fresh), ("--from-step", args.from_step is not None)) if given
        ]
        recovery.resume = (
            "rerun the command"
            + (f" without {' and '.join(restart_flags)}" if restart_flags else "")
            + " to resume from its last checkpoint"
        )
        try:
            params, meta = train_lib.train(
                config,
                dataset,
                run_dir,
                log=lambda s: print(s, flush=True),
                resume=not args.fresh,
                from_step=args.from_step,
            )
        except CheckpointError as e:
            intact = getattr(e, "intact", ())
            if intact:
                raise CheckpointError(
                    f"{e}; continue from the latest intact one with --from-step {intact[-1]}"
                ) from None
            raise
        meta.update(_provenance())
        for target in [run_dir / "gst.npz"] + ([pathlib.Path(args.export)] if args.export else []):
            print(f"wrote {weights_lib.save_params(target, params, meta)}")
        return 0
    # eval
    if not 1 <= args.windows <= train_lib._LIMITS["eval_windows"]:
        raise ValueError(
            f"--windows = {args.windows:,} is out of range; allowed: 1 .. {train_lib._LIMITS['eval_windows']:,}"
        )
    params, source = _load_params(args)
    _check_finite_params(params, source)
    dataset = data_lib.load_dataset(args.dataset)
    if args.all_envs:
        arrays = dataset["arrays"]
        val_index = data_lib.window_index(arrays["visible"], arrays["seg"], range(arrays["visible"].shape[0]))
    else:
        _, val_index = data_lib.split_index(dataset["arrays"])
    if not len(val_index):
        raise data_lib.DatasetError(
            f"dataset {args.dataset!r} has no held-out window to evaluate (no pedestrian "
            "seen for 10 frames in its last 20% of envs)"
        )
    evaluate = train_lib.make_evaluator(data_lib.device_arrays(dataset["arrays"]))
    metrics = evaluate(params, train_lib.eval_subset(val_index, args.windows))
    if not all(math.isfinite(metrics[k]) for k in ("ade", "fde", "nll", "ade_change", "fde_change")):
        raise ValueError(
            f"the evaluation of {source!r} on {args.dataset!r} is not finite (ADE {metrics['ade']}, "
            f"FDE {metrics['fde']}, NLL {metrics['nll']}): the parameters or the data are damaged"
        )
    print(f"parameters: {source}")
    print(train_lib.format_eval(metrics, f"{dataset['config']['crowd']} ({args.dataset})"))
    if args.out:
        out = pathlib.Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(
            out, json.dumps({"params": source, "dataset": str(args.dataset), **metrics, **_provenance()}, indent=2)
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
