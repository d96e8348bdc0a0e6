"""The ``mpe3d`` command line."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from .config import config_from_file, describe_keys, make_config, parse_override
from .errors import MpeError


class _Parser(argparse.ArgumentParser):
    """argparse, but usage errors are one line and exit code 2."""

    def error(self, message: str):  # noqa: D401 - argparse's signature
        raise MpeError(message)


def _number(value) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def _print_summary(summary: dict) -> None:
    cfg = summary["config"]
    print(f"shape {cfg['shape']}, N={cfg['points']}, K={cfg['views']}, "
          f"visibility {cfg['visibility']['mode']}, projections {cfg['projections']}, "
          f"solver {cfg['solver']['name']} (init {cfg['init']}), seed {cfg['seed']}")
    print(f"visible per view: {summary['visible_per_view']}")
    print("  ".join(f"{k}={_number(summary[k])}" for k in
                    ("cd", "cd_mean", "emd", "emd_mean", "roa")))
    print(f"stress={_number(summary['stress'])}  iterations={summary['iterations']} "
          f"({summary['termination']})  solver {summary['runtime_s']:.3f} s, "
          f"total {summary['wall_s']:.3f} s")


def cmd_run(args) -> int:
    from .execute import run, write_outputs

    overrides = dict(parse_override(item) for item in args.overrides)
    config = config_from_file(args.config, overrides) if args.config else make_config(overrides)
    result = run(config)
    summary = result.summary()
    if args.out:
        try:
            written = write_outputs(result, Path(args.out))
        except OSError as exc:
            raise MpeError(f"cannot write outputs to {args.out}: {exc.strerror or exc}") from None
        summary["outputs"] = [str(p) for p in written]
    if args.json:
        print(json.dumps(summary))
    else:
        _print_summary(summary)
        for path in summary.get("outputs", []):
            print(f"wrote {path}")
    return 0


def cmd_shapes(args) -> int:
    from .shapes import PROCEDURAL, bundled_manifest

    for name, entry in bundled_manifest().items():
        print(f"{name:<9} stands in for {entry['paper_category']:<9} "
              f"{entry['source_name']} by {entry['creator']} ({entry['faces']} faces, {entry['license']})")
    for name in PROCEDURAL:
        print(f"{name:<9} procedural")
    return 0


def cmd_solvers(args) -> int:
    import solvers

    for name in sorted(solvers.SOLVERS):
        options = ", ".join(f"{k}={v}" for k, v in solvers.solver_options(name).items())
        print(f"{name:<9} {options}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="mpe3d", description="3D multi-perspective embedding: "
                     "rebuild a 3D point cloud from partial 2D views.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    run = sub.add_parser("run", help="run one configuration",
                         formatter_class=argparse.RawDescriptionHelpFormatter,
                         epilog="keys (KEY=VALUE; solver=NAME is short for solver.name=NAME,\n"
                                "solver options are solver.<option>=VALUE):\n" + describe_keys())
    run.add_argument("overrides", nargs="*", metavar="KEY=VALUE")
    run.add_argument("--config", metavar="FILE.yaml", help="YAML file of keys (overrides win)")
    run.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    run.add_argument("--out", metavar="DIR", help="write ground_truth.ply, reconstruction.ply and a PNG")
    run.set_defaults(func=cmd_run)
    sub.add_parser("shapes", help="list the bundled and procedural shapes").set_defaults(func=cmd_shapes)
    sub.add_parser("solvers", help="list solvers and their options").set_defaults(func=cmd_solvers)
    return parser


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.WARNING, format="mpe3d: %(message)s", stream=sys.stderr)
    try:
        args = build_parser().parse_args(argv)
        return args.func(args)
    except MpeError as exc:
        print(f"mpe3d: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("mpe3d: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
