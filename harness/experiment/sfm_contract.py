"""The contract of an SfM plug-in, checked as :mod:`.contract` checks a stress
solver's: on small scenes of our own, through the same
:func:`~mpe3d.solvers.sfm.methods.run_sfm` a photos sweep uses.

The scenes are pinhole photos made in code: :data:`SCENE` points in a unit
cube, cameras on an arc looking at it, 640 × 480 px at a focal length of
500 px, keypoints projected without noise, and each photo missing some
points; once with the EXIF focal length given, once without. A method passes
when, in both, its output keeps the types and shapes of the contract
(checked by ``run_sfm``), one seed gives one result whatever numpy's global
state, and the poses it returns are usable: every ordered pair of registered
photos within :data:`POSE_BOUND` degrees of the truth (the larger of the
relative rotation's error and the angle between the relative translations'
directions, as COLMAP's benchmark scores a pair). Each failure is one line.
"""

from __future__ import annotations

import numpy as np

from mpe3d.errors import MpeError
from mpe3d.harness.experiment.contract import Check
from mpe3d.harness.scene.metrics import relative_pose_errors
from mpe3d.solvers.sfm.methods import SfmResult, SfmView, get_sfm, run_sfm

SCENE = {"points": 60, "photos": 6, "width": 640, "height": 480, "focal_px": 500.0,
         "arc_deg": 60.0, "distance": 3.0, "hidden": 0.15}  # share of points each photo misses
POSE_BOUND = 5.0  # degrees: loose, a usable pose on noise-free photos is far closer
SAME_RUN = 1e-9  # as the stress contract's: BLAS may round by memory alignment, which no seed fixes
CASES = {"EXIF focal": True, "no EXIF focal": False}


def check_sfm(name: str, random_state: int = 0) -> list[str]:
    """The contract's failures for SfM plug-in ``name``, a line each (empty: it passes).

    Use it in a test: ``assert check_sfm("mine") == []``.
    """
    return [c.line() for c in run_sfm_checks(name, random_state) if not c.passed]


def run_sfm_checks(name: str, random_state: int = 0) -> list[Check]:
    """Every check of the SfM contract for plug-in ``name`` (see the module doc)."""
    get_sfm(name)  # an unknown name is one line before anything runs
    checks: list[Check] = []
    for case, exif in CASES.items():
        checks += _in_case(name, case, exif, random_state)
    return checks


def _in_case(name: str, case: str, exif: bool, seed: int) -> list[Check]:
    views, truth = synthetic_views(seed, exif)
    first = _run(name, views, seed, f"result ({case})", global_seed=1)
    if isinstance(first, Check):  # it raised: the checks below would only repeat it
        return [first]
    checks = [_result(first, case)]
    if not checks[-1].passed:
        return checks
    again = _run(name, views, seed, f"seed ({case})", global_seed=2)  # numpy's global state drawn otherwise
    checks.append(again if isinstance(again, Check) else _determinism(first, again, seed, case))
    checks.append(_poses(first, views, truth, case))
    return checks


def synthetic_views(seed: int, exif: bool) -> tuple[list[SfmView], dict[str, tuple[np.ndarray, np.ndarray]]]:
    """Noise-free pinhole photos of :data:`SCENE` and their true poses ``{name: (R, t)}``.

    Track ids are neither 0-based nor contiguous and each photo lists its
    keypoints in its own order, as a matcher's tracks are.
    """
    rng = np.random.default_rng(seed)
    n, k = SCENE["points"], SCENE["photos"]
    points = rng.uniform(-0.5, 0.5, (n, 3))
    ids = 1000 + 7 * rng.permutation(n)
    size = (SCENE["width"], SCENE["height"])
    centre = np.array(size, dtype=float) / 2
    views, truth = [], {}
    for j, angle in enumerate(np.radians(np.linspace(-SCENE["arc_deg"] / 2, SCENE["arc_deg"] / 2, k))):
        R, t = _look_at(angle, SCENE["distance"], height=0.3 * np.sin(3 * angle))
        cam = points @ R.T + t
        xy = SCENE["focal_px"] * cam[:, :2] / cam[:, 2:] + centre
        seen = rng.permutation(n)[int(SCENE["hidden"] * n):]  # each point is still seen by most photos
        name = f"photo_{j:02d}.jpg"
        views.append(SfmView(name=name, ids=ids[seen].astype(np.int64), xy=xy[seen], image_size=size,
                             focal_px=SCENE["focal_px"] if exif else None, camera=0))
        truth[name] = (R, t)
    return views, truth


