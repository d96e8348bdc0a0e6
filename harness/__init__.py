"""mpe3d's experiment harness: scenes, configs, metrics and the command line."""

__version__ = "0.1.0"
