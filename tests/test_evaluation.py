"""`rover eval` on hand-made trajectories with known errors, and agreement with evo_ape."""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
from decimal import Decimal
from pathlib import Path

import numpy as np
import pytest
from helpers import run_rover

from rover.cli.app import main
from rover.evaluation.metrics import Poses2D, Rigid2D, RunRecord, Truth, fit_rigid, published_honesty, trajectory_errors

T0 = 1_700_000_000.0


def square_path(n: int = 400) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 4 x 2 m rectangle driven counter-clockwise from the origin along +x: stamps (s), xy, yaw."""
    s = np.linspace(0, 12.0, n, endpoint=False)
    corners = np.array([[0, 0], [4, 0], [4, 2], [0, 2], [0, 0]], float)
    lengths = np.linalg.norm(np.diff(corners, axis=0), axis=1)
    edge = np.searchsorted(np.cumsum(lengths), s, side="right")
    start = np.concatenate([[0], np.cumsum(lengths)])[edge]
    direction = np.diff(corners, axis=0)[edge] / lengths[edge, None]
    xy = corners[edge] + direction * (s - start)[:, None]
    return T0 + s * 2.0, xy, np.arctan2(direction[:, 1], direction[:, 0])


def write_tum(path: Path, t: np.ndarray, xy: np.ndarray, yaw: np.ndarray) -> Path:
    path.write_text(
        "".join(
            f"{a:.9f} {x:.6f} {y:.6f} 0 0 0 {math.sin(w / 2):.9f} {math.cos(w / 2):.9f}\n"
            for a, (x, y), w in zip(t, xy, yaw, strict=True)
        )
    )
    return path


def rotate(xy: np.ndarray, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return xy @ np.array([[c, -s], [s, c]]).T


def poses(t, xy, yaw) -> Poses2D:
    return Poses2D((np.asarray(t) * 1e9).astype(np.int64), xy, yaw)


def test_known_offset_and_rotation():
    t, xy, yaw = square_path()
    shifted = trajectory_errors(poses(t, xy, yaw), poses(t, xy + [0.1, 0.0], yaw))
    assert shifted.unaligned["mean_m"] == pytest.approx(0.1, abs=1e-9)
    assert shifted.aligned["max_m"] < 1e-9
    turned = rotate(xy, math.radians(5.0))
    errors = trajectory_errors(poses(t, xy, yaw), poses(t, turned, yaw))
    expected = np.linalg.norm(turned - xy, axis=1)
    assert errors.unaligned["mean_m"] == pytest.approx(expected.mean(), rel=1e-9)
    assert errors.unaligned["rmse_m"] == pytest.approx(math.sqrt(np.mean(expected**2)), rel=1e-9)
    assert errors.aligned["max_m"] < 1e-9


def test_truth_in_another_frame_is_brought_to_the_start():
    t, xy, yaw = square_path()
    room = rotate(xy, 0.7) + [3.0, -2.0]
    errors = trajectory_errors(poses(t, room, yaw + 0.7), poses(t, xy, yaw))
    assert errors.unaligned["max_m"] < 1e-6


def test_the_fit_is_rigid_never_scaled():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(50, 2))
    fit = fit_rigid(1.5 * a, a)
    assert np.linalg.det(fit.rotation) == pytest.approx(1.0)
    assert np.allclose(fit.rotation @ fit.rotation.T, np.eye(2))


def evo_stats(reference: Path, estimate: Path, *extra: str) -> dict[str, float]:
    evo = Path(sys.executable).with_name("evo_ape")
    assert evo.exists(), "evo is a test dependency (pip install -e .[test])"
    out = subprocess.run(
        [
            str(evo),
            "tum",
            str(reference),
            str(estimate),
            *extra,
            "--project_to_plane",
            "xy",
            "--t_max_diff",
            "0.01",
            "--no_warnings",
        ],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    return {k: float(v) for k, v in re.findall(r"^\s*(max|mean|median|rmse)\s+([0-9.eE+-]+)\s*$", out, re.M)}


def make_run(tmp_path: Path) -> tuple[Path, Path, Path]:
    """A run directory whose estimate is the truth plus a drift and noise, truth as TUM + tags CSV."""
    rng = np.random.default_rng(7)
    t, xy, yaw = square_path()
    reference = write_tum(tmp_path / "truth.tum", t, xy, yaw)
    drift = np.cumsum(rng.normal(scale=0.01, size=xy.shape), axis=0)
    estimate = rotate(xy + drift, math.radians(2.0))
    run = tmp_path / "run"
    run.mkdir()
    write_tum(run / "trajectory.tum", t, estimate, yaw)
    write_tum(run / "trajectory_live.tum", t[::2] + 0.004, estimate[::2] + 0.05, yaw[::2])
    (run / "tags.csv").write_text(
        "id,channel,x,y,z,var_x,cov_xy,var_y,observable,first_heard_s,first_localized_s,"
        "last_heard_s\n1,149,2.1,3.0,0,0.01,0,0.01,1,1,2,3\n2,153,,,,1,0,1,0,1,,3\n"
    )
    tags = tmp_path / "tags_truth.csv"
    tags.write_text("id,channel,x,y,z,nlos\n1,149,2.0,3.0,0,0\n2,153,-1.0,1.0,0,1\n")
    return run, reference, tags


NO_POSES = Poses2D(np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0))


def estimates_only(stamps, ids, xy, observable, cov, **extra) -> RunRecord:
    """A run record of published tag estimates alone (no poses, no AoAs)."""
    return RunRecord(
        NO_POSES,
        NO_POSES,
        np.zeros(0, int),
        np.zeros((0, 2)),
        np.zeros((0, 2, 2)),
        tag_history=(stamps, ids, xy, observable, cov),
        aoa=(np.zeros(0, np.int64), np.zeros(0, int), np.zeros(0), np.zeros(0)),
        **extra,
    )


def test_published_estimates_are_judged_in_their_own_covariance():
    """Every estimate published as localized counts, in the standard deviations of the covariance
    it was published with (along its major axis here: 4 sigma is 0.4 m on a 10 cm std), LOS and
    NLOS apart; one not localized yet, or of a tag the truth does not know, does not count."""
    stretched = np.array([[0.01, 0.0], [0.0, 0.0001]])  # 10 cm along x, 1 cm along y
    rows = [  # (id, error along x, error along y, observable)
        *[(4, 0.1, 0.0, True)] * 8,  # 1 sigma
        (4, 0.4, 0.0, True),  # 4 sigma
        (4, 0.0, 0.04, True),  # 4 sigma along the narrow axis: 4 cm
        (4, 5.0, 0.0, False),  # not yet localized: not published as known
        (1, 0.0, 0.005, True),  # 0.5 sigma
        (9, 3.0, 3.0, True),  # a tag the truth does not know
    ]
    where = {1: np.array([2.0, 3.0]), 4: np.array([-1.0, 1.0]), 9: np.array([0.0, 0.0])}
    ids = np.array([r[0] for r in rows])
    xy = np.array([where[r[0]] + [r[1], r[2]] for r in rows])
    run = estimates_only(
        np.arange(len(rows), dtype=np.int64),
        ids,
        xy,
        np.array([r[3] for r in rows]),
        np.repeat(stretched[None], len(rows), axis=0),
    )
    truth = Truth(NO_POSES, {1: (where[1], False), 4: (where[4], True)})
    honesty = published_honesty(run, truth, Rigid2D(np.eye(2), np.zeros(2)))
    assert honesty["nlos"]["estimates"] == 10 and honesty["nlos"]["beyond_3_sigma"] == pytest.approx(0.2)
    assert honesty["nlos"]["sigmas_median"] == pytest.approx(1.0)
    assert honesty["los"] == {"estimates": 1, "sigmas_median": pytest.approx(0.5), "beyond_3_sigma": 0.0}


def test_rover_eval_agrees_with_evo(tmp_path):
    run, reference, tags = make_run(tmp_path)
    proc = run_rover("eval", str(run), "--truth", str(reference), "--tags", str(tags), "--json")
    assert proc.returncode == 0, proc.stderr
    metrics = json.loads(proc.stdout)
    for name in ("trajectory.tum", "trajectory_live.tum"):
        evo = evo_stats(reference, run / name, "-a")
        mine = metrics["robot"][name]["aligned"]
        for key in ("max", "mean", "median", "rmse"):
            assert mine[f"{key}_m"] == pytest.approx(evo[key], abs=1e-5), (name, key)
        unaligned = evo_stats(reference, run / name)
        assert metrics["robot"][name]["unaligned"]["mean_m"] == pytest.approx(unaligned["mean"], abs=1e-5)
    assert metrics["tags"]["1"]["error_m"] == pytest.approx(0.1, abs=1e-6)
    assert metrics["tags"]["1"]["sigmas"] == pytest.approx(1.0, abs=1e-5)  # 10 cm off, std 10 cm
    assert metrics["tags"]["2"] == {"nlos": True, "localized": False, "geometry_after_s": None}  # no AoA recorded
    table = run_rover("eval", str(run), "--truth", str(reference), "--tags", str(tags))
    assert "trajectory_live.tum aligned" in table.stdout and "never localized" in table.stdout


def test_rover_eval_bad_input(tmp_path):
    run, reference, _tags = make_run(tmp_path)
    (tmp_path / "bad.tum").write_text("1.0 2.0 oops\n")
    proc = run_rover("eval", str(run), "--truth", str(tmp_path / "bad.tum"))
    assert proc.returncode == 2 and "bad.tum:1:" in proc.stderr and "Traceback" not in proc.stderr
    proc = run_rover("eval", str(run))
    assert proc.returncode == 2 and "pass --truth" in proc.stderr


def test_eval_after_a_failed_run_says_the_results_are_the_earlier_runs(tmp_path):
    run, reference, tags = make_run(tmp_path)
    (run / "run.json").write_text(json.dumps({"status": "complete", "reason": "", "dataset": str(reference)}))
    (run / "failed-run.json").write_text(json.dumps({"status": "failed", "reason": "operator 'slam' failed: boom"}))
    proc = run_rover("eval", str(run), "--truth", str(reference), "--tags", str(tags))
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.splitlines() == [
        f"rover: WARNING: {run}: the last run into this folder failed (failed-run.json: operator 'slam' failed: "
        "boom): these are the results of the run before it"
    ]
    (run / "run.json").unlink()
    proc = run_rover("eval", str(run), "--truth", str(reference))
    assert proc.returncode == 2
    assert proc.stderr == f"rover: error: {run}: the run failed, nothing to evaluate: operator 'slam' failed: boom\n"


def one_error_line(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    """Run the CLI in-process: status 2 and exactly one line on stderr, which is returned."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("rover: error: ") and "Traceback" not in err, err
    return err.rstrip("\n")


