"""``mpe3d solvers``, ``mpe3d shapes`` and ``mpe3d check-solver``: what is
installed, and whether a solver (or an SfM plug-in) keeps its contract."""

from __future__ import annotations

from mpe3d.cli.options import add_plugins


def add_parsers(sub) -> None:
    shapes = sub.add_parser("shapes", help="list the bundled and procedural shapes, and plug-in datasets")
    add_plugins(shapes)
    shapes.set_defaults(func=cmd_shapes)
    listing = sub.add_parser("solvers", help="list solvers and their options, plug-ins in their own group")
    add_plugins(listing)
    listing.set_defaults(func=cmd_solvers)
    check = sub.add_parser("check-solver", help="check a solver or SfM plug-in against its contract",
                           description="Run solver NAME on small scenes and check the contract every "
                           "solver keeps (result shapes, orthonormal projections, one result per seed, "
                           "option rules, observations only, coordinates, exactness if claimed). An SfM "
                           "plug-in runs on synthetic pinhole photos instead (result types and shapes, one "
                           "result per seed, relative poses within 5 degrees of the truth). One "
                           "line per check; exit code 0 if all pass, 1 if one fails.")
    check.add_argument("name", metavar="NAME", help="a registered solver or SfM plug-in (see mpe3d solvers)")
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
    _list_sfm()
    for line in plugins.failures():
        print(f"not loaded: {line}")
    return 0


def _list_sfm() -> None:
    """The SfM plug-ins, in a group of their own (mpe3d's own SfM methods are
    ``reconstruct --solver`` values, listed by its help)."""
    from mpe3d.solvers.sfm.methods import SFM_METHODS

    if SFM_METHODS:
        print("structure-from-motion plug-ins:")
    for method in sorted(SFM_METHODS.values(), key=lambda m: m.name):
        print(f"  {method.name:<9} {method.summary or 'an SfM method'}  (from {method.origin})")


def cmd_check_solver(args) -> int:
    from mpe3d import plugins, solvers
    from mpe3d.solvers.sfm.methods import SFM_METHODS

    plugins.load_entry_points()
    if args.name not in solvers.SOLVERS and args.name not in SFM_METHODS:
        from mpe3d.errors import MpeError, suggest

        raise MpeError(f"unknown solver '{args.name}' (solvers: {', '.join(sorted(solvers.SOLVERS))}; "
                       f"SfM plug-ins: {', '.join(sorted(SFM_METHODS)) or 'none'})"
                       + plugins.failure_note("solver") + plugins.failure_note("sfm"),
                       hint=suggest(args.name, [*solvers.SOLVERS, *SFM_METHODS]))
    if args.name in SFM_METHODS and args.name not in solvers.SOLVERS:
        from mpe3d.harness.experiment.sfm_contract import run_sfm_checks as run_checks
    else:
        from mpe3d.harness.experiment.contract import run_checks
    checks = run_checks(args.name, args.seed)
    for check in checks:
        print(check.line())
    failed = sum(not c.passed for c in checks)
    print(f"{args.name}: {len(checks) - failed} of {len(checks)} checks pass"
          + ("" if not failed else f"; {failed} to fix"))
    return 1 if failed else 0
