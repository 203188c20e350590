"""The `rover` command line and the registry of built-in operators: the top layer, free to import anything."""

import os

# Rover's operators work on small matrices (a SLAM window, a 3-antenna covariance) in threads of their
# own; OpenBLAS's thread pool on top only spins against them (it doubled the SLAM's CPU, measured).
# Set before numpy loads; an explicit setting in the environment wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from rover.cli.app import main  # noqa: E402

__all__ = ["main"]
