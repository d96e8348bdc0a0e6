"""``mpe3d solvers``, ``mpe3d shapes`` and ``mpe3d check-solver``: what is
installed, and whether a solver keeps the solver contract."""

from __future__ import annotations

from mpe3d.cli.options import add_plugins


def add_parsers(sub) -> None:
    shapes = sub.add_parser("shapes", help="list the bundled and procedural shapes, and plug-in datasets")
    add_plugins(shapes)
    shapes.set_defaults(func=cmd_shapes)
    listing = sub.add_parser("solvers", help="list solvers and their options, plug-ins in their own group")
    add_plugins(listing)
    listing.set_defaults(func=cmd_solvers)
    check = sub.add_parser("check-solver", help="check a solver against the solver contract",
                           description="Run solver NAME on small scenes and check the contract every "
                           "solver keeps (result shapes, orthonormal projections, one result per seed, "
                           "option rules, observations only, coordinates, exactness if claimed). One "
                           "line per check; exit code 0 if all pass, 1 if one fails.")
    check.add_argument("name", metavar="NAME", help="a registered solver (see mpe3d solvers)")
    check.add_argument("--seed", type=int, default=0, help="the scenes' and the solver's seed (default 0)")
    add_plugins(check)
    check.set_defaults(func=cmd_check_solver)


def cmd_shapes(args) -> int:
    from mpe3d import plugins
    from mpe3d.harness.scene.shapes import DATASETS, PROCEDURAL, bundled_manifest

    for name, entry in bundled_manifest().items():
        print(f"{name:<9} stands in for {entry['paper_category']:<9} "
              f"{entry['source_name']} by {entry['creator']} ({entry['faces']} faces, {entry['license']})")
    for name in PROCEDURAL:
        print(f"{name:<9} procedural")
    plugins.load_entry_points()
    for dataset in sorted(DATASETS.values(), key=lambda d: d.name):
        items = ", ".join(f"{dataset.name}:{item}" for item in dataset.items) or f"{dataset.name}:<item>"
        print(f"{dataset.name:<9} {dataset.summary or 'a dataset'}: {items}  (from {dataset.origin})")
    for line in plugins.failures():
        print(f"not loaded: {line}")
    return 0


def cmd_solvers(args) -> int:
    from mpe3d import plugins, solvers

    plugins.load_entry_points()
    specs = sorted(solvers.SOLVERS.values(), key=lambda s: s.name)
    groups = [("the paper's solvers", [s for s in specs if s.origin is None and s.paper]),
              ("our solvers", [s for s in specs if s.origin is None and not s.paper])]
    for origin in dict.fromkeys(s.origin for s in specs if s.origin is not None):
        groups.append((f"from {origin}", [s for s in specs if s.origin == origin]))
    for title, members in groups:
        print(f"{title}:")
        for spec in members:
            notes = [*(["exact"] if spec.exact else []),
                     *([f"{' and '.join(spec.settings)} only"] if len(spec.settings) < 2 else [])]
            print(f"  {spec.name:<9} {spec.summary}" + (f" [{', '.join(notes)}]" if notes else ""))
            for option, default in spec.options().items():
                print(f"    solver.{option}={default}  ({spec.constraints[option]})")
            if spec.uses_init:
                print("    init=smart|random  (the starting point)")
    for line in plugins.failures():
        print(f"not loaded: {line}")
    return 0


def cmd_check_solver(args) -> int:
    from mpe3d.harness.experiment.contract import run_checks

    checks = run_checks(args.name, args.seed)
    for check in checks:
        print(check.line())
    failed = sum(not c.passed for c in checks)
    print(f"{args.name}: {len(checks) - failed} of {len(checks)} checks pass"
          + ("" if not failed else f"; {failed} to fix"))
    return 1 if failed else 0
