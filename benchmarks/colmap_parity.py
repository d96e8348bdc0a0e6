"""Ours against COLMAP's mapper on identical raw matches, one JSON line a case.

    python benchmarks/colmap_parity.py [--shapes airplane chair lamp] [--sizes 10 25 100]
                                       [--seeds 0 1 2] [--threads 1] [--photos DIR ...]

Each rendered case: the bundled shape photographed along a closed spiral
(``mpe3d.harness.scene.rendering``, the path turned by an angle drawn from the
seed, the texture drawn from it too), SIFT features and matches extracted
once by pycolmap (exhaustive up to 50 photos, sequential beyond), the raw
matches joined into tracks, and the same tracks given to both methods
through :func:`mpe3d.reconstruct`: ``solver="bundle"`` (ours, default
camera) and ``solver="colmap"`` (COLMAP's geometric verification and
incremental mapper). Each cloud is moved into the mesh's frame by the
similarity that takes its camera centres onto the true ones (robust, the
only use of ground truth before scoring); then

* the 3D error of the tracks both place: each point's distance to the mesh
  surface, median and 90th percentile, in % of the mesh's bounding-box
  diagonal;
* the camera-centre error: median distance of the registered centres to the
  true ones after that similarity, same unit;
* registered views, points placed, time: ours is the whole solve
  (``runtime_s``), COLMAP's is its verification plus mapping only (the
  database it is handed is not counted), at the same thread count.

``--summarise LINES.jsonl`` prints the shape x size table of a run's lines
(medians over seeds, ours / COLMAP's). ``--photos DIR`` adds real photo folders (no reference): both methods on the
same tracks, COLMAP's camera centres against ours after a similarity (in %
of the centres' extent), reprojection RMS, registered views, time. A real
set fetched for this goes to a scratch folder, never into the repository.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from machine import describe

from mpe3d.harness.scene import metrics, rendering, shapes
from mpe3d.harness.userdata import photo_folder, photos
from mpe3d.harness.userdata.reconstruct import reconstruct
from mpe3d.solvers import threads
from mpe3d.solvers.sfm import colmap

METHODS = ("bundle", "colmap")


def spiral(count: int, size: int, seed: int, fill: float = 0.85) -> rendering.PhotoCameras:
    """The spiral of ``rendering.spiral_cameras`` with photos about 15-18 degrees
    apart (the spacing photogrammetry guides ask for: half a turn for 10
    photos, one for 25, two for 100 and more), turned about the vertical by
    an angle drawn from ``seed``."""
    cams = rendering.spiral_cameras(count, size=size, turns=min(2.0, max(0.5, count / 25)), fill=fill)
    a = np.random.default_rng(seed).uniform(0, 2 * np.pi)
    turn = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    return rendering.PhotoCameras(cams.rotations @ turn.T, cams.translations, cams.focal, cams.width,
                               cams.height)


def tracks_of(folder: Path, names: list[str], workdir: Path, count_threads: int) -> tuple[list[dict], dict]:
    database = workdir / "database.db"
    seconds = colmap.extract_and_match(database, folder, names, threads=count_threads)
    return photos.read_database(database, "raw"), seconds


def centres_of(result) -> dict[str, np.ndarray]:
    """Registered pinholes' centres (an affine camera has none: it is at infinity)."""
    return {c.view: -c.rotation.T @ c.translation for c in result.cameras
            if c.registered and c.translation is not None}


def solve(views: list[dict], method: str, seed: int) -> tuple[object, float, float]:
    start = time.perf_counter()
    result = reconstruct(views, solver=method, random_state=seed)
    wall = time.perf_counter() - start
    facts = result.facts
    timed = sum(facts["colmap_seconds"].values()) if method == "colmap" else facts["runtime_s"]
    return result, timed, wall


def placed_ids(result) -> set:
    return set(result.ids.tolist()) - set(result.unplaced.tolist())


