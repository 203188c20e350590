"""Ground truth as users deliver it: TUM stamps read exactly, and every bad truth or tags file refused
in one line naming the file and line (through `rover eval` and `rover convert`, in-process)."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers import reference_data

from rover.cli.app import main
from rover.errors import BadInput
from rover.formats.truth import parse_tags_csv, read_tags_csv, read_tum

TUM = "".join(f"1700000000.{i}00000000 {0.1 * i:.1f} 0 0 0 0 0 1\n" for i in range(10))
TAGS = "id,channel,x,y,z,nlos\n1,149,2.0,3.0,0,0\n2,153,-1.0,1.0,0,1\n"


@pytest.fixture
def run(tmp_path: Path) -> Path:
    """A run directory whose estimate is the truth written by `truth()`."""
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / "trajectory.tum").write_text(TUM)
    return folder


def write(path: Path, content: str | bytes) -> Path:
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content)
    return path


def one_error_line(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    """Run the CLI in-process: status 2 and exactly one line on stderr, which is returned."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("rover: error: ") and "Traceback" not in err, err
    return err.rstrip("\n")


def test_stamps_in_exponent_notation_are_exact(tmp_path, run, capsys):
    truth = write(
        tmp_path / "t.tum", TUM.replace("1700000000.000000000", "1.7e9").replace("1700000000.5", "1700000000.5e0")
    )
    trajectory = read_tum(truth)
    assert trajectory.stamp_ns[0] == 1_700_000_000_000_000_000
    assert trajectory.stamp_ns[5] == 1_700_000_000_500_000_000
    assert main(["eval", str(run), "--truth", str(truth), "--tags", str(write(tmp_path / "tags.csv", TAGS))]) == 0
    assert "trajectory.tum aligned" in capsys.readouterr().out


def test_sub_nanosecond_digits_round_to_the_nearest_nanosecond(tmp_path):
    truth = write(tmp_path / "t.tum", "1700000000.0000000015 0 0 0 0 0 0 1\n12.5e-10 0 0 0 0 0 0 1\n")
    assert read_tum(truth).stamp_ns.tolist() == [1_700_000_000_000_000_002, 1]


def test_a_stamp_beyond_2038_is_one_line(tmp_path, run, capsys):
    truth = write(tmp_path / "t.tum", TUM + "1e20 0 0 0 0 0 0 1\n")
    assert one_error_line(capsys, ["eval", str(run), "--truth", str(truth)]) == (
        f"rover: error: {truth}:11: t is '1e20' s, not before 2**31 s (2038-01-19), the end of a ROS 2 stamp"
    )


def test_a_negative_stamp_is_one_line(tmp_path, run, capsys):
    truth = write(tmp_path / "t.tum", "# t x y z qx qy qz qw\n-5 0 0 0 0 0 0 1\n")
    assert one_error_line(capsys, ["eval", str(run), "--truth", str(truth)]) == (
        f"rover: error: {truth}:2: t is negative: '-5' (stamps are seconds since 1970)"
    )


def test_a_negative_stamp_stops_convert_before_the_writer(tmp_path, capsys):
    setup = write(
        tmp_path / "setup.yaml",
        "receiver: {antenna_positions_m: [[0, 0], [0.0258, 0]]}\nexcitation: {channel: 165}\n"
        "topics: {csi: null, imu: /imu/data, odom: null}\n",
    )
    truth = write(tmp_path / "t.tum", "-5 0 0 0 0 0 0 1\n")
    bag = reference_data() / "bags" / "jackal_imu_odom.bag"
    argv = ["convert", str(bag), "-o", str(tmp_path / "out.mcap"), "--setup", str(setup), "--truth", str(truth)]
    assert (
        one_error_line(capsys, argv) == f"rover: error: {truth}:1: t is negative: '-5' (stamps are seconds since 1970)"
    )
    assert not (tmp_path / "out.mcap").exists()