def eval_error(capsys: pytest.CaptureFixture[str], tmp_path: Path, name: str, content: str | bytes) -> tuple[Path, str]:
    """`rover eval` of a good run whose file `name` is replaced by `content`; the one error line."""
    run, reference, tags = make_run(tmp_path)
    path = run / name
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content)
    return path, one_error_line(capsys, ["eval", str(run), "--truth", str(reference), "--tags", str(tags)])


def test_eval_of_a_binary_trajectory_is_one_line(tmp_path, capsys):
    path, line = eval_error(capsys, tmp_path, "trajectory.tum", b"\x89PNG\r\n\x1a\n\x00\x00")
    assert line == f"rover: error: {path}: not a text file (byte 0x89 at offset 0 is not UTF-8)"


def test_eval_of_a_binary_tags_csv_is_one_line(tmp_path, capsys):
    path, line = eval_error(capsys, tmp_path, "tags.csv", b"id,x\n\x00\x01\x02")
    assert line == f"rover: error: {path}: not a text file (NUL byte at offset 5)"


@pytest.mark.parametrize(
    ("row", "problem"),
    [
        ("3,157,inf,1,0,0.01,0,0.01,1,1,2,3", "column x has a non-finite value 'inf'"),
        ("3,157,1,1,0,nan,0,0.01,1,1,2,3", "column var_x has a non-finite value 'nan'"),
        ("1,157,1,1,0,0.01,0,0.01,1,1,2,3", "tag id 1 repeated (first on line 2)"),
        ("3,157,1,,0,0.01,0,0.01,1,1,2,3", "x and y are both numbers, or both empty for a tag never localized"),
        ("3,157,1,1,0,,,,1,1,2,3", "a localized tag has var_x, cov_xy and var_y"),
        ("3,157,1", "3 field(s), no value for column(s) y, var_x, cov_xy, var_y"),
    ],
)
def test_eval_of_a_bad_tags_csv_row_is_one_line(tmp_path, capsys, row, problem):
    header = "id,channel,x,y,z,var_x,cov_xy,var_y,observable,first_heard_s,first_localized_s,last_heard_s\n"
    good = "1,149,2.1,3.0,0,0.01,0,0.01,1,1,2,3\n2,153,,,,1,0,1,0,1,,3\n"
    path, line = eval_error(capsys, tmp_path, "tags.csv", header + good + row + "\n")
    assert line == f"rover: error: {path}:4: {problem}"


