"""Every option's rule, declared once: :class:`Interval` (a range) and
:class:`Choice` (one of a few names), and the choices that more than one part
of mpe3d offers (the camera models, the objectives, the losses, the starts).

The config keys (:data:`mpe3d.harness.experiment.config.KEYS`), a solver's
options (``register_solver(constraints=...)``), the command line's
``choices``, ``reconstruct``'s and ``bundle_adjust``'s checks and the
generated references all read these declarations, so that a rule cannot
drift between them. Light to import: the command line reads it while it
builds its parser.
"""

from __future__ import annotations

from dataclasses import dataclass

from mpe3d.errors import MpeError, suggest

__all__ = ["CAMERAS", "CAMERA_MODELS", "COLMAP_CAMERAS", "COLMAP_MAPPERS", "COLMAP_SOLVERS", "Choice",
           "DEFAULT_MATCHES", "INITS", "Interval", "MATCHES", "OBJECTIVES", "OUTLIER_THRESHOLD", "OUTLIER_THRESHOLDS",
           "PROJECTIONS", "REPROJECTION_LOSSES", "REPROJECTION_SOLVERS", "STARTS", "STRESS_LOSSES"]


@dataclass(frozen=True)
class Interval:
    """An option's allowed range, as in scikit-learn's ``_parameter_constraints``:
    ``kind`` (int or float) between ``low`` and ``high`` (``None``: unbounded),
    each end included or not (``closed``: "both", "left", "right", "neither")."""

    kind: type
    low: float | None
    high: float | None
    closed: str = "both"

    def __contains__(self, value) -> bool:
        left = self.closed in ("both", "left")
        right = self.closed in ("both", "right")
        return ((self.low is None or value > self.low or (left and value == self.low))
                and (self.high is None or value < self.high or (right and value == self.high)))

    def _bound(self) -> str:
        """The range alone: ">= 4", "< 1", "in [0, 1)"."""
        closed_low, closed_high = self.closed in ("both", "left"), self.closed in ("both", "right")
        if self.high is None:
            return f"{'>=' if closed_low else '>'} {self.low:g}"
        if self.low is None:
            return f"{'<=' if closed_high else '<'} {self.high:g}"
        return f"in {'[' if closed_low else '('}{self.low:g}, {self.high:g}{']' if closed_high else ')'}"

    def __str__(self) -> str:
        return f"{'an integer' if self.kind is int else 'a number'} {self._bound()}"

    def requirement(self) -> str:
        """The rule as a config error says it: "must be at least 4",
        "must be between 64 and 4096", "must be in [0, 1)"."""
        if self.kind is int and self.high is None and self.closed in ("both", "left") and self.low > 0:
            return f"must be at least {self.low:g}"  # a count
        if self.kind is int and None not in (self.low, self.high) and self.closed == "both":
            return f"must be between {self.low:g} and {self.high:g}"
        return f"must be {self._bound()}"

    def check(self, key: str, value, unit: str = "") -> None:
        """Raise one line naming ``key`` when ``value`` breaks the rule."""
        if value not in self:
            raise MpeError(f"{key}: {self.requirement()}{f' {unit}' if unit else ''}, got {value}", key=key)


@dataclass(frozen=True)
class Choice:
    """An option that takes one of a few names."""

    names: tuple[str, ...]

    def __contains__(self, value) -> bool:
        return value in self.names

    def __iter__(self):
        return iter(self.names)

    def __len__(self) -> int:
        return len(self.names)

    def __str__(self) -> str:
        return "one of " + ", ".join(self.names)

    def index(self, name: str) -> int:
        return self.names.index(name)

    def check(self, key: str, value) -> None:
        """Raise one line naming ``key`` (and the nearest name) when ``value`` is not a choice."""
        if value not in self.names:
            raise MpeError(f"{key}: '{value}' is not one of {', '.join(self.names)}", key=key,
                           hint=suggest(str(value), self.names))


# The camera models of the reprojection objective (solvers.sfm.cameras), and
# the choice a user has: one of them, or auto (the data decide).
CAMERA_MODELS = Choice(("orthographic", "scaled", "perspective", "radial"))
CAMERAS = Choice(("auto", *CAMERA_MODELS))
# What reconstruct and pipeline=tracks minimise: bundle adjustment's
# reprojection error, or the 3DMPE stress (paper Eq. 1) of the pixel distances.
OBJECTIVES = Choice(("reprojection", "stress"))
# The stress's losses, in the order of the kernels' loss codes, and the
# reprojection error's (scipy's names).
STRESS_LOSSES = Choice(("l2", "huber", "soft_l1"))
REPROJECTION_LOSSES = Choice(("l2", "huber", "soft_l1", "cauchy"))
# Who minimises the reprojection error: mpe3d's bundle adjustment, or COLMAP's
# geometric verification and one of its mappers on the same tracks: colmap
# the incremental one, colmap_global the global one (GLOMAP's).
COLMAP_SOLVERS = {"colmap": "incremental", "colmap_global": "global"}  # each solver's COLMAP mapper
COLMAP_MAPPERS = Choice(tuple(COLMAP_SOLVERS.values()))
REPROJECTION_SOLVERS = Choice(("bundle", *COLMAP_SOLVERS))
# The camera choices COLMAP's mapper takes: it has no affine camera.
COLMAP_CAMERAS = Choice(("auto", "radial", "perspective"))
# Which matches of a COLMAP database (or of photos) make the tracks: the raw
# ones of the matcher, or those its two-view geometric verification kept.
MATCHES = Choice(("raw", "verified"))
DEFAULT_MATCHES = "raw"  # every reader's and the command line's: the solve finds the wrong ones
# Where bundle adjustment starts: mpe3d's own start, or a Bundler/BAL file's.
STARTS = Choice(("own", "file"))
# Observations beyond this many robust sigmas are wrong matches: real tracks
# have heavy tails (0.1% of VGG's verified house and dino observations lie
# beyond 26-58 sigmas of a pinhole fit), while a wrong match is typically
# hundreds of sigmas away. inf keeps every observation.
OUTLIER_THRESHOLD = 20.0
OUTLIER_THRESHOLDS = Interval(float, 0, None, "neither")
# A stress solver's starting point: the baseline (MDS), or uniform in the unit cube.
INITS = Choice(("smart", "random"))
# Given projections P^k, or estimated ones (the paper's two settings).
PROJECTIONS = Choice(("fixed", "variable"))