def test_a_binary_tum_file_is_one_line(tmp_path, run, capsys):
    truth = write(tmp_path / "t.tum", b"\x89\xff\x00\x01binary")
    assert one_error_line(capsys, ["eval", str(run), "--truth", str(truth)]) == (
        f"rover: error: {truth}: not a text file (byte 0x89 at offset 0 is not UTF-8)"
    )
    write(truth, b"1 0 0 0\x00 0 0 0 1\n")
    assert one_error_line(capsys, ["eval", str(run), "--truth", str(truth)]) == (
        f"rover: error: {truth}: not a text file (NUL byte at offset 7)"
    )


def test_nan_in_a_tum_row_says_which_value(tmp_path, run, capsys):
    truth = write(tmp_path / "t.tum", TUM + "1700000001 0 0 nan 0 0 0 1\n")
    assert one_error_line(capsys, ["eval", str(run), "--truth", str(truth)]) == (
        f"rover: error: {truth}:11: z has a non-finite value 'nan'"
    )
    write(truth, "inf 0 0 0 0 0 0 1\n")
    with pytest.raises(BadInput, match=r"t\.tum:1: t has a non-finite value 'inf'$"):
        read_tum(truth)
    write(truth, "1 2 3\n")
    with pytest.raises(BadInput, match=r"t\.tum:1: a TUM row has 8 numbers \(t x y z qx qy qz qw\), got 3: '1 2 3'$"):
        read_tum(truth)


def eval_with_tags(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, run: Path, tags: str | bytes
) -> tuple[Path, str]:
    truth = write(tmp_path / "t.tum", TUM)
    path = write(tmp_path / "tags.csv", tags)
    return path, one_error_line(capsys, ["eval", str(run), "--truth", str(truth), "--tags", str(path)])


def test_a_binary_tags_csv_is_one_line(tmp_path, run, capsys):
    path, line = eval_with_tags(capsys, tmp_path, run, b"id,channel\n\xff\xfe")
    assert line == f"rover: error: {path}: not a text file (byte 0xff at offset 11 is not UTF-8)"


@pytest.mark.parametrize("value", ["nan", "inf", "-Infinity"])
def test_a_non_finite_tag_position_is_one_line(tmp_path, run, capsys, value):
    path, line = eval_with_tags(capsys, tmp_path, run, TAGS + f"3,157,{value},1,0,0\n")
    assert line == f"rover: error: {path}:4: column x has a non-finite value '{value}'"


def test_missing_tag_columns_are_one_line(tmp_path, run, capsys):
    path, line = eval_with_tags(capsys, tmp_path, run, "id,channel,x\n1,149,2.0\n")
    assert line == f"rover: error: {path}:1: missing column(s) y, z (expected id,channel,x,y,z[,nlos])"
    path, line = eval_with_tags(capsys, tmp_path, run, TAGS + "3,157,1.0\n")
    assert line == f"rover: error: {path}:4: 3 field(s), no value for column(s) y, z"


def test_a_repeated_tag_id_is_one_line(tmp_path, run, capsys):
    path, line = eval_with_tags(capsys, tmp_path, run, TAGS + "1,157,5.0,5.0,0,0\n")
    assert line == f"rover: error: {path}:4: tag id 1 repeated (first on line 2)"


def test_tag_values_outside_their_message_fields_are_refused():
    with pytest.raises(BadInput, match=r"^src:2: column id is -1, outside 0\.\.4294967295$"):
        parse_tags_csv("id,channel,x,y,z\n-1,149,0,0,0\n", "src")
    with pytest.raises(BadInput, match=r"^src:2: column channel is 'ch149', not an integer$"):
        parse_tags_csv("id,channel,x,y,z\n1,ch149,0,0,0\n", "src")
    with pytest.raises(BadInput, match=r"^src:2: column nlos is 2, outside 0\.\.1$"):
        parse_tags_csv("id,channel,x,y,z,nlos\n1,149,0,0,0,2\n", "src")


def test_a_spreadsheet_csv_with_byte_order_mark_and_blank_lines_reads(tmp_path):
    path = write(tmp_path / "tags.csv", b"\xef\xbb\xbfid,channel,x,y,z\r\n1,149,2.0,3.0,0\r\n\r\n")
    (tag,) = read_tags_csv(path)
    assert (tag.id, tag.channel, tag.xyz, tag.nlos) == (1, 149, (2.0, 3.0, 0.0), False)