def test_eval_of_a_tags_csv_without_its_columns_is_one_line(tmp_path, capsys):
    path, line = eval_error(capsys, tmp_path, "tags.csv", "id,channel,x,y\n1,149,2,3\n")
    assert (
        line == f"rover: error: {path}:1: missing column(s) var_x, cov_xy, var_y (expected id,x,y,var_x,cov_xy,var_y)"
    )


def test_eval_reads_stamps_in_exponent_notation(tmp_path, capsys):
    run, reference, tags = make_run(tmp_path)
    argv = ["eval", str(run), "--truth", str(reference), "--tags", str(tags), "--json"]
    assert main(argv) == 0
    plain = json.loads(capsys.readouterr().out)
    for name in ("trajectory.tum", "trajectory_live.tum"):
        lines = (run / name).read_text().splitlines()
        (run / name).write_text(
            "".join(f"{Decimal(t):e} {rest}\n" for t, rest in (line.split(" ", 1) for line in lines))
        )
    assert (run / "trajectory.tum").read_text().startswith("1.700000000000000000e+9 ")
    assert main(argv) == 0
    assert json.loads(capsys.readouterr().out) == plain


@pytest.mark.parametrize(
    ("content", "problem"),
    [
        ("[]", "not a run description: a JSON object, got an array"),
        ('{"dataset": 5}', "field dataset: a file path (a string), got a number"),
        ('{"dataset": ', "not a run description: not JSON (Expecting value: line 1 column 13 (char 12))"),
        (b"\x1f\x8b\x08\x00\xff", "not a text file (byte 0x8b at offset 1 is not UTF-8)"),
    ],
)
def test_eval_of_a_bad_run_json_is_one_line(tmp_path, capsys, content, problem):
    run, _reference, _tags = make_run(tmp_path)
    path = run / "run.json"
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content)
    assert one_error_line(capsys, ["eval", str(run)]) == f"rover: error: {path}: {problem}"


