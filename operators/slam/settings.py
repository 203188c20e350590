"""The sliding window's settings: the `slam` operator's params (one set of defaults, the shipped ones)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from rover.pipeline.params import (
    Checked,
    Fraction,
    NonNegativeFloat,
    NonNegativeInt,
    ParamValueError,
    PositiveFloat,
    PositiveInt,
    Range,
)


@dataclass(frozen=True)
class WindowSettings(Checked):
    window: Annotated[int, Range(ge=2)] = 30
    """epochs kept in the window; older ones are marginalized into the prior"""
    huber_sigma: PositiveFloat = 1.5
    """AoA residuals beyond this many standard deviations count linearly (Huber)"""
    hinge_weight: NonNegativeFloat = 10.0
    """cost per (distance / (d * sigma)) of a tag placed behind its bearing"""
    reweight_passes: PositiveInt = 1
    """at most this many convex solves per update, each with the distances of the previous one;
    none while every tag in use is localized (the Gauss-Newton steps start from the last estimate).
    Each update starts from the last one's estimate, so reweighting goes on over the next epochs; on
    `paper` seeds 1-6, `long_hall` and the sample recording the estimates are the same as with 3 (to
    0.1 mm), the work per update bounded. Batch mode, which solves once, takes at least 3"""
    reweight_tolerance: PositiveFloat = 0.1
    """the passes stop once no distance to a tag not yet localized (inlier rows) changed by more than
    this fraction; for localized tags the distances of the last refined estimate are already right,
    and reweighting toward the convex solution would feed its short-range bias"""
    refine_iterations: NonNegativeInt = 2
    """at most this many Gauss-Newton steps on the angle residual after the convex passes (batch
    mode: at least 3)"""
    refine_tolerance_m: PositiveFloat = 2e-3
    """the steps stop once no state moved by more than this"""
    initial_range_m: PositiveFloat = 3.0
    """the distance guessed for a tag heard for the first time"""
    min_range_m: PositiveFloat = 0.3
    """floor of the distances in the AoA weights: no tag sits inside the robot"""
    tag_prior_std_m: PositiveFloat = 30.0
    """the prior on a newly heard tag, around its first bearing at `initial_range_m`"""
    gauge_std_m: PositiveFloat = 1e-3
    """the first pose is the origin of the world frame"""
    initial_velocity_std_m_s: PositiveFloat = 0.01
    """the robot starts from rest (the preintegration needs a still start for its gyro bias)"""
    wheel_speed_std_m_s: PositiveFloat = 0.01
    """wheel odometry speed noise"""
    wheel_scale_std: NonNegativeFloat = 0.03
    """wheel radius error, as a fraction of the speed: the prior std of the wheel scale state (with
    `wheel_scale`), else noise added to every speed"""
    wheel_scale: bool = True
    """estimate the wheel odometry's scale error as a state shared by the window and carried through
    the marginalization: a radius error is one number for the run, not noise per epoch, and over a
    long straight leg it is most of the robot's error (bearings say nothing of scale); the IMU makes
    it observable wherever the speed changes (starts, stops, turns in place)"""
    wheel_scale_walk_rts: NonNegativeFloat = 1e-4
    """how fast the wheel scale may wander (random walk, fraction per square-root second: tyre
    pressure, load)"""
    nonholonomic: bool = True
    """a wheeled base does not move sideways: its velocity is along its heading (linear given the gyro's)"""
    lateral_std_m_s: PositiveFloat = 0.02
    """how fast the robot may slip sideways"""
    reset_updates: NonNegativeInt = 20
    """a localized tag whose bearings in the window mostly disagree with its estimate (Huber-active)
    for this many updates in a row has its prior relaxed: the Gaussian prior of a tag first seen
    through wrong-path bearings can otherwise hold it at the wrong place for good. 0 turns it off."""
    reset_factor: Fraction = 0.01
    """how much of the tag's prior information is kept at such a reset"""
    observable_std_m: PositiveFloat = 0.5
    """a tag is reported localized once its position's largest standard deviation is below this"""
    source_std_m: NonNegativeFloat = 0.1
    """how far (1 sigma, in every direction) where a tag's signal appears to come from may be from
    where it is, added to every published tag covariance: a tag w in front of a wall of amplitude
    reflection rho blends with its image 2w behind it, and reads up to 2 w rho d/d' off across the
    bearing (d, d' the distances to the tag and to its image), an error that averages out only where
    the robot's motion sweeps the two paths' phase difference (toward the wall, not along it).
    Tags on walls as in the paper (w 0.25 m, rho 0.5, d/d' about 0.6 where they are seen from): up
    to 0.15 m, 0.1 m rms over the phase. 0 for tags in the open (integrity.py)"""
    aoa_std_scale: PositiveFloat = 4.0
    """multiplies each AoA's std in the window (not in the search for a tag, which compares bearings
    spread over the whole run): the operator's std describes one burst, but consecutive bursts of a
    tag share most of their multipath error, so each carries less information than its own std says
    (swept 1.5/2/3/4 over the eight robustness runs: 4 is best on average, 1.5 clearly worst)"""
    accel_bias: bool = True
    """estimate what the IMU integration left of the accelerometer bias, as window states carried
    through the marginalization: a bias fixed to the body (2D, turns with the robot) and one fixed to
    the world (2D: gravity leaking through a tilt, or a body bias aligned away at the start heading)"""
    accel_bias_std_m_s2: PositiveFloat = 0.03
    """prior std of each of those biases (about 3 mg: MEMS IMUs of the paper's class are within it)"""
    accel_bias_walk_m_s2_rts: NonNegativeFloat = 1e-4
    """how fast they may wander (random walk, per square-root second)"""
    turns_in_place: bool = True
    """an epoch the preintegration flags as turning in place has zero velocity (off for a platform
    that may rotate while it drifts, such as a drone)"""
    zero_velocity_std_m_s: PositiveFloat = 0.02
    """the velocity of such an epoch"""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.source_std_m >= self.observable_std_m:
            raise ParamValueError(
                "source_std_m",
                f"{self.source_std_m:g} m is not below observable_std_m ({self.observable_std_m:g} m): no tag "
                "could ever be published as localized",
            )
