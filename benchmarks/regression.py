"""Speed never slips silently: every path a user waits on, timed against a committed baseline.

    python benchmarks/regression.py [--quick] [--mpe3d PATH] [--record] [--work DIR]

Each case is a whole process of the installed command line (the ``mpe3d``
beside this Python, or ``--mpe3d PATH``, so that another install can be
timed on the same inputs), as a user starts it:

=================  =====  ======================================================
case               quick  what a user waits on
=================  =====  ======================================================
startup            yes    ``mpe3d --help``
run                yes    a fresh ``mpe3d run shape=airplane points=512 views=4 solver=refine``
orthographic_200k  yes    ``mpe3d reconstruct`` of 200,000 points x 8 orthographic views (NPZ)
bundle_250         yes    ``--camera perspective``: 250 pinholes x 3,000 points, 0.5 px noise
photos_10          yes    ``mpe3d reconstruct images/``: 10 rendered photos, SIFT to model
photos_25          yes    the same, 25 photos
photos_100         no     the same, 100 photos
reproduce_tiny     yes    ``mpe3d reproduce-paper --scale tiny`` from an empty store
reproduce_quick    no     ``mpe3d reproduce-paper --scale quick`` from an empty store
house              no     ``mpe3d reconstruct house/keypoints.csv`` (``../shared/realdata``)
=================  =====  ======================================================

A case's time is the best of its repeats (two or three for the quick cases;
the machine's noise moved single runs by 15 % here), in units of
``benchmarks/machine.py``'s loop timed just before and after the case, so
that a faster or slower machine moves the baseline and the reading alike.
The loop is interpreter work and the cases are mostly numeric, so on a
machine whose speed drifts the units drift too (30 % within an hour here):
``--against OTHER`` times another install's ``mpe3d`` in turns with this one
on the same inputs, and gives their ratio in the same run, which no drift
moves; a case flagged against the baseline is confirmed or cleared that way.
The inputs are made by this checkout's code (the photos rendered by
``mpe3d.harness.scene.rendering``) and kept in ``--work`` under a digest of
what made them, so a rerun renders nothing and a changed renderer
renders again. One JSON line a case on stdout, then the table (case,
baseline, now, ratio) on stderr; a case more than ``SLOWER`` times its
baseline is flagged, and the exit code is 1 when one is.

``--record`` writes this run as the baseline (``regression_baseline.json``
beside this script): do it only in a commit that says why the baseline moves.

asv and pytest-benchmark, the ecosystem's tools, were weighed: pytest-benchmark
times functions inside a pytest process (these cases are whole processes
and minutes long, and the suite must never assert on time); asv builds an
environment per commit and normalises by the host's name, not by a measured
loop, which on a virtual machine whose speed moved 2x between two sessions
is the wrong unit. A script of ~200 lines does what is needed.
"""

from __future__ import annotations

import argparse
import hashlib
import inspect
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from machine import at_once, describe

HERE = Path(__file__).resolve().parent
BASELINE = HERE / "regression_baseline.json"
SHARED = HERE.parent.parent / "shared"
SLOWER = 1.2  # a case this many times its baseline is flagged


@dataclass
class Case:
    name: str
    quick: bool
    argv: Callable[[Path], list[str]]  # the command's words after ``mpe3d``, given the inputs' folder
    make: Callable[[Path], None] | None = None  # writes the inputs into their folder
    repeats: int = 1
    needs: list[Path] = field(default_factory=list)  # files outside the repository


def _orthographic(folder: Path, points: int = 200_000, views: int = 8) -> None:
    from mpe3d import make_config
    from mpe3d.harness.scene.observe import build_scene, observe, seed_streams

    config = make_config({"shape": "chair", "points": points, "views": views,
                          "observe": "coordinates", "projections": "variable"})
    streams = seed_streams(0)
    obs, _ = observe(build_scene(config, streams), config, streams)
    np.savez(folder / "views.npz", **{f"view{k}_{key}": value for k, v in enumerate(obs.views)
                                      for key, value in (("ids", v.ids), ("xy", v.coordinates))})


