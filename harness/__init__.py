"""mpe3d's experiment harness: scenes, user data, experiments, the runner and tracking.

Its subpackages are layers (docs/architecture.md; the import-linter contracts
in pyproject.toml enforce them): :mod:`.scene` and :mod:`.userdata` over
:mod:`.tracking`, :mod:`.experiment` over those, then :mod:`.runner` and
:mod:`.progress` on top. :mod:`.files` and :mod:`.shutdown` are the bottom
helpers every layer may use. The command line (:mod:`mpe3d.cli`) and the
reports (:mod:`mpe3d.reports`) sit above the harness; it imports neither.

May import: :mod:`mpe3d.solvers`, :mod:`mpe3d.plugins`, :mod:`mpe3d.options`
and :mod:`mpe3d.errors`.
"""

__all__ = ["experiment", "files", "progress", "runner", "scene", "shutdown", "tracking", "userdata"]