def test_eval_of_a_three_byte_results_mcap_is_one_line(tmp_path, capsys):
    path, line = eval_error(capsys, tmp_path, "results.mcap", b"abc")
    assert line == f"rover: error: {path}: cannot read: not an MCAP file (no MCAP magic bytes at its start)"


def test_eval_against_a_three_byte_truth_is_one_line(tmp_path, capsys):
    run, _reference, _tags = make_run(tmp_path)
    truth = tmp_path / "truth.mcap"
    truth.write_bytes(b"abc")
    assert one_error_line(capsys, ["eval", str(run), "--truth", str(truth)]) == (
        f"rover: error: {truth}: cannot read the dataset's ground truth: not an MCAP file "
        "(no MCAP magic bytes at its start)"
    )


def test_eval_given_the_tags_csv_as_its_trajectory_truth_says_where_it_goes(tmp_path, capsys):
    run, _reference, tags = make_run(tmp_path)
    assert one_error_line(capsys, ["eval", str(run), "--truth", str(tags)]) == (
        f"rover: error: {tags}: a CSV is not a trajectory: the truth is a dataset (.mcap, or a bag folder) or a "
        "TUM file (.tum, .txt); tag positions go to --tags"
    )


def test_eval_of_a_run_outside_the_truths_time_is_one_line(tmp_path, capsys):
    run, _reference, tags = make_run(tmp_path)
    t, xy, yaw = square_path(20)
    later = write_tum(tmp_path / "later.tum", t + 1000.0, xy, yaw)
    line = one_error_line(capsys, ["eval", str(run), "--truth", str(later), "--tags", str(tags)])
    assert line == (
        "rover: error: trajectory.tum and the ground truth do not overlap in time (within 0.01 s): "
        "trajectory.tum spans 1700000000.000-1700000023.940 s, 400 poses; "
        "the ground truth 1700001000.000-1700001022.800 s, 20 poses"
    )