def _spiral_bundle(folder: Path) -> None:
    from bundle_scale import scene

    views, _, _ = scene(250, 3000, 0.5, 0)
    np.savez(folder / "views.npz", **{f"view{k}_{key}": v[key] for k, v in enumerate(views)
                                      for key in ("ids", "xy")})


def _photos(count: int) -> Callable[[Path], None]:
    def make(folder: Path) -> None:
        from mpe3d.harness.scene import rendering, shapes

        rendering.save_images(rendering.render(shapes.load_shape("chair"), rendering.photo_spiral(count, 400, 0),
                                               seed=0), folder / "images")
    make.__name__ = f"photos_{count}"
    return make


def _reproduce(scale: str) -> Callable[[Path], list[str]]:
    return lambda _: ["reproduce-paper", "--scale", scale, "--jobs", "2", "--out", "report", "--quiet"]


CASES = [
    Case("startup", True, lambda _: ["--help"], repeats=3),
    Case("run", True, lambda _: ["run", "shape=airplane", "points=512", "views=4", "solver=refine"],
         repeats=3),
    Case("orthographic_200k", True, lambda d: ["reconstruct", str(d / "views.npz"), "--out", "cloud.ply"],
         _orthographic, repeats=2),
    Case("bundle_250", True, lambda d: ["reconstruct", str(d / "views.npz"), "--camera", "perspective",
                                        "--principal-point", "200,200", "--out", "cloud.ply"], _spiral_bundle,
         repeats=2),
    Case("photos_10", True, lambda d: ["reconstruct", str(d / "images"), "--out", "model"], _photos(10),
         repeats=3),
    Case("photos_25", True, lambda d: ["reconstruct", str(d / "images"), "--out", "model"], _photos(25),
         repeats=2),
    Case("photos_100", False, lambda d: ["reconstruct", str(d / "images"), "--out", "model"], _photos(100)),
    Case("reproduce_tiny", True, _reproduce("tiny")),
    Case("reproduce_quick", False, _reproduce("quick")),
    Case("house", False, lambda _: ["reconstruct", str(SHARED / "realdata/house/keypoints.csv"),
                                    "--out", "cloud.ply"], repeats=3, needs=[SHARED / "realdata/house/keypoints.csv"]),
]


def _digest(make: Callable) -> str:
    """What made a case's inputs: the maker's source and every mpe3d module it
    may use to render or observe, so that a changed renderer makes them again."""
    import mpe3d.harness.scene.observe as observe
    import mpe3d.harness.scene.rendering as rendering

    text = inspect.getsource(make) + "".join(inspect.getsource(m) for m in (rendering, observe))
    for name in ("bundle_scale.py",):
        text += (HERE / name).read_text()
    closure = [c.cell_contents for c in (make.__closure__ or ())]
    return hashlib.sha256((text + repr(closure)).encode()).hexdigest()[:12]


def inputs(case: Case, work: Path) -> Path:
    """The case's input folder, made once per digest of what makes it."""
    if case.make is None:
        return work
    folder = work / f"{case.name}-{_digest(case.make)}"
    if not (folder / "done").exists():
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir(parents=True)
        print(f"regression: making the inputs of {case.name} in {folder}", file=sys.stderr, flush=True)
        case.make(folder)
        (folder / "done").touch()
    return folder


def timed(command: list[str]) -> float:
    """One run's wall time, in an empty folder with no tracking server named
    (a fresh SQLite store there)."""
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    with tempfile.TemporaryDirectory(prefix="mpe3d-regression-") as cwd:
        start = time.perf_counter()
        done = subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True)
        seconds = time.perf_counter() - start
    if done.returncode not in (0, 1):  # 1: a sweep with a failed run still timed its work
        sys.exit(f"regression: {' '.join(command)} exited {done.returncode}: "
                 f"{(done.stderr.strip().splitlines() or [''])[-1]}")
    return seconds


