"""tgrf-data: download the recorded pedestrians (ETH/UCY), list what is known and present, and summarise a file."""

from __future__ import annotations

import argparse
import pathlib
import sys

from tgrf_jax.cli.common import Recovery, command_line
from tgrf_jax.config import ConfigError
from tgrf_jax.pedestrians import catalogue
from tgrf_jax.pedestrians.recordings import DEFAULT_DT, FORMATS, RecordingError, RecordingSpec, load

TOOL = "tgrf-data"


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=TOOL,
        description="Recorded pedestrian trajectories (ETH/BIWI and UCY) for the simulator: download them, list "
        "them, summarise a file (docs/pedestrians.md). The recordings are not shipped with tgrf-jax; files are "
        f"kept in ${catalogue.DATA_ENV}/pedestrians or the user data directory ({catalogue.default_data_dir()}).",
    )
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    fetch = sub.add_parser("fetch", help="download a set of recordings, each checked against its SHA-256")
    fetch.add_argument("dataset", choices=sorted(catalogue.DATASETS), help="the set to download")
    fetch.add_argument("--dir", metavar="DIR", help="where to put the files (default: the user data directory)")
    lst = sub.add_parser("list", help="the known recordings, where they are and whether they verify")
    lst.add_argument("--dir", metavar="DIR", help="where to look (default: the user data directory)")
    info = sub.add_parser("info", help="people, duration, largest crowd and median walking speed of a file")
    info.add_argument("file", metavar="FILE", help="a 4-column (frame id x y) or obsmat (8-column) text file")
    spacing = info.add_mutually_exclusive_group(required=True)
    spacing.add_argument("--seconds-per-frame", type=float, metavar="S", help="seconds per frame unit of the file")
    spacing.add_argument("--fps", type=float, help="frame units per second of the file")
    info.add_argument("--format", choices=sorted(FORMATS), help="default: told by the number of columns")
    info.add_argument("--dt", type=float, default=DEFAULT_DT, help=f"resampling step in seconds ({DEFAULT_DT})")
    info.add_argument("--max-gap", type=float, metavar="S", help="split tracks missing longer (default: 1.5 steps)")
    return p


def _error(message: object, hint: list[str] | None = None) -> int:
    print(f"{TOOL}: error: {message}", file=sys.stderr)
    for line in hint or ():
        print(f"{TOOL}: {line}", file=sys.stderr)
    return 2


def _fetch(name: str, directory: str | None) -> int:
    entries = catalogue.DATASETS[name]
    data_dir = pathlib.Path(directory) if directory else catalogue.default_data_dir()
    try:
        data_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        return _error(f"cannot create the data directory {data_dir} ({e.strerror or e})")
    print(f"{TOOL}: {name}: {len(entries)} files into {data_dir}", flush=True)
    from tgrf_jax.pedestrians.fetch import fetch

    try:
        outcomes = fetch(entries, data_dir, progress=lambda line: print(line, flush=True))
    except OSError as e:
        return _error(f"cannot write into {data_dir} ({e})")
    print("Terms of use (the recordings are not part of tgrf-jax; cite them when you use them):")
    for terms in sorted({e.terms for e in entries}):
        print(f"  {terms}")
    failed = [o for o in outcomes if o.action == "failed"]
    if not failed:
        done = sum(o.action == "downloaded" for o in outcomes)
        print(f"{TOOL}: {name}: {done} downloaded, {len(outcomes) - done} already present; all verified")
        return 0
    hint = [
        f"offline: download these files elsewhere and copy them by hand into {data_dir} (paths relative to it), "
        f"then check them with `{TOOL} list --dir {data_dir}`:",
        *(f"  {o.entry.name}  sha256 {o.entry.sha256}  {o.entry.url}" for o in failed),
    ]
    first = failed[0].error
    return _error(f"{len(failed)} of {len(outcomes)} files failed; {first} (the file is left out)", hint)


def _list(directory: str | None) -> int:
    data_dir = pathlib.Path(directory) if directory else catalogue.default_data_dir()
    print(f"data directory: {data_dir}")
    for name, entries in catalogue.DATASETS.items():
        print(f"{name} (tgrf-data fetch {name}):")
        print(f"  {'file':26} {'scene':24} {'test fold':10} {'s/frame':>8}  status")
        for e in entries:
            fold = e.fold or "train only"
            state = catalogue.status(e, data_dir)
            print(f"  {e.name:26} {e.scene:24} {fold:10} {e.seconds_per_frame:8.4g}  {state}")
    return 0


def _info(args: argparse.Namespace) -> int:
    try:
        spec = RecordingSpec(args.file, args.seconds_per_frame, args.fps, args.format)
        scene = load(spec, dt=args.dt, max_gap=args.max_gap)
    except RecordingError as e:
        return _error(e)
    crowd = scene.max_crowd()
    print(f"{scene.source} ({scene.format}, {scene.seconds_per_frame:.4g} s per frame, resampled to dt {scene.dt:g} s)")
    print(f"  people:       {scene.num_people} ({scene.num_tracks} continuous tracks)")
    print(f"  duration:     {scene.duration:.1f} s ({scene.num_steps} steps)")
    print(f"  max crowd:    {crowd.count} people at once (step {crowd.step}, t = {crowd.time:.2f} s)")
    print(f"  median speed: {scene.median_speed:.2f} m/s")
    return 0


@command_line(TOOL, bad_input=(ConfigError, RecordingError))
def main(argv: list[str] | None, recovery: Recovery) -> int:
    args = parser().parse_args(argv)
    if args.command == "fetch":
        return _fetch(args.dataset, args.dir)
    if args.command == "list":
        return _list(args.dir)
    return _info(args)


if __name__ == "__main__":
    sys.exit(main())
