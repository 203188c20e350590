"""Errors of an estimated trajectory and tag map against ground truth, the way evo computes them.

The estimator's world frame starts at the robot's first pose (x along its initial heading), so the
truth is first expressed in that frame ("unaligned" errors: what the robot itself believes). The
"aligned" errors fit one 2-D rigid transform (rotation and translation, never a scale) of the
estimate onto the truth by least squares over the associated poses (Umeyama 1991, as `evo_ape -a`)
and apply the same transform to the tags.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rover.errors import BadInput
from rover.geometry import parallax_deg, wrap_angle, yaw_from_quaternion


@dataclass(frozen=True)
class Poses2D:
    """Planar poses: stamps (ns), positions (n, 2), yaws (rad)."""

    stamp_ns: np.ndarray
    xy: np.ndarray
    yaw: np.ndarray


@dataclass(frozen=True)
class Rigid2D:
    rotation: np.ndarray
    translation: np.ndarray

    def apply(self, xy: np.ndarray) -> np.ndarray:
        moved: np.ndarray = xy @ self.rotation.T + self.translation
        return moved


def poses_of_messages(msgs: list[Any]) -> Poses2D:
    """Planar poses of geometry_msgs/PoseStamped messages, in the given order."""
    q = np.array(
        [[m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z, m.pose.orientation.w] for m in msgs]
    ).reshape(-1, 4)
    stamps = [m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec for m in msgs]
    return Poses2D(
        np.array(stamps, dtype=np.int64),
        np.array([[m.pose.position.x, m.pose.position.y] for m in msgs]).reshape(-1, 2),
        yaw_from_quaternion(*q.T),
    )


def associate(reference: Poses2D, estimate: Poses2D, max_diff_s: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (reference, estimate) of the nearest stamps within `max_diff_s` (evo's --t_max_diff)."""
    ref = reference.stamp_ns
    j = np.clip(np.searchsorted(ref, estimate.stamp_ns), 1, len(ref) - 1)
    nearer = np.where(np.abs(ref[j - 1] - estimate.stamp_ns) <= np.abs(ref[j] - estimate.stamp_ns), j - 1, j)
    ok = np.abs(ref[nearer] - estimate.stamp_ns) <= max_diff_s * 1e9
    return nearer[ok], np.nonzero(ok)[0]


def start_frame(truth: Poses2D, first_stamp_ns: int) -> Rigid2D:
    """The transform taking the truth's frame to the estimator's (origin at the pose at `first_stamp_ns`)."""
    k = int(np.argmin(np.abs(truth.stamp_ns - first_stamp_ns)))
    c, s = math.cos(truth.yaw[k]), math.sin(truth.yaw[k])
    rotation = np.array([[c, s], [-s, c]])
    return Rigid2D(rotation, -rotation @ truth.xy[k])


