"""``mpe3d run``: one configuration, solved and scored."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from mpe3d.cli.options import add_plugins, add_yaml_limit
from mpe3d.errors import MpeError
from mpe3d.harness.experiment.config import config_from_file, describe_keys, make_config, parse_override


def add_parser(sub) -> None:
    run = sub.add_parser("run", help="run one configuration",
                         formatter_class=argparse.RawDescriptionHelpFormatter,
                         epilog="keys (KEY=VALUE; solver=NAME is short for solver.name=NAME,\n"
                                "solver options are solver.<option>=VALUE):\n" + describe_keys())
    run.add_argument("overrides", nargs="*", metavar="KEY=VALUE",
                     help="run keys (listed below), e.g. shape=lamp points=1024 solver=refine")
    run.add_argument("--config", metavar="FILE.yaml", help="YAML file of keys (overrides win)")
    run.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    run.add_argument("--out", metavar="DIR", help="write ground_truth.ply, reconstruction.ply and a PNG")
    add_plugins(run)
    add_yaml_limit(run)
    run.set_defaults(func=cmd_run)


def cmd_run(args) -> int:
    from mpe3d.harness.experiment.execute import pipeline, run, write_outputs

    overrides = dict(parse_override(item) for item in args.overrides)
    config = config_from_file(args.config, overrides, args.max_yaml_mb) if args.config \
        else make_config(overrides)
    result = run(config)
    summary = result.summary()
    for message in summary["warnings"]:
        print(f"mpe3d: warning: {message}", file=sys.stderr)
    if args.out:
        try:
            written = write_outputs(result, Path(args.out))
        except OSError as exc:
            raise MpeError(f"cannot write outputs to {args.out}: {exc.strerror or exc}") from None
        summary["outputs"] = [str(p) for p in written]
    if args.json:
        print(json.dumps(summary))
        return 0
    print("\n".join(pipeline(summary["config"]["pipeline"]).describe(summary)))
    for path in summary.get("outputs", []):
        print(f"wrote {path}")
    return 0