def surface_distance(mesh, points: np.ndarray, candidates: int = 32) -> np.ndarray:
    """Each point's exact distance to the mesh surface, over the ``candidates``
    triangles whose centroids are nearest (trimesh's own query needs rtree)."""
    from scipy.spatial import cKDTree
    from trimesh.triangles import closest_point

    k = min(candidates, len(mesh.faces))
    _, near = cKDTree(mesh.triangles_center).query(points, k=k)
    near = near.reshape(len(points), k)
    repeated = np.repeat(points, k, axis=0)
    closest = closest_point(mesh.triangles[near.ravel()], repeated)
    return np.linalg.norm(closest - repeated, axis=1).reshape(len(points), k).min(axis=1)


def scores(result, mesh, true_centres: dict, both: set, rng, views: set | None = None) -> dict:
    """The errors of the module doc; the similarity is fitted on ``views``
    (those both methods register), so that a view one method alone places
    weighs on neither its alignment nor its centre error."""
    est = centres_of(result)
    names = [n for n in est if n in true_centres and (views is None or n in views)]
    if len(names) < 3:  # nothing to put the cloud in the mesh's frame by: the case is lost
        return {"median_pct": None, "p90_pct": None, "centre_pct": None, "camera": result.facts["camera"],
                "registered": sum(c.registered for c in result.cameras), "placed": len(placed_ids(result)),
                "rms_px": result.facts["reprojection_rms_px"]}
    s, Q, t = metrics.robust_similarity(np.array([est[n] for n in names]),
                                        np.array([true_centres[n] for n in names]), rng)
    centre_error = np.linalg.norm(s * np.array([est[n] for n in names]) @ Q.T + t
                                  - np.array([true_centres[n] for n in names]), axis=1)
    rows = np.isin(result.ids, list(both))
    cloud = s * result.points[rows] @ Q.T + t
    distance = surface_distance(mesh, cloud)
    unit = float(np.linalg.norm(mesh.extents)) / 100  # percent of the diagonal
    return {"median_pct": float(np.median(distance) / unit),
            "p90_pct": float(np.percentile(distance, 90) / unit),
            "centre_pct": float(np.median(centre_error) / unit),
            "camera": result.facts["camera"], "registered": len(centres_of(result)),
            "placed": len(placed_ids(result)), "rms_px": result.facts["reprojection_rms_px"]}


def rendered_case(shape: str, count: int, seed: int, size: int, count_threads: int) -> dict:
    mesh = shapes.load_shape(shape)
    cams = spiral(count, size, seed)
    with tempfile.TemporaryDirectory(prefix="mpe3d-parity-") as scratch:
        scratch = Path(scratch)
        start = time.perf_counter()
        names = rendering.save_images(rendering.render(mesh, cams, seed=seed), scratch / "images")
        render_s = time.perf_counter() - start
        views, seconds = tracks_of(scratch / "images", names, scratch, count_threads)
    true_centres = dict(zip(names, cams.centres))
    line = {"case": f"{shape}-{count}-s{seed}", "shape": shape, "photos": count, "seed": seed,
            "threads": count_threads, "render_s": render_s, **seconds, "views": len(views),
            "tracks": len({i for v in views for i in np.asarray(v["ids"]).tolist()})}
    results = {}
    for method in METHODS:
        try:
            results[method] = solve(views, method, seed)
        except Exception as exc:  # a method that fails loses the case; the line says why
            line[f"{method}_error"] = str(exc).splitlines()[0]
    both = set.intersection(*(placed_ids(r[0]) for r in results.values())) if results else set()
    common = set.intersection(*(set(centres_of(r[0])) for r in results.values())) if results else set()
    line["both_placed"], line["both_registered"] = len(both), len(common)
    for method, (result, timed, wall) in results.items():
        line[method] = {**scores(result, mesh, true_centres, both, np.random.default_rng(seed), common),
                        "time_s": timed, "wall_s": wall}
    return line