def test_a_truth_that_pairs_with_few_of_the_runs_poses_is_warned_of_and_noted(tmp_path):
    run, _reference, tags = make_run(tmp_path)
    t, xy, yaw = square_path()
    partial = write_tum(tmp_path / "partial.tum", t[:160], xy[:160], yaw[:160])
    proc = run_rover("eval", str(run), "--truth", str(partial), "--tags", str(tags), "--json")
    assert proc.returncode == 0, proc.stderr
    note = "the truth pairs with 160 of the run's 400 final poses (40%; at least 90% expected): is it this run's truth?"
    assert proc.stderr.splitlines() == [f"rover: WARNING: {run}: {note}"]
    assert json.loads(proc.stdout)["notes"] == [note]
    whole = run_rover("eval", str(run), "--truth", str(tmp_path / "truth.tum"), "--tags", str(tags), "--json")
    assert whole.stderr == "" and "notes" not in json.loads(whole.stdout)


def test_two_truths_are_the_same_only_where_they_agree():
    from rover.evaluation.checks import same_trajectory
    from rover.evaluation.metrics import Poses2D

    t, xy, yaw = square_path()
    stamps = (t * 1e9).astype(np.int64)
    truth = Poses2D(stamps, xy, yaw)
    assert same_trajectory(truth, Poses2D(stamps[::3], xy[::3], yaw[::3]))
    assert not same_trajectory(truth, Poses2D(stamps, xy + [0.05, 0.0], yaw))
    assert not same_trajectory(truth, Poses2D(stamps + 1, xy, yaw))


def test_a_run_folder_says_when_each_tag_was_first_and_last_heard(tmp_path):
    """From tags.csv, which the tag-error figure's lines follow (they followed the first AoA the SLAM
    used, long after the tag was first heard)."""
    from rover.formats.run_dir import load_run

    run, _reference, _tags = make_run(tmp_path)
    assert load_run(run).heard == {1: (1_000_000_000, 3_000_000_000), 2: (1_000_000_000, 3_000_000_000)}


def test_the_time_each_tag_took_to_be_localized_counts_from_its_first_aoa():
    """From the first AoA (tags.csv's first_heard_s) to the first estimate published as localized;
    none for a tag published only with its prior, or never heard."""
    from rover.evaluation.metrics import localized_after_s

    rows = [(5_000_000_000, 1, False), (7_500_000_000, 1, True), (9_000_000_000, 1, True), (8_000_000_000, 2, False)]
    run = estimates_only(
        np.array([r[0] for r in rows], dtype=np.int64),
        np.array([r[1] for r in rows]),
        np.zeros((len(rows), 2)),
        np.array([r[2] for r in rows]),
        np.repeat(np.eye(2)[None], len(rows), axis=0),
        heard={1: (1_250_000_000, 9_000_000_000), 2: (1_000_000_000, 8_000_000_000)},
    )
    assert localized_after_s(run, 1) == pytest.approx(6.25)
    assert localized_after_s(run, 2) is None
    assert localized_after_s(run, 3) is None


