"""mpe3d's experiment harness: scenes, configs, sweeps, tracking and the command line."""

from importlib.metadata import PackageNotFoundError, version

try:  # one source of truth: pyproject.toml
    __version__ = version("mpe3d")
except PackageNotFoundError:  # running from a checkout that was never installed
    __version__ = "0+unknown"
