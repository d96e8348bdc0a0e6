"""The stages of bundle adjustment, each run when a cheap test says the data need it.

:func:`.bundle.bundle_adjust` is a short sequence of these stages, as
COLMAP's incremental pipeline is a loop over its mapper's steps. Each stage
records what it did and why (a :class:`Stage`), so that a report says which
paths ran and what decided them:

1. **suspects** (:func:`suspects`): two views at a time (:mod:`.epipolar`)
   flag the likely wrong matches, and give two noise levels for free: each
   pair's distances to its epipolar geometry (the keypoints' noise, whatever
   the camera) and to its affine epipolar hyperplane (that noise plus the
   perspective no affine camera explains).
2. **the affine start** (:func:`affine_start`): the incremental
   weak-perspective start and the scaled fit. It is the scaled camera's fit,
   and a pinhole's start or second opinion; it is not run when two views
   already show perspective (:func:`perspective_shows`) and the pinhole grown
   from them fits at the noise level.
3. **the pinhole** (:func:`pinhole`): a first opinion, the pinhole grown view
   by view (:mod:`.pinhole_start`) when two views show perspective, else the
   pinhole from the affine start; the second opinion runs only when the first
   is doubtful (:func:`doubt`: views left out, or a median residual beyond
   :data:`DOUBTFUL` times the keypoints' noise), and the better one is kept.
4. **the lens** (:func:`lens`): the radial camera, when the pinhole's
   residuals hold a lens's distortion by a model-selection rule.

What comes after (wrong matches peeled, the final adjustment) is in
:mod:`.bundle` and :mod:`.outliers`. The thresholds, and the measurements
behind them, are in docs/methods/stages.md ("How bundle adjustment decides what runs").
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from mpe3d.errors import MpeError
from mpe3d.options import CAMERAS, OUTLIER_THRESHOLDS, REPROJECTION_LOSSES
from mpe3d.solvers.sfm import incremental
from mpe3d.solvers.sfm.adjust import Fit, LMOptions, adjust, robust_cost
from mpe3d.solvers.sfm.camera_fits import FITTERS, RACE_POINTS, grown_pinhole, race_points, scaled_fit
from mpe3d.solvers.sfm.epipolar import PARTNERS, two_view_tests
from mpe3d.solvers.sfm.outliers import OUTLIER_THRESHOLD, finite_threshold, without_runaways
from mpe3d.solvers.sfm.support import informative
from mpe3d.solvers.sfm.tracks import EXACT_RMS, RAYLEIGH_MEDIAN, Tracks, image_size, residual_lengths

START_ITERATIONS = 20  # the scaled fit's when it is only a pinhole's start or rival
# Two views show perspective when the distances to their affine epipolar
# hyperplane exceed this many times those to their epipolar geometry (both
# estimate the keypoints' noise under an affine camera: measured 1.00-1.01 on
# orthographic views with 0.5-2 px of noise; 1.74 on VGG's dino, 2.09 on 250
# photos round a sphere, 4-92 on photos).
PERSPECTIVE = 1.5
# A fit is at the noise level when its median residual length is at most this
# many times the keypoints' noise: a right model's is about 1.18 times it (the
# Rayleigh median) or less where tracks are short (measured 0.63-1.21 on
# synthetic, real-track and photo sets), a wrong one's 1.64 (the scaled camera
# on dino, whose pinhole reaches 1.00) to 21. Too tight costs a second
# opinion; too loose would keep a wrong model.
AT_NOISE = 1.5
# A pinhole opinion is doubtful (a second one is fitted) when its median
# residual exceeds this many times the noise: right pinholes measured
# 0.63-1.21, and 1.65 on 250 photos in sequence, whose neighbours' keypoints
# err alike so that two of them tell too little noise (0.094 px, against
# 0.24 px from 25 photos of the same renderer); a principal point 94 px off
# 2.0, its second opinion better; the failures the second opinion is for
# (a folded affine start, a far point misleading the grown one) 7-130.
DOUBTFUL = 2.0
NOISE_FLOOR = 1e-5  # of the image size: keypoints are never more exact (as robust_sigma's)
NOISE_PARTNERS = 2  # views each view is tested with when only the noise is wanted
AUTO_RATIO = 0.8  # camera="auto" keeps the pinhole below this share of the weak median residual
GROWN_RATIO = 0.5  # the grown pinhole, leaving views out, is kept below this share of the other's median


@dataclass(frozen=True)
class BundleOptions:
    """What a bundle adjustment is asked, checked once (see :func:`.bundle.bundle_adjust`)."""

    camera: str = "auto"
    principal_point: tuple[float, float] | None = None
    shared_focal: bool = True
    focal: float | None = None  # a prior, in pixels (a photo's EXIF focal length)
    loss: str = "l2"
    loss_scale: float = 1.0
    outlier_threshold: float = OUTLIER_THRESHOLD
    max_iter: int = 100
    tol: float = 1e-10
    random_state: int = 0

    def __post_init__(self):
        CAMERAS.check("camera", self.camera)
        REPROJECTION_LOSSES.check("loss", self.loss)
        OUTLIER_THRESHOLDS.check("outlier_threshold", self.outlier_threshold)
        if self.focal is not None and not (np.isfinite(self.focal) and self.focal > 0):
            raise MpeError(f"focal: expected a focal length in pixels > 0, got {self.focal!r}")
        if self.principal_point is not None and (np.shape(self.principal_point) != (2,)
                                                 or not np.all(np.isfinite(self.principal_point))):
            raise MpeError(f"principal_point: expected two finite numbers, got {self.principal_point!r}")
        if isinstance(self.random_state, bool) or not isinstance(self.random_state, (int, np.integer)) \
                or self.random_state < 0:
            raise MpeError(f"random_state: expected an integer >= 0, got {self.random_state!r}")

    @property
    def lm(self) -> LMOptions:
        return LMOptions(self.loss, self.loss_scale, self.max_iter, self.tol)

    @property
    def robust(self) -> bool:
        """Wrong matches are looked for (a finite threshold)."""
        return bool(np.isfinite(self.outlier_threshold))


@dataclass(frozen=True)
class Stage:
    """One stage of a bundle adjustment: what ran (or not), why, and its seconds."""

    name: str
    ran: bool
    why: str
    seconds: float = 0.0

    def numbers(self) -> dict:
        return {"stage": self.name, "ran": self.ran, "why": self.why, "seconds": round(self.seconds, 4)}


@dataclass
class Opinion:
    """A pinhole fit, the views it registers and the observations it rests on."""

    fit: Fit
    registered: np.ndarray  # (K,) bool
    rests_on: np.ndarray  # (T,) bool
    source: str  # "grown" or "affine start"
    solved: bool  # to the options' tolerance (False: loosely, as a start the last solves finish)


@dataclass
class BundleState:
    """A bundle adjustment under way: what the stages found so far."""

    tracks: Tracks
    options: BundleOptions
    flagged: np.ndarray = None  # (T,) bool: suspected wrong matches, left out of every fit
    noise: float = float("nan")  # the keypoints' noise (pixels), NaN when no pair tells it
    affine: float = float("nan")  # the distances to two views' affine epipolar geometry (pixels)
    fits: dict = field(default_factory=dict)  # model -> Fit
    rows: dict = field(default_factory=dict)  # model -> (T,) bool: the observations it rests on
    solved: dict = field(default_factory=dict)  # model -> bool: solved to the tolerance asked
    registered: np.ndarray = None  # (K,) bool: the views the kept pinhole registers
    affine_rms: float = float("nan")  # the affine factorisation's RMS (pixels)
    stages: list = field(default_factory=list)

    def __post_init__(self):
        if self.flagged is None:
            self.flagged = np.zeros(len(self.tracks.view), dtype=bool)
        if self.registered is None:
            self.registered = np.ones(self.tracks.n_views, dtype=bool)

    @property
    def used(self) -> np.ndarray:
        """The observations every fit uses: not suspected, of points seen twice."""
        return informative(self.tracks, ~self.flagged)

    def median(self, model: str) -> float:
        return float(np.median(residual_lengths(*self.fits[model][:2], self.tracks, self.rows[model])))

    def rms(self, model: str) -> float:
        return float(np.sqrt(np.mean(residual_lengths(*self.fits[model][:2], self.tracks,
                                                      self.rows[model]) ** 2)))

    def record(self, name: str, ran: bool, why: str, since: float | None = None) -> None:
        self.stages.append(Stage(name, ran, why, 0.0 if since is None else time.perf_counter() - since))


def suspects(state: BundleState) -> None:
    """Stage 1: the two-view tests' suspects (when wrong matches are looked
    for) and the keypoints' two noise levels."""
    start = time.perf_counter()
    tracks, options = state.tracks, state.options
    floor = NOISE_FLOOR * image_size(tracks)
    tests = two_view_tests(tracks.view, tracks.point, tracks.z, tracks.n_views, tracks.n_points,
                           floor=floor, seed=options.random_state,
                           partners=PARTNERS if options.robust else NOISE_PARTNERS)
    if options.robust:
        state.flagged = tests.flagged.copy()
    state.noise = max(tests.noise, floor) if np.isfinite(tests.noise) else float("nan")
    state.affine = max(tests.affine, floor) if np.isfinite(tests.affine) else float("nan")
    found = f"{int(state.flagged.sum())} observations suspected; " if options.robust else ""
    state.record("suspects", True, found + (
        f"keypoint noise {state.noise:.3g} px, affine epipolar misfit {state.affine:.3g} px"
        if np.isfinite(state.noise) else "no pair of views has matches enough to tell the noise"), start)