def fit_rigid(source: np.ndarray, target: np.ndarray) -> Rigid2D:
    """Least-squares rotation and translation taking `source` points onto `target` (no scale)."""
    if len(source) < 2:
        raise BadInput("alignment needs at least two associated poses")
    ms, mt = source.mean(axis=0), target.mean(axis=0)
    cov = (target - mt).T @ (source - ms)
    u, _, vt = np.linalg.svd(cov)
    d = np.diag([1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = u @ d @ vt
    return Rigid2D(rotation, mt - rotation @ ms)


def error_stats(errors: np.ndarray) -> dict[str, float]:
    return {
        "mean_m": float(np.mean(errors)),
        "median_m": float(np.median(errors)),
        "rmse_m": float(np.sqrt(np.mean(errors**2))),
        "max_m": float(np.max(errors)),
        "poses": int(len(errors)),
    }


@dataclass(frozen=True)
class TrajectoryErrors:
    unaligned: dict[str, float]
    aligned: dict[str, float]
    alignment: Rigid2D
    """estimate -> truth-in-start-frame"""
    to_start: Rigid2D
    """truth frame -> estimator frame"""


def trajectory_errors(
    truth: Poses2D, estimate: Poses2D, max_diff_s: float = 0.01, name: str = "the estimated trajectory"
) -> TrajectoryErrors:
    """Errors of `estimate` (called `name` in messages); BadInput when there is nothing to compare: an
    empty trajectory, or fewer than two estimated poses with a ground-truth pose within `max_diff_s`."""
    if not max_diff_s >= 0:
        raise BadInput(f"the largest stamp difference of associated poses is a number >= 0, got {max_diff_s}")
    if len(estimate.stamp_ns) == 0:
        raise BadInput(f"{name} is empty")
    if len(truth.stamp_ns) == 0:
        raise BadInput("the ground truth has no poses")
    to_start = start_frame(truth, int(estimate.stamp_ns[0]))
    i, j = associate(truth, estimate, max_diff_s)
    if len(i) < 2:
        spans = f"{name} spans {_span(estimate.stamp_ns)}; the ground truth {_span(truth.stamp_ns)}"
        if len(i) == 0:
            raise BadInput(f"{name} and the ground truth do not overlap in time (within {max_diff_s} s): {spans}")
        raise BadInput(
            f"only one pose of {name} has a ground-truth pose within {max_diff_s} s, the alignment needs two: {spans}"
        )
    reference = to_start.apply(truth.xy[i])
    est = estimate.xy[j]
    alignment = fit_rigid(est, reference)
    return TrajectoryErrors(
        error_stats(np.linalg.norm(est - reference, axis=1)),
        error_stats(np.linalg.norm(alignment.apply(est) - reference, axis=1)),
        alignment,
        to_start,
    )


def _span(stamp_ns: np.ndarray) -> str:
    """The time range of stamps, for messages: `1700000000.000-1700000012.000 s, 2 poses`, in
    integer arithmetic (a float would round the nanoseconds)."""

    def seconds(ns: int) -> str:
        ms = (ns + 500_000) // 1_000_000
        return f"{'-' if ms < 0 else ''}{abs(ms) // 1000}.{abs(ms) % 1000:03d}"

    first, last = int(stamp_ns.min()), int(stamp_ns.max())
    return f"{seconds(first)}-{seconds(last)} s, {len(stamp_ns)} pose{'s' if len(stamp_ns) != 1 else ''}"


@dataclass(frozen=True)
class RunRecord:
    """What a run estimated, as plain arrays (from memory at the end of a run, or from its files)."""

    final: Poses2D
    live: Poses2D
    tag_ids: np.ndarray
    tag_xy: np.ndarray
    """final tag estimates (nan where never localized)"""
    tag_cov: np.ndarray
    tag_history: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]
    """(stamp_ns, id, xy (n, 2), observable, covariance (n, 2, 2)) of every tag estimate published"""
    aoa: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
    """(stamp_ns, tag id, robot-frame angle, reported std) of every AoA"""
    heard: dict[int, tuple[int, int]] = field(default_factory=dict)
    """tag id -> (first, last) stamp it was heard at, ns (tags.csv's first_heard_s, last_heard_s)"""
    seen: tuple[np.ndarray, np.ndarray] = field(default_factory=lambda: (np.zeros(0, np.int64), np.zeros(0, int)))
    """(stamp_ns, tag id) of every AoA the SLAM had, resolved or not (those before a tag was found too)"""


@dataclass(frozen=True)
class Truth:
    trajectory: Poses2D
    tags: dict[int, tuple[np.ndarray, bool]]
    """id -> (xy, nlos)"""


def poses_at(truth: Poses2D, stamps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Truth position and yaw interpolated at `stamps` (clamped to its span)."""
    t = truth.stamp_ns.astype(np.float64)
    x = np.interp(stamps, t, truth.xy[:, 0])
    y = np.interp(stamps, t, truth.xy[:, 1])
    yaw = np.interp(stamps, t, np.unwrap(truth.yaw))
    return np.stack([x, y], axis=1), yaw


def angle_stats(errors_rad: np.ndarray, std_rad: np.ndarray) -> dict[str, float]:
    """Error figures, and how the reported std tracks the error (a unit Gaussian's |error| / std:
    median 0.67, 68% within 1, 99.7% within 3)."""
    deg = np.degrees(np.abs(errors_rad))
    if len(deg) == 0:
        return {"count": 0}
    z = np.abs(errors_rad) / std_rad
    return {
        "count": int(len(deg)),
        "median_deg": float(np.median(deg)),
        "p90_deg": float(np.percentile(deg, 90)),
        "mean_deg": float(np.mean(deg)),
        "error_over_std_median": float(np.median(z)),
        "within_1_std": float(np.mean(z <= 1)),
        "within_3_std": float(np.mean(z <= 3)),
    }


def evaluate(run: RunRecord, truth: Truth, max_diff_s: float = 0.01) -> dict[str, Any]:
    """metrics.json: robot errors (both trajectories, unaligned and aligned), tag errors, AoA errors."""
    final = trajectory_errors(truth.trajectory, run.final, max_diff_s, "trajectory.tum")
    metrics: dict[str, Any] = {"robot": {"trajectory.tum": {"unaligned": final.unaligned, "aligned": final.aligned}}}
    if len(run.live.stamp_ns):
        live = trajectory_errors(truth.trajectory, run.live, max_diff_s, "trajectory_live.tum")
        metrics["robot"]["trajectory_live.tum"] = {"unaligned": live.unaligned, "aligned": live.aligned}
    start = final.to_start
    tags: dict[str, dict[str, Any]] = {}
    for tag_id, xy, cov in zip(run.tag_ids, run.tag_xy, run.tag_cov, strict=True):
        if int(tag_id) not in truth.tags:
            continue
        where, nlos = truth.tags[int(tag_id)]
        reference = start.apply(np.asarray(where)[None])[0]
        entry: dict[str, Any] = {"nlos": bool(nlos), "localized": bool(np.isfinite(xy).all())}
        entry["geometry_after_s"] = geometry_after_s(run, truth, int(tag_id))
        if entry["localized"]:
            entry["localized_after_s"] = localized_after_s(run, int(tag_id))
            if entry["localized_after_s"] is not None and entry["geometry_after_s"] is not None:
                entry["localized_after_geometry_s"] = entry["localized_after_s"] - entry["geometry_after_s"]
            entry["parallax_at_localization_deg"] = parallax_at_localization_deg(run, int(tag_id))
            entry["error_m"] = float(np.linalg.norm(xy - reference))
            entry["aligned_error_m"] = float(np.linalg.norm(final.alignment.apply(xy[None])[0] - reference))
            entry["reported_std_m"] = float(math.sqrt(max(np.linalg.eigvalsh(cov)[-1], 0.0)))
            entry["sigmas"] = mahalanobis(xy - reference, cov)
        tags[str(int(tag_id))] = entry
    metrics["tags"] = tags
    for kind, flag in (("los", False), ("nlos", True)):
        errors = [t["error_m"] for t in tags.values() if t["nlos"] == flag and "error_m" in t]
        metrics[f"{kind}_tags_mean_m"] = float(np.mean(errors)) if errors else None
    metrics["published"] = published_honesty(run, truth, start)
    error, aoa_nlos, std = aoa_errors(run, truth)
    if len(error):
        metrics["aoa"] = {
            "all": angle_stats(error, std),
            "los": angle_stats(error[~aoa_nlos], std[~aoa_nlos]),
            "nlos": angle_stats(error[aoa_nlos], std[aoa_nlos]),
        }
    return metrics


def localized_after_s(run: RunRecord, tag_id: int) -> float | None:
    """Seconds from the tag's first AoA to its first estimate published as localized (None: never,
    or not heard)."""
    stamps, ids, _, observable, _ = run.tag_history
    mine = observable & (ids == tag_id)
    if not mine.any() or tag_id not in run.heard:
        return None
    return float(stamps[mine].min() - run.heard[tag_id][0]) * 1e-9


GEOMETRY_PARALLAX_DEG = 30.0
"""the spread of views after which the geometry allows a tag: bearings with the paper's 5 deg errors
at the two ends of such a span fix its range to about a sixth"""


def geometry_after_s(run: RunRecord, truth: Truth, tag_id: int) -> float | None:
    """Seconds from the tag's first AoA until the AoAs the SLAM had of it were taken from views
    spanning GEOMETRY_PARALLAX_DEG, seen from its true place along the true path: when the geometry
    first allowed it, whatever the estimator (None: never, or not heard)."""
    every = run.seen if len(run.seen[0]) else run.aoa[:2]
    stamps = np.sort(every[0][every[1] == tag_id])
    if tag_id not in run.heard or tag_id not in truth.tags or len(stamps) == 0:
        return None
    robot, _ = poses_at(truth.trajectory, stamps.astype(np.float64))
    seen = np.asarray(truth.tags[tag_id][0])[None, :] - robot
    direction = wrap_angle(np.arctan2(seen[:, 1], seen[:, 0]) - math.atan2(seen[0, 1], seen[0, 0]))
    spread = np.degrees(np.maximum.accumulate(direction) - np.minimum.accumulate(direction))
    reached = np.flatnonzero(spread >= GEOMETRY_PARALLAX_DEG)
    return float(stamps[reached[0]] - run.heard[tag_id][0]) * 1e-9 if len(reached) else None


def parallax_at_localization_deg(run: RunRecord, tag_id: int) -> float | None:
    """The spread (deg) of the directions from which the tag had been seen when it was first
    published as localized: from its first localized position to the robot's positions (the final
    trajectory) at its AoAs until then; what the geometry allowed so far (None: never localized, or
    no AoA or pose to tell)."""
    stamps, ids, xy, observable, _ = run.tag_history
    mine = np.flatnonzero(observable & (ids == tag_id))
    every = run.seen if len(run.seen[0]) else run.aoa[:2]
    aoa_stamps = every[0][every[1] == tag_id]
    if len(mine) == 0 or len(run.final.stamp_ns) == 0:
        return None
    first = mine[np.argmin(stamps[mine])]
    seen = aoa_stamps[aoa_stamps <= stamps[first]]
    if len(seen) == 0:
        return None
    t = run.final.stamp_ns.astype(np.float64)
    robot = np.stack([np.interp(seen, t, run.final.xy[:, 0]), np.interp(seen, t, run.final.xy[:, 1])], axis=1)
    return parallax_deg(xy[first], robot)


def published_honesty(run: RunRecord, truth: Truth, start: Rigid2D) -> dict[str, dict[str, Any]]:
    """How honest the covariance of every tag estimate the run published as localized was, LOS and
    NLOS tags apart: how many standard deviations of its own covariance each was from the truth
    (`start` maps the truth into the estimate's frame). A 2-D Gaussian's: median 1.18, 1.1% beyond 3."""
    stamps, ids, xy, observable, cov = run.tag_history
    out: dict[str, dict[str, Any]] = {}
    for kind, flag in (("los", False), ("nlos", True)):
        mine = observable & np.array([int(i) in truth.tags and truth.tags[int(i)][1] == flag for i in ids], bool)
        if not mine.any():
            out[kind] = {"estimates": 0}
            continue
        where = start.apply(np.array([truth.tags[int(i)][0] for i in ids[mine]]))
        sigmas = np.array([mahalanobis(e, c) for e, c in zip(xy[mine] - where, cov[mine], strict=True)], dtype=float)
        sigmas = np.where(np.isnan(sigmas), np.inf, sigmas)
        out[kind] = {
            "estimates": int(mine.sum()),
            "sigmas_median": float(np.median(sigmas)),
            "beyond_3_sigma": float(np.mean(sigmas > 3)),
        }
    return out


def mahalanobis(error: np.ndarray, cov: np.ndarray) -> float | None:
    """How many standard deviations of `cov` the error vector is (None for a singular covariance)."""
    try:
        return math.sqrt(max(float(error @ np.linalg.solve(cov, error)), 0.0))
    except np.linalg.LinAlgError:
        return None


def aoa_errors(run: RunRecord, truth: Truth) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each AoA's error against the direction from the true pose to the true tag, its NLOS flag and
    its reported std."""
    stamps, ids, angles, stds = run.aoa
    known = np.array([int(i) in truth.tags for i in ids], dtype=bool)
    if not known.any():
        return np.zeros(0), np.zeros(0, bool), np.zeros(0)
    position, yaw = poses_at(truth.trajectory, stamps[known])
    where = np.array([truth.tags[int(i)][0] for i in ids[known]])
    true = np.arctan2(where[:, 1] - position[:, 1], where[:, 0] - position[:, 0]) - yaw
    return (
        wrap_angle(angles[known] - true),
        np.array([truth.tags[int(i)][1] for i in ids[known]]),
        stds[known],
    )


PAPER_ROBOT_MEAN_M = 0.393
PAPER_LOS_TAGS_MEAN_M = 0.746


def render(metrics: dict[str, Any]) -> str:
    """The readable table of `rover eval` (the JSON is `metrics`)."""

    def cm(v: float | None) -> str:
        return "-" if v is None else f"{v * 100:.1f} cm"

    lines = [f"{'robot':<30}{'mean':>10}{'median':>10}{'rmse':>10}{'max':>10}{'poses':>7}"]
    for name, entry in metrics["robot"].items():
        for kind in ("unaligned", "aligned"):
            e = entry[kind]
            lines.append(
                f"{name + ' ' + kind:<30}{cm(e['mean_m']):>10}{cm(e['median_m']):>10}{cm(e['rmse_m']):>10}"
                f"{cm(e['max_m']):>10}{e['poses']:>7}"
            )
    lines.append(f"  paper (Zhang et al.): robot mean {cm(PAPER_ROBOT_MEAN_M)}")
    lines.append(
        f"{'tag':<8}{'error':>10}{'aligned':>10}{'reported std':>14}{'sigmas':>8}{'localized after':>17}"
        f"{'seen over':>11}{'geometry after':>16}"
    )
    for tag_id, t in metrics["tags"].items():
        label = f"{tag_id}{' NLOS' if t['nlos'] else ''}"
        geometry = "never" if t.get("geometry_after_s") is None else f"{t['geometry_after_s']:.1f} s"
        if t["localized"]:
            sigmas = "-" if t["sigmas"] is None else f"{t['sigmas']:.1f}"
            after = "-" if t.get("localized_after_s") is None else f"{t['localized_after_s']:.1f} s"
            seen = t.get("parallax_at_localization_deg")
            lines.append(
                f"{label:<8}{cm(t['error_m']):>10}{cm(t['aligned_error_m']):>10}{cm(t['reported_std_m']):>14}"
                f"{sigmas:>8}{after:>17}{'-' if seen is None else f'{seen:.0f} deg':>11}{geometry:>16}"
            )
        else:
            lines.append(f"{label:<8}{'never localized':>34}{'':>36}{geometry:>16}")
    lines.append(
        f"LOS tags mean {cm(metrics['los_tags_mean_m'])} (paper {cm(PAPER_LOS_TAGS_MEAN_M)}), "
        f"NLOS tags mean {cm(metrics['nlos_tags_mean_m'])}"
    )
    for kind, p in metrics.get("published", {}).items():
        if p["estimates"]:
            lines.append(
                f"published {kind.upper():<4} estimates {p['estimates']}: median {p['sigmas_median']:.2f} sigma, "
                f"{p['beyond_3_sigma']:.1%} beyond 3 sigma (a 2-D Gaussian's: 1.18, 1.1%)"
            )
    if "aoa" in metrics:
        for kind, a in metrics["aoa"].items():
            if a["count"]:
                lines.append(
                    f"AoA {kind:<4} median {a['median_deg']:.1f} deg, 90th percentile {a['p90_deg']:.1f} deg "
                    f"({a['count']} bursts); |error|/std: median {a['error_over_std_median']:.2f}, "
                    f"{a['within_1_std']:.0%} <= 1, {a['within_3_std']:.0%} <= 3"
                )
        lines.append(
            "  a unit Gaussian's |error|/std: median 0.67, 68% <= 1, 99.7% <= 3; sigmas: a tag's error "
            "in its reported covariance's standard deviations; geometry after: when its views first "
            f"spanned {GEOMETRY_PARALLAX_DEG:.0f} deg, from its true place along the true path"
        )
    return "\n".join(lines) + "\n"