def test_when_the_geometry_first_allowed_a_tag():
    """From the tag's true place along the true path, at the AoAs the SLAM had: a robot driving along
    y = 0 at 0.5 m/s past a tag at (0, 2), first hearing it at x = -3.5 (29.7 deg off its path),
    has seen it over 30 deg once that angle is 59.7 deg, at x = -1.17, 4.7 s later; a tag heard
    from one place only never allows it."""
    from rover.evaluation.metrics import GEOMETRY_PARALLAX_DEG, Truth, geometry_after_s

    stamps = np.arange(0, 81, dtype=np.int64) * 100_000_000  # 8 s at 0.5 m/s from x = -4
    x = -4.0 + 0.05 * np.arange(81)
    path = Poses2D(stamps, np.stack([x, np.zeros(81)], axis=1), np.zeros(81))
    truth = Truth(path, {1: (np.array([0.0, 2.0]), False), 2: (np.array([0.0, 2.0]), False)})
    every = (np.concatenate([stamps[10:], np.full(5, stamps[10])]), np.concatenate([np.ones(71, int), np.full(5, 2)]))
    empty = np.zeros(0, int), np.zeros((0, 2)), np.zeros((0, 2, 2))
    history = (np.zeros(0, np.int64), np.zeros(0, int), np.zeros((0, 2)), np.zeros(0, bool), np.zeros((0, 2, 2)))
    aoa = (np.zeros(0, np.int64), np.zeros(0, int), np.zeros(0), np.zeros(0))
    heard = {1: (int(stamps[10]), int(stamps[-1])), 2: (int(stamps[10]), int(stamps[10]))}
    run = RunRecord(path, path, *empty, tag_history=history, aoa=aoa, heard=heard, seen=every)
    first = math.atan2(2.0, 0.0 - x[10])  # the direction from the robot's first view, seen from the tag
    crossing = 2.0 / math.tan(first + math.radians(GEOMETRY_PARALLAX_DEG))  # tag x less robot x there
    expected_s = ((0.0 - crossing) - x[10]) / 0.5
    assert geometry_after_s(run, truth, 1) == pytest.approx(expected_s, abs=0.1)
    assert geometry_after_s(run, truth, 2) is None
    assert geometry_after_s(run, truth, 3) is None


def test_the_parallax_a_tag_had_when_first_localized():
    """Seen from the robot's positions at its AoAs until its first localized estimate, those the
    SLAM could not resolve yet included: the robot at (0, 0), (2, 0) and (2, 2) seen from a tag at
    (1, 1) spans 180 deg; an AoA after it adds nothing."""
    from rover.evaluation.metrics import parallax_at_localization_deg

    stamps = np.array([1, 2, 3, 4], dtype=np.int64) * 1_000_000_000
    final = Poses2D(stamps, np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0]]), np.zeros(4))
    history = (
        np.array([2_500_000_000, 3_000_000_000, 4_000_000_000], dtype=np.int64),
        np.array([1, 1, 1]),
        np.array([[5.0, 5.0], [1.0, 1.0], [1.0, 1.0]]),
        np.array([False, True, True]),
        np.repeat(np.eye(2)[None], 3, axis=0),
    )
    resolved = (stamps[2:], np.array([1, 1]), np.zeros(2), np.ones(2))  # the SLAM resolved these once it had the tag
    every = (stamps, np.array([1, 1, 1, 1]))
    empty = np.zeros(0, int), np.zeros((0, 2)), np.zeros((0, 2, 2))
    run = RunRecord(final, final, *empty, tag_history=history, aoa=resolved, seen=every)
    assert parallax_at_localization_deg(run, 1) == pytest.approx(180.0)
    assert parallax_at_localization_deg(run, 2) is None
    older = RunRecord(final, final, *empty, tag_history=history, aoa=resolved)  # a run folder without them
    assert parallax_at_localization_deg(older, 1) == pytest.approx(0.0)