def perspective_shows(state: BundleState) -> bool:
    """Two views at a time already show perspective (:func:`shows_perspective`)."""
    return shows_perspective(state.noise, state.affine)


def shows_perspective(noise: float, affine: float) -> bool:
    """The affine epipolar misfit beyond PERSPECTIVE times the keypoints'
    noise (both in pixels; False when the noise is unknown)."""
    return bool(np.isfinite(noise) and affine > PERSPECTIVE * noise)


def affine_start(state: BundleState, short: bool) -> None:
    """Stage 2: the incremental weak-perspective start and the scaled fit from
    it and from the factorisation (:func:`.camera_fits.scaled_fit`); ``short``:
    solved for START_ITERATIONS at most, as a pinhole's start or rival."""
    start = time.perf_counter()
    tracks, options = state.tracks, state.options
    used = state.used
    grown = incremental.incremental_start(tracks.subset(used), finite_threshold(options.outlier_threshold),
                                          random_state=options.random_state)
    if grown is not None and options.robust:  # its left-outs are suspects too
        state.flagged[np.flatnonzero(used)[grown.left_out]] = True
        used = state.used
    lm = options.lm.short(START_ITERATIONS) if short else options.lm
    state.fits["scaled"], state.affine_rms = scaled_fit(tracks.subset(used), lm,
                                                        None if grown is None else grown[:2])
    state.rows["scaled"], state.solved["scaled"] = used, not short
    state.record("affine start", True, ("a start or rival, solved for at most "
                                        f"{START_ITERATIONS} iterations" if short else "solved to the end"), start)


