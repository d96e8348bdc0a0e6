"""mpe3d's experiment harness: scenes, configs, sweeps, tracking and the command line."""
