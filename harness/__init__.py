"""mpe3d's experiment harness: scenes, user data, experiments, tracking, and the command line.

Its subpackages are layers (docs/architecture.md; the import-linter contracts
in pyproject.toml enforce them): :mod:`.scene` and :mod:`.userdata` over
:mod:`.tracking`, :mod:`.experiment` over those, then :mod:`.runner`,
:mod:`.progress` and :mod:`.cli` on top. :mod:`.files` and :mod:`.shutdown`
are the bottom helpers every layer may use.
"""