def exact(state: BundleState, model: str) -> bool:
    """The model explains the keypoints to the last digits: nothing fits better."""
    return state.rms(model) <= 1e3 * EXACT_RMS * image_size(state.tracks)


def at_noise(state: BundleState, model: str) -> str:
    """Why ``model``'s fit is at the noise level, or "" when it is not (or the noise is unknown)."""
    if exact(state, model):
        return f"the {model} camera explains the keypoints exactly"
    median = state.median(model)
    if np.isfinite(state.noise) and median <= AT_NOISE * state.noise:
        return (f"the {model} camera's median residual {median:.3g} px is within {AT_NOISE:g} x the "
                f"keypoints' noise {state.noise:.3g} px")
    return ""


def doubt(state: BundleState, opinion: Opinion) -> str:
    """Why a pinhole opinion is doubtful, or "" when it is not."""
    left_out = int((~opinion.registered).sum())
    if left_out:
        return f"it leaves {left_out} view(s) out"
    if not np.isfinite(state.noise):
        return "the keypoints' noise is unknown (no pair of views has matches enough)"
    median = float(np.median(residual_lengths(*opinion.fit[:2], state.tracks, opinion.rests_on)))
    if median > DOUBTFUL * state.noise:
        return (f"its median residual {median:.3g} px is over {DOUBTFUL:g} x the keypoints' noise "
                f"{state.noise:.3g} px")
    return ""