def real_case(folder: Path, seed: int, count_threads: int) -> dict:
    names = photo_folder.list_photos(folder)
    with tempfile.TemporaryDirectory(prefix="mpe3d-parity-") as scratch:
        views, seconds = tracks_of(folder, names, Path(scratch), count_threads)
    line = {"case": str(folder), "photos": len(names), "threads": count_threads, **seconds,
            "views": len(views)}
    results = {m: solve(views, m, seed) for m in METHODS}
    ours, theirs = centres_of(results["bundle"][0]), centres_of(results["colmap"][0])
    common = [n for n in theirs if n in ours]
    a, b = np.array([ours[n] for n in common]), np.array([theirs[n] for n in common])
    s, Q, t = metrics.robust_similarity(a, b, np.random.default_rng(seed))
    extent = float(np.linalg.norm(np.ptp(b, axis=0))) / 100
    line["centres_disagree_pct"] = float(np.median(np.linalg.norm(s * a @ Q.T + t - b, axis=1)) / extent)
    for method, (result, timed, wall) in results.items():
        line[method] = {"registered": len(centres_of(result)), "placed": len(placed_ids(result)),
                        "rms_px": result.facts["reprojection_rms_px"], "time_s": timed, "wall_s": wall}
    return line


CELL_KEYS = ("median_pct", "p90_pct", "centre_pct")  # lower is better, ours against COLMAP's


def _median(values):
    values = [v for v in values if v is not None]
    return float(np.median(values)) if values else None


def summarise(lines: list[dict]) -> str:
    """The shape x size cells as a Markdown table: each metric's median over
    the seeds, ours / COLMAP's, and whether ours is at least as good in all
    three errors and registers at least as many views."""
    cells: dict[tuple, list] = {}
    for line in lines:
        if "case" in line and "shape" in line:
            cells.setdefault((line["shape"], line["photos"]), []).append(line)
    rows = ["| shape | photos | 3D median % | 3D 90th pct % | centre % | registered | time s | ours wins |",
            "|---|---|---|---|---|---|---|---|"]
    won = 0
    for (shape, count), cases in sorted(cells.items()):
        got = {m: {k: _median([c.get(m, {}).get(k) for c in cases]) for k in (*CELL_KEYS, "registered", "time_s")}
               for m in ("bundle", "colmap")}
        ours, theirs = got["bundle"], got["colmap"]
        wins = all(ours[k] is not None and (theirs[k] is None or ours[k] <= theirs[k]) for k in CELL_KEYS) \
            and (ours["registered"] or 0) >= (theirs["registered"] or 0)
        won += wins

        shown = {k: " / ".join("-" if v is None else f"{v:.3g}" for v in (ours[k], theirs[k]))
                 for k in (*CELL_KEYS, "registered", "time_s")}
        rows.append(f"| {shape} | {count} | {' | '.join(shown.values())} | {'yes' if wins else 'no'} |")
    rows.append(f"\nours at least as good in {won} of {len(cells)} cells (each value: ours / COLMAP's, "
                "the median over seeds)")
    return "\n".join(rows)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", nargs="*", default=["airplane", "chair", "lamp"])
    parser.add_argument("--sizes", nargs="+", type=int, default=[10, 25, 100])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--size", type=int, default=400, help="photo side in pixels")
    parser.add_argument("--threads", type=int, default=1, help="both methods' thread count")
    parser.add_argument("--photos", nargs="*", default=[], type=Path, help="real photo folders")
    parser.add_argument("--summarise", type=Path, metavar="LINES.jsonl",
                        help="print the shape x size table of an earlier run's lines, and stop")
    args = parser.parse_args(argv)
    if args.summarise:
        print(summarise([json.loads(line) for line in args.summarise.read_text().splitlines() if line.strip()]))
        return 0
    print(json.dumps({"machine": describe()}), flush=True)
    with threads.limit(args.threads):
        for shape in args.shapes:
            for count in args.sizes:
                for seed in args.seeds:
                    print(json.dumps(rendered_case(shape, count, seed, args.size, args.threads)), flush=True)
        for folder in args.photos:
            print(json.dumps(real_case(folder, 0, args.threads)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
