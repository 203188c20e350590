"""A real building's clutter, which gives real bearings their heavy, persistent errors.

A room of four bare walls gives a clean angle wherever the direct path is not blocked. A real one
has furniture, people, shelves and pillars: each re-radiates the tag's signal (a point scatterer, a
bistatic path tag -> scatterer -> robot whose amplitude is its reflectivity over the product of the
two distances), and they shadow the direct path as the robot moves (log-normal shadow fading along
the robot's path, correlated over a distance: Gudmundson, Electronics Letters 27(23), 1991). Where
the direct path is shadowed and a scatterer is near, the bearing follows the scatterer for as long
as the geometry holds: seconds at walking speed. That is the error real arrays show (a public
recording of four arrays measuring a robot for 22 minutes: median 6-12 deg, 90th percentile 14-48
deg per array, persisting for seconds).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter

SHADOW_STEP_M = 0.05
"""path-length spacing at which the shadowing is drawn before it is interpolated to the poses"""
WALL_MARGIN_M = 0.3
"""scatterers stand at least this far from the walls"""
PATH_CLEARANCE_M = 0.5
"""and this far from the robot's path"""
CHUNK_PLACES = 256
"""candidate places checked against the path at once"""
DRAWS_PER_SCATTERER = 20
"""candidate places drawn per scatterer"""


@dataclass(frozen=True)
class Scatterers:
    """Point scatterers in the room: positions (S, 2) and amplitude reflectivities (S,) in metres
    (a path via one has amplitude reflectivity / (d_in d_out), as a direct path of d has 1 / d)."""

    xy: np.ndarray
    reflectivity_m: np.ndarray


def place_scatterers(
    room_m: tuple[float, float],
    count: int,
    median_m: float,
    spread_db: float,
    rng: np.random.Generator,
    path_xy: np.ndarray | None = None,
) -> Scatterers:
    """`count` scatterers uniform over the room (WALL_MARGIN_M from its walls) and PATH_CLEARANCE_M
    from the robot's path (points along it a few centimetres apart, `path_xy`: the robot drives
    around furniture, not through it), their reflectivity log-normal: median `median_m`, a standard deviation of
    `spread_db` in power (the heavy tail: a metal shelf among chairs). Fewer when the room leaves
    too little space off the path (none after DRAWS_PER_SCATTERER tries each)."""
    w, h = room_m
    tries = DRAWS_PER_SCATTERER * count
    xy = np.stack(
        [rng.uniform(WALL_MARGIN_M, w - WALL_MARGIN_M, tries), rng.uniform(WALL_MARGIN_M, h - WALL_MARGIN_M, tries)],
        axis=1,
    )
    if path_xy is not None and len(path_xy) and len(xy):
        gap = np.concatenate(
            [
                np.min(np.linalg.norm(part[:, None, :] - path_xy[None, :, :], axis=-1), axis=1)
                for part in np.array_split(xy, -(-len(xy) // CHUNK_PLACES))
            ]
        )
        xy = xy[gap >= PATH_CLEARANCE_M]
    xy = xy[:count]
    reflectivity = median_m * 10 ** (rng.normal(0.0, spread_db, len(xy)) / 20)
    return Scatterers(xy, reflectivity)


def shadowing_db(along_m: np.ndarray, std_db: float, distance_m: float, rng: np.random.Generator) -> np.ndarray:
    """The direct path's shadow fading (dB, >= 0 is a loss; zero mean) at each distance travelled
    along the robot's path (N,): Gaussian with `std_db`, correlated as exp(-|d| / distance_m)
    (Gudmundson's model), drawn every SHADOW_STEP_M and interpolated."""
    if std_db == 0 or len(along_m) == 0:
        return np.zeros(len(along_m))
    grid = np.arange(0.0, float(along_m.max()) + 2 * SHADOW_STEP_M, SHADOW_STEP_M)
    rho = float(np.exp(-SHADOW_STEP_M / distance_m))
    drive = rng.standard_normal(len(grid)) * np.sqrt(1 - rho**2)
    drive[0] = rng.standard_normal()  # the process starts in its stationary law
    field = lfilter([1.0], [1.0, -rho], drive)
    return std_db * np.interp(along_m, grid, field)