def pinhole(state: BundleState) -> None:
    """Stage 3: the pinhole camera's fit: a first opinion, and a second one
    only when the first is doubtful (:func:`doubt`), the better one kept
    (:func:`_better`). The grown pinhole goes first where two views show
    perspective (or where no affine start has run), the pinhole from the
    affine start otherwise; the grown one needs one shared focal length."""
    options = state.options
    can_grow = options.shared_focal
    first = "grown" if can_grow and (perspective_shows(state) or "scaled" not in state.fits) else "affine start"
    opinion = _opinion(state, first)
    why = doubt(state, opinion) if opinion is not None else "no pair of views starts it"
    second = "affine start" if first == "grown" else ("grown" if can_grow else None)
    if not why or second is None:
        state.record("second pinhole", False, f"the {first} pinhole " + (
            "is at the noise level and registers every view" if not why else f"is doubtful ({why}), "
            "and the grown start needs one shared focal length"))
    else:
        start = time.perf_counter()
        other = _opinion(state, second)
        opinion = other if opinion is None else opinion if other is None else _better(state, opinion, other)
        state.record("second pinhole", True, f"the {first} pinhole is doubtful ({why}); kept: the "
                     f"{opinion.source} one", start)
    state.fits["perspective"], state.rows["perspective"] = opinion.fit, opinion.rests_on & state.used
    state.registered, state.solved["perspective"] = opinion.registered, opinion.solved


def _opinion(state: BundleState, source: str) -> Opinion | None:
    """The pinhole fit from ``source``: "grown" (None when no pair starts it)
    or "affine start" (run first if it has not)."""
    start = time.perf_counter()
    tracks, options = state.tracks, state.options
    used = state.used
    if source == "grown":
        # solved loosely: an opinion is judged by its median residual, and the
        # rounds of wrong matches solve the kept one to the end (100 photos:
        # 47 iterations, 2.2 s, to 1e-10, most of them on points of weak geometry)
        grown = grown_pinhole(tracks.subset(used), options.principal_point, options.lm.loose(),
                              options.focal, options.random_state)
        state.record("grown pinhole", True, ("two views show perspective" if perspective_shows(state)
                                             else "a second opinion") + "; started at " + (
            f"the prior focal length {options.focal:.4g} px" if options.focal is not None
            else "1.2 times the image size (no prior focal length)"), start)
        if grown is None:
            return None
        rests_on = np.zeros(len(tracks.view), dtype=bool)
        rests_on[np.flatnonzero(used)[grown[2]]] = True
        if not options.robust:  # every observation kept: the fit rests on all of its views'
            rests_on = used & grown[1][tracks.view]
        return Opinion(grown[0], grown[1], rests_on, source, solved=False)
    if "scaled" not in state.fits:
        affine_start(state, short=True)
        start, used = time.perf_counter(), state.used  # the start's left-outs are suspects now
    scaled = state.fits["scaled"]
    fit = FITTERS["perspective"](*scaled[:2], tracks.subset(used), options.principal_point,
                                 options.shared_focal, options.lm, options.focal)
    fit, runaways = without_runaways(fit, tracks, used, options.lm)
    state.flagged |= runaways  # suspects, as the two-view test's are
    state.record("pinhole from the affine start", True, "raced from focal lengths (the prior's among "
                 "them, when one is given) and both depth orders", start)
    return Opinion(fit, np.ones(tracks.n_views, dtype=bool), np.ones(len(tracks.view), dtype=bool), source, True)


def _better(state: BundleState, first: Opinion, second: Opinion) -> Opinion:
    """Of the grown pinhole and the one from the affine start, the grown one
    when it registers every view with a median residual no larger on the
    observations both rest on, or, leaving views out, with one under
    GROWN_RATIO times the other's (close photos from far apart fold the
    affine start; a guessed principal point can mislead the grown one)."""
    grown, other = (first, second) if first.source == "grown" else (second, first)
    rows = grown.rests_on & state.used
    theirs, ours = (float(np.median(residual_lengths(*o.fit[:2], state.tracks, rows))) for o in (grown, other))
    keep = theirs <= ours if grown.registered.all() else theirs < GROWN_RATIO * ours
    return grown if keep else other


