"""tgrf-reproduce: run one of the paper's experiments, resumably, and write its table as it fills."""

from __future__ import annotations

import argparse
import pathlib
import shlex
import sys

from tgrf_jax.cli.common import Recovery, add_layout_arg, check_jax, check_writable, command_line
from tgrf_jax.config import ConfigError
from tgrf_jax.experiments import spec as spec_lib


@command_line("tgrf-reproduce")
def main(argv: list[str] | None, recovery: Recovery) -> int:
    recovery.resume = "rerun the same command to resume"  # finished rows are skipped, a started one resumes
    parser = argparse.ArgumentParser(
        prog="tgrf-reproduce",
        description="Run an experiment (a list of rows, each one tgrf-sweep or, in a search experiment, one "
        "tgrf-tune) and write its report (Markdown and CSV: our numbers beside the paper's, or the searches "
        "compared) after every row. Rerun the same command after any interruption: finished rows are skipped, a "
        "started row resumes from its last checkpoint.",
    )
    parser.add_argument(
        "experiment",
        nargs="?",
        help=f"an experiment name ({', '.join(spec_lib.available())}) or a path to an experiment YAML",
    )
    parser.add_argument("--out", help="results directory (default: runs/reproduce/<experiment>)")
    parser.add_argument("--steps", type=int, help="env steps per run instead of the experiment's budget (quick look)")
    parser.add_argument("--seeds", type=int, help="seeds per cell instead of the experiment's")
    parser.add_argument("--rows", help="comma-separated row names to run (default: all)")
    parser.add_argument("--list", action="store_true", help="list the experiments and their rows, then exit")
    parser.add_argument(
        "--print-plan",
        action="store_true",
        help="print each row's tgrf-sweep (or tgrf-tune) command and state, then exit (nothing runs)",
    )
    parser.add_argument(
        "--report-only",
        action="store_true",
        help="rewrite the report from finished rows (and export their policies, with --export-pretrained), then exit",
    )
    parser.add_argument(
        "--export-pretrained",
        metavar="DIR",
        help="export the best seed's policy of every finished row and compared value to "
        "DIR/<experiment>-<row>-<value> (tgrf-eval --pretrained plays it)",
    )
    add_layout_arg(
        parser,
        "the layout of the sweep and tune rows this command trains: new rows start in it (default: auto, "
        "sequential on CPUs), started rows switch to it (default: they keep theirs)",
    )
    args = parser.parse_args(argv)

    from tgrf_jax.experiments import runner

    if args.list:
        for name in spec_lib.available():
            exp = spec_lib.load(name)
            print(f"{name}: {exp.title}")
            for row in exp.rows:
                print(f"  {row.name}: {row.label}")
        return 0
    if not args.experiment:
        raise ConfigError(f"name an experiment: {', '.join(spec_lib.available())}")
    exp = spec_lib.load(args.experiment)
    rows = None
    if args.rows is not None:
        rows = [r.strip() for r in args.rows.split(",")]
        if not all(rows):
            raise ConfigError(
                f"--rows {args.rows[:60]!r}: empty row name; give comma-separated names of "
                f"{exp.name}'s rows: {', '.join(r.name for r in exp.rows)}"
            )
    whole = exp.shrunk(steps=args.steps, seeds=args.seeds)  # the report always covers every row
    exp = whole.shrunk(rows=rows)
    if args.export_pretrained and exp.search:
        raise ConfigError(
            f"--export-pretrained exports the best policies of sweep rows; {exp.name!r} compares searches (every "
            "member of its rows is a run directory that tgrf-eval and tgrf-export take)"
        )
    out = pathlib.Path(args.out or pathlib.Path("runs") / "reproduce" / exp.name)
    runner.check_out_dir(exp, out)
    if not (args.print_plan or args.report_only):
        check_jax()
        check_writable(out, "--out", directory=True)
    if args.export_pretrained and not args.print_plan:
        check_writable(args.export_pretrained, "--export-pretrained", directory=True)
    retested = {name for name, _, _ in runner.retested_rows(exp, out)}
    if args.print_plan:
        for row in exp.rows:
            state = runner.row_state(out / row.name, row.kind)
            if row.name in retested:
                state += ", test settings changed: its tests play again"
            if row.kind == "grid":
                print(f"{row.name} [{state}]: the finished sweep {spec_lib.portable(row.results)}")
                continue
            cmd = spec_lib.row_command(exp, row, args.layout or "auto") + ["--out", str(out / row.name)]
            print(f"{row.name} [{state}]: {shlex.join(cmd)}")
        return 0
    if args.report_only:
        if not out.is_dir():
            raise ConfigError(
                f"--out {str(out)!r} does not exist: no rows to report (tgrf-reproduce "
                f"{args.experiment} --out {out} trains them)"
            )
        for name in sorted(retested):
            print(
                f"note: row {name}'s test settings changed since its tests ran; the report shows the earlier "
                f"tests' results until `tgrf-reproduce {args.experiment}` plays them again"
            )
        for path in runner.write_report(whole, out):
            print(path)
        if args.export_pretrained:
            for path in runner.export_finished(exp, out, args.export_pretrained):
                print(f"exported {path}")
        return 0
    return runner.reproduce(exp, out, export_to=args.export_pretrained, report_exp=whole, layout=args.layout)


if __name__ == "__main__":
    sys.exit(main())