def _look_at(angle: float, distance: float, height: float) -> tuple[np.ndarray, np.ndarray]:
    """World -> camera of a camera at ``angle`` on a circle round the origin, looking at it
    (y down in the image, as in pixels)."""
    from mpe3d.harness.scene.rendering import look_at  # here: it loads trimesh and numba

    position = np.array([distance * np.sin(angle), height, -distance * np.cos(angle)])
    R = look_at(position[None])[0]
    return R, -R @ position


def _run(name: str, views: list[SfmView], seed: int, check: str, global_seed: int) -> SfmResult | Check:
    """The method's result, numpy's global state seeded with ``global_seed``
    first, or a failed ``check`` when it raised (any error of its own is a failure)."""
    np.random.seed(global_seed)
    try:
        return run_sfm(name, views, seed)  # types, shapes, finiteness, names and ids: checked there
    except MpeError as exc:
        return Check(check, False, str(exc))
    except Exception as exc:  # noqa: BLE001 - reported in one line, as the stress contract does
        return Check(check, False, f"raised {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}")


def _result(result: SfmResult, case: str) -> Check:
    if not result.poses:
        return Check(f"result ({case})", False, "registered no photo of a noise-free scene")
    return Check(f"result ({case})", True)


def _determinism(first: SfmResult, again: SfmResult, seed: int, case: str) -> Check:
    gap = _gap(first, again)
    if gap is not None:
        return Check(f"seed ({case})", False, f"two runs with random_state={seed} differ ({gap}): "
                     "draw every random number from a generator built from random_state")
    return Check(f"seed ({case})", True)


def _gap(a: SfmResult, b: SfmResult) -> str | None:
    """How two results differ, or None when they are the same."""
    if set(a.poses) != set(b.poses):
        return f"registered {len(a.poses)} then {len(b.poses)} photos"
    if not np.array_equal(np.asarray(a.point_ids), np.asarray(b.point_ids)):
        return "placed other points"
    extent = max(float(np.ptp(np.asarray(a.points, dtype=float), axis=0).max()) if len(a.points) else 0.0, 1e-300)
    pairs = [(np.asarray(a.points, dtype=float), np.asarray(b.points, dtype=float), extent)]
    for photo, pose in a.poses.items():
        other = b.poses[photo]
        pairs += [(pose.rotation, other.rotation, 1.0), (pose.translation, other.translation, extent),
                  (pose.focal_px, other.focal_px, pose.focal_px)]
    worst = max(float(np.max(np.abs(np.asarray(x, dtype=float) - np.asarray(y, dtype=float)), initial=0.0)) / scale
                for x, y, scale in pairs)
    return None if worst <= SAME_RUN else f"by up to {worst:.2g} of the scene's extent"


def _poses(result: SfmResult, views: list[SfmView], truth: dict, case: str) -> Check:
    estimated = {photo: (pose.rotation, pose.translation) for photo, pose in result.poses.items()}
    registered = {photo: truth[photo] for photo in estimated}
    if len(registered) < 2:
        return Check(f"poses ({case})", False, f"registered {len(registered)} of {len(views)} photos of a "
                     "noise-free scene: no pair to score")
    errors = relative_pose_errors(registered, estimated)
    worst = float(errors.max())
    if worst > POSE_BOUND:
        return Check(f"poses ({case})", False, f"a pair of registered photos is {worst:.3g}° off the true "
                     f"relative pose (at most {POSE_BOUND:g}° on noise-free photos): check the convention "
                     "x_cam = R x + t, R world -> camera, pixels with the origin at the top-left corner")
    note = "" if len(registered) == len(views) else f"{len(registered)} of {len(views)} photos registered; "
    return Check(f"poses ({case})", True, f"{note}worst pair {worst:.2g}°" if note else "")