def lens(state: BundleState, pinhole: Fit, tracks: Tracks, rows: np.ndarray, asked: bool) -> Fit | None:
    """Stage 4: the radial camera (one lens, k1 and k2, fitted from the
    pinhole's solution on the observations ``rows``, those the rounds of
    wrong matches kept: a lens fitted before them bends to the wrong matches
    at the frame's edges), when it is ``asked`` for, or, for
    ``camera="auto"``, when it explains the keypoints better; None when it
    does not.

    The rule is the Bayesian information criterion of the two nested models
    on their robust residuals (:func:`_lens_criterion`), first on at most
    RACE_POINTS points (both models refitted there from the pinhole's
    solution), and, when the radial camera wins there, on all. With no
    distortion the pinhole's cost exceeds the radial camera's by about 2
    (a chi-square of 2 degrees of freedom), under the penalty of 2 log n;
    a lens of k1 = -0.03 at f = 2,400 px moves the corners by 9 px and the
    cost by far more.
    """
    start = time.perf_counter()
    options = state.options
    # fitted loosely: its rounds of wrong matches finish it (11 photos of
    # 3,000 px through a lens: this stage 6.7 -> 1.1 s, the rounds' no longer)
    sub, lm = tracks.subset(rows), options.lm.loose()
    if asked:
        radial = FITTERS["radial"](*pinhole[:2], sub, options.principal_point, options.shared_focal, lm)
        state.record("lens", True, "the radial camera asked for", start)
        return radial
    raced = race_points(sub)
    scout = rows if raced is None else rows & raced[tracks.point]
    # on the scouts, the pinhole is refitted as the radial camera is: neither
    # gains from the points left out
    scouted = adjust(*pinhole[:2], tracks.subset(scout), lm) if raced is not None else pinhole
    radial = FITTERS["radial"](*scouted[:2], tracks.subset(scout), options.principal_point, True, lm)
    better, why = _lens_criterion(scouted, radial, tracks, scout)
    if better and raced is not None:  # shown on the scouts: fitted and judged on all
        radial = FITTERS["radial"](*pinhole[:2], sub, options.principal_point, True, lm)
        better, why = _lens_criterion(pinhole, radial, tracks, rows)
    state.record("lens", True, why + ("" if raced is None else f" (decided on {RACE_POINTS} points first)"),
                 start)
    return radial if better else None


def _lens_criterion(pinhole: Fit, radial: Fit, tracks: Tracks, rows: np.ndarray) -> tuple[bool, str]:
    """The information criterion of :func:`lens` on the robust residuals of
    the observations ``rows``: each fit's cost under soft_l1 at the
    pinhole's robust sigma (a Gaussian's -2 log-likelihood for residuals
    within it, growing only linearly beyond, so that the wrong matches not
    yet peeled off do not decide), the radial camera kept when the pinhole's
    exceeds its by more than 2 log n (n residual coordinates, 2 more
    parameters: the BIC)."""
    lengths = residual_lengths(*pinhole[:2], tracks, rows)
    sigma = max(float(np.median(lengths)) / RAYLEIGH_MEDIAN, 1e-300)
    robust = LMOptions(loss="soft_l1", loss_scale=sigma)
    cost_pinhole = robust_cost(lengths ** 2, robust) / sigma ** 2
    cost_radial = robust_cost(residual_lengths(*radial[:2], tracks, rows) ** 2, robust) / sigma ** 2
    if not np.isfinite(cost_radial):
        return False, "the plain pinhole: the radial fit failed"
    gain, penalty = cost_pinhole - cost_radial, 2 * np.log(2 * int(rows.sum()))
    k1, k2 = radial.cameras.distortion()[0]
    verdict = "the radial camera" if gain > penalty else "the plain pinhole"
    return gain > penalty, (f"{verdict}: information gain {gain:.3g} against a penalty of {penalty:.3g} "
                            f"(k1 = {k1:.3g}, k2 = {k2:.3g})")