def measured(case: Case, folder: Path, commands: list[list[str]]) -> tuple[list[float], float]:
    """The best of ``case.repeats`` runs of each command (the commands taking
    turns, so that a slow minute of the machine falls on both), and the
    machine's loop timed just before and after them: the case's unit (this
    virtual machine's loop moved by 30 % within an hour)."""
    loops = [at_once(1)]
    best = [float("inf")] * len(commands)
    for _ in range(case.repeats):
        for i, command in enumerate(commands):
            best[i] = min(best[i], timed(command + case.argv(folder)))
    loops.append(at_once(1))
    return best, float(np.mean(loops))


def table(rows: list[dict]) -> str:
    against = any("against_s" in row for row in rows)
    lines = ["| case | baseline | now | ratio | |" + (" against, same run | ratio |" if against else ""),
             "|---|---|---|---|---|" + ("---|---|" if against else "")]
    for row in rows:
        base = row["baseline_units"]
        shown = "-" if base is None else f"{base:.2f} ({row['baseline_s']:.2f} s)"
        ratio = "-" if row["ratio"] is None else f"{row['ratio']:.2f}"
        line = (f"| {row['case']} | {shown} | {row['units']:.2f} ({row['seconds']:.2f} s) | {ratio} | "
                f"{'SLOWER' if row['slower'] else ''} |")
        if against:
            line += f" {row['against_s']:.2f} s | {row['same_run_ratio']:.2f} |"
        lines.append(line)
    return "\n".join(lines) + (f"\n(units of machine.py's loop, timed before and after each case; SLOWER: more "
                               f"than {SLOWER}x the baseline" + ("; against: the other install, taking turns with "
                                                                "this one" if against else "") + ")")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the cases marked quick (at most 2 minutes)")
    parser.add_argument("--cases", nargs="+", help="these cases only")
    parser.add_argument("--mpe3d", help="the command to time (default: the mpe3d beside this Python)")
    parser.add_argument("--against", metavar="MPE3D", help="another install's mpe3d, timed in turns with this "
                        "one: the ratio of the two in the same run, which a machine's drift cannot move")
    parser.add_argument("--record", action="store_true", help=f"write this run as the baseline ({BASELINE.name})")
    parser.add_argument("--code", help="what --record says the baseline was measured on (e.g. a commit)")
    parser.add_argument("--work", type=Path, default=Path.home() / ".cache" / "mpe3d-regression",
                        help="where the inputs are kept between runs")
    args = parser.parse_args(argv)
    command = [args.mpe3d or str(Path(sys.executable).parent / "mpe3d")]
    cases = [c for c in CASES if (c.quick or not args.quick) and (not args.cases or c.name in args.cases)
             and all(p.exists() for p in c.needs)]
    folders = {c.name: inputs(c, args.work) for c in cases}  # before the clock: inputs are not timed
    machine = describe()
    baseline = json.loads(BASELINE.read_text()) if BASELINE.exists() else {"cases": {}}
    rows = []
    for case in cases:
        commands = [command] + ([[args.against]] if args.against else [])
        times, unit = measured(case, folders[case.name], commands)
        seconds = times[0]
        base = baseline["cases"].get(case.name)
        units = seconds / unit
        ratio = None if base is None else units / base["units"]
        row = {"benchmark": "regression", "case": case.name, "seconds": round(seconds, 3),
               "units": round(units, 3), "baseline_units": None if base is None else base["units"],
               "baseline_s": None if base is None else base["seconds"],
               "ratio": None if ratio is None else round(ratio, 3),
               "slower": ratio is not None and ratio > SLOWER, "unit_s": round(unit, 4)}
        if args.against:
            row.update(against_s=round(times[1], 3), same_run_ratio=round(seconds / times[1], 3))
        print(json.dumps(row), flush=True)
        rows.append(row)
    print(table(rows), file=sys.stderr)
    if args.record:
        recorded = {**baseline["cases"], **{r["case"]: {"seconds": r["seconds"], "units": r["units"]}
                                            for r in rows}}
        BASELINE.write_text(json.dumps({"recorded": time.strftime("%Y-%m-%d"), "code": args.code,
                                        "machine": machine, "cases": recorded}, indent=1) + "\n")
    return int(any(r["slower"] for r in rows))


if __name__ == "__main__":
    sys.exit(main())
