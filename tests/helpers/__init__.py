"""What tests share, imported as `from helpers import ...` (never from conftest, which holds only
fixtures): paths, the real `rover` command in a subprocess, datasets written on the fly, the
reference data, and one way to wait for a condition."""

from helpers.cli import popen_rover, run_rover, stop_while_writing
from helpers.data import LAP, T0_NS, read_bag, strip_truth, write_imu_dataset
from helpers.paths import ROOT, TESTS, free_port, reference_data
from helpers.wait import wait_for_file, wait_for_line, wait_until

__all__ = [
    "LAP",
    "ROOT",
    "T0_NS",
    "TESTS",
    "free_port",
    "popen_rover",
    "read_bag",
    "reference_data",
    "run_rover",
    "stop_while_writing",
    "strip_truth",
    "wait_for_file",
    "wait_for_line",
    "wait_until",
    "write_imu_dataset",
]
