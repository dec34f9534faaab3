"""tgrf-export: a trained policy's single decision as ONNX and StableHLO files plus interface.json."""

from __future__ import annotations

import argparse
import sys
import time

from tgrf_jax.cli.common import Recovery, check_jax, command_line, start
from tgrf_jax.config import ConfigError

FORMATS = ("onnx", "stablehlo")  # tgrf_jax.deploy.FORMATS, repeated so --help needs no JAX import


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="tgrf-export",
        description="Export one decision of a trained policy, (observation, recurrent state) -> (action, new "
        "recurrent state), as an ONNX file and a serialized jax.export StableHLO artifact, with interface.json "
        "stating every input and output (docs/deployment.md). The output directory also works as "
        "--pretrained DIR and as tgrf_jax.deploy.Navigator(DIR).",
    )
    p.add_argument("run_dir", nargs="?", metavar="RUN_DIR", help="a tgrf-train run directory")
    p.add_argument(
        "--pretrained",
        metavar="NAME|DIR",
        help="a shipped policy (tgrf_jax.pretrained.available()) or a pretrained-format directory, instead of RUN_DIR",
    )
    p.add_argument("--step", type=int, default=None, help="RUN_DIR: checkpoint (update) to export; default: latest")
    p.add_argument("--out", required=True, metavar="DIR", help="new directory to write (an existing one is refused)")
    p.add_argument("--format", dest="formats", action="append", choices=FORMATS, help="repeatable; default: both")
    return p


@command_line("tgrf-export")
def main(argv: list[str] | None, recovery: Recovery) -> int:
    args = parser().parse_args(argv)
    check_jax()
    if (args.run_dir is None) == (args.pretrained is None):
        raise ConfigError("give exactly one of RUN_DIR and --pretrained NAME")
    if args.step is not None and args.run_dir is None:
        raise ConfigError("--step selects a checkpoint of a RUN_DIR; no RUN_DIR given")
    from tgrf_jax.deploy.export import check_out_dir

    check_out_dir(args.out)
    formats = tuple(dict.fromkeys(args.formats or FORMATS))
    if "onnx" in formats:
        try:
            import jax2onnx  # noqa: F401
        except ImportError:
            raise ConfigError(
                "ONNX export needs jax2onnx: pip install 'tgrf-jax[deploy]' (or --format stablehlo)"
            ) from None

    start()
    from tgrf_jax.deploy import export, load_source

    recovery.from_checkpoint = f"tgrf-export {args.run_dir} --out {args.out} --step"
    source = load_source(args.run_dir or args.pretrained, step=args.step)
    net, rays = source.config.network, source.config.env.lidar_rays
    lidar = f", {rays}-ray LiDAR (extra input 'lidar')" if rays else ""
    print(
        f"exporting {args.run_dir or args.pretrained} ({net.name}/{net.size}, {source.config.env.kinematics}, "
        f"predictor {source.config.env.predictor}{lidar}) to {args.out}",
        flush=True,
    )
    t0 = time.perf_counter()
    out = export(source, args.out, formats)
    files = ", ".join(sorted(p.name for p in out.iterdir()))
    print(f"wrote {out} in {time.perf_counter() - t0:.1f} s: {files}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
