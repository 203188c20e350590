"""The figures of a run with ground truth, in the style of the paper's: the trajectory and tags with
their error ellipses over the truth (Fig. 6b), robot and tag errors over time (Fig. 7b), the AoA
error CDF (Fig. 5a)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from rover.evaluation.metrics import RunRecord, Truth, aoa_errors, poses_at, start_frame
from rover.formats.atomic_file import write_aside

if TYPE_CHECKING:
    from matplotlib.figure import Figure

ELLIPSE_SIGMA = 2.0


FIGURE_FILES = ("trajectory.png", "robot_error.png", "tag_error.png", "aoa_cdf.png")
"""Every figure `write_figures` may write, by file name."""


def _pyplot() -> Any:
    """matplotlib.pyplot on the Agg backend (imported on first use: it is slow to import)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def write_figures(run: RunRecord, truth: Truth, out: Path) -> list[Path]:
    """Write the PNGs into `out`; returns their paths."""
    plt = _pyplot()
    to_start = start_frame(truth.trajectory, int(run.final.stamp_ns[0]))
    t0 = run.final.stamp_ns[0]
    written = []
    plain = _plain_ticks()

    fig, ax = plt.subplots(figsize=(8, 5))
    # wide and pale under the estimates, so it shows where they lie on it
    ax.plot(*to_start.apply(truth.trajectory.xy).T, color="0.75", lw=6, label="ground truth", solid_capstyle="round")
    ax.plot(*run.live.xy.T, color="tab:orange", lw=0.8, alpha=0.7, label="live estimate")
    ax.plot(*run.final.xy.T, color="tab:blue", lw=1.2, label="final estimate")
    localized = {int(i) for i, xy in zip(run.tag_ids, run.tag_xy, strict=True) if np.isfinite(xy).all()}
    at_end = localized_at_the_end(run)
    for tag_id, (xy, nlos) in truth.tags.items():
        p = to_start.apply(np.asarray(xy)[None])[0]
        ax.plot(*p, "x", color="tab:red" if nlos else "k", ms=9, mew=2)
        state = "" if tag_id in at_end else ", not localized at the end" if tag_id in localized else ", never localized"
        label = f"tag {tag_id}{' (NLOS)' if nlos else ''}{state}"
        ax.annotate(label, p, textcoords="offset points", xytext=(6, 6))
    ax.plot([], [], "x", color="k", ms=9, mew=2, label="true tag (red: NLOS)")
    ax.plot([], [], "o", color="tab:blue", label=f"estimated tag, {ELLIPSE_SIGMA:.0f}-sigma ellipse")
    angle = np.linspace(0, 2 * np.pi, 60)
    circle = np.stack([np.cos(angle), np.sin(angle)])
    for xy, cov in zip(run.tag_xy, run.tag_cov, strict=True):
        if not np.isfinite(xy).all():
            continue
        values, vectors = np.linalg.eigh(0.5 * (cov + cov.T))
        ellipse = vectors @ (ELLIPSE_SIGMA * np.sqrt(np.maximum(values, 0))[:, None] * circle) + xy[:, None]
        ax.plot(*xy, "o", color="tab:blue")
        ax.plot(*ellipse, color="tab:blue", lw=1)
    ax.set_aspect("equal")
    ax.margins(0.1)  # room for the tags' names at the edges
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"Trajectory and tags ({ELLIPSE_SIGMA:.0f}-sigma ellipses), world frame of the first pose")
    ax.legend(loc="best", fontsize=8)
    written.append(_save(fig, out / "trajectory.png", plt))

    fig, ax = plt.subplots(figsize=(8, 3.5))
    for poses, label in ((run.final, "final"), (run.live, "live")):
        if len(poses.stamp_ns):
            where, _ = poses_at(truth.trajectory, poses.stamp_ns)
            error = np.linalg.norm(poses.xy - to_start.apply(where), axis=1)
            ax.plot((poses.stamp_ns - t0) / 1e9, error * 100, label=label, lw=1)
    ax.set_xlabel("time since the first pose (s)")
    ax.set_ylabel("robot error (cm)")
    ax.set_title(
        "Robot position error (final: each pose as it left the SLAM window; live: as estimated at its own time)",
        fontsize=9,
    )
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1), fontsize=8)
    written.append(_save(fig, out / "robot_error.png", plt))

    stamps, ids, xy, observable, _cov = run.tag_history
    aoa_stamps, aoa_ids, _angles, _stds = run.aoa
    fig, ax = plt.subplots(figsize=(8, 3.5))
    for tag_id, (where, nlos) in sorted(truth.tags.items()):
        mine = (ids == tag_id) & observable
        if not mine.any():
            continue
        reference = to_start.apply(np.asarray(where)[None])[0]
        (line,) = ax.plot(
            (stamps[mine] - t0) / 1e9,
            np.linalg.norm(xy[mine] - reference, axis=1) * 100,
            label=f"tag {tag_id}{' (NLOS)' if nlos else ''}",
            lw=1,
        )
        first: int | None
        last: int | None
        if tag_id in run.heard:  # as tags.csv says
            first, last = run.heard[tag_id]
        else:  # a run folder from before tags.csv had the times: the AoAs the SLAM used
            used = aoa_stamps[aoa_ids == tag_id]
            first, last = (int(used.min()), int(used.max())) if len(used) else (None, None)
        if first is not None and last is not None:
            ax.axvline((first - t0) / 1e9, color=line.get_color(), ls=":", lw=0.8)
            ax.axvline((last - t0) / 1e9, color=line.get_color(), ls="--", lw=0.8)
    ax.set_xlabel("time since the first pose (s)  (dotted: first heard, dashed: last heard)")
    ax.set_ylabel("tag error (cm)")
    if ax.lines:  # without a localized tag the plot is empty: no log scale, no legend to warn about
        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(plain)
        ax.yaxis.set_minor_formatter(plain)
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1), fontsize=8)
    else:
        heard = ", ".join(str(t) for t in sorted(run.heard)) or "none"
        ax.text(0.5, 0.5, f"no tag was localized (heard: {heard})", transform=ax.transAxes, ha="center")
    written.append(_save(fig, out / "tag_error.png", plt))

    error, aoa_nlos, _std = aoa_errors(run, truth)
    if len(error):
        fig, ax = plt.subplots(figsize=(5, 4))
        for mask, label in ((~aoa_nlos, "LOS"), (aoa_nlos, "NLOS")):
            if mask.any():
                e = np.sort(np.degrees(np.abs(error[mask])))
                ax.plot(e, np.arange(1, len(e) + 1) / len(e), label=f"{label} (median {np.median(e):.1f} deg)")
        ax.set_xlabel("AoA error (deg)")
        ax.set_ylabel("CDF")
        ax.set_xlim(0, 180)
        ax.legend()
        written.append(_save(fig, out / "aoa_cdf.png", plt))
    return written


def localized_at_the_end(run: RunRecord) -> set[int]:
    """The tags whose last published estimate is localized (tags.csv's `observable`)."""
    stamps, ids, _xy, observable, _cov = run.tag_history
    last: dict[int, bool] = {}
    for tag_id in np.unique(ids):
        mine = np.flatnonzero(ids == tag_id)
        last[int(tag_id)] = bool(observable[mine[np.argmax(stamps[mine])]])
    return {t for t, ok in last.items() if ok}


def _plain_ticks() -> Any:
    """Tick labels as plain numbers (1, 2, 5, 10, 20), not powers of ten, on a log axis."""
    from matplotlib.ticker import FuncFormatter

    return FuncFormatter(lambda value, _pos: f"{value:g}" if f"{value:g}"[0] in "125" else "")


def _save(fig: Figure, path: Path, plt: Any) -> Path:
    """Draw aside and rename into place; nothing is left behind when that fails or is interrupted."""

    def draw(partial: Path) -> None:
        fig.tight_layout()
        fig.savefig(partial, dpi=110, format="png")

    try:
        return write_aside(path, draw)
    finally:
        plt.close(fig)
