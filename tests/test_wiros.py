"""WiROS bags (rover.formats.csi_sources.wiros, `rover aoa BAG`, `rover info BAG`): ROS 1 and ROS 2
bags of rf_msgs/msg/Wifi written here with rosbags, from the message's public field list (the
definition below, not Rover's copy), holding a plane wave written from the physics
(test_aoa_capture.plane_wave) in the layout WiROS records: fft-shifted bins, Fortran order, the
chip's lower 64 bins rotated."""

from __future__ import annotations

import sqlite3
from contextlib import closing
from pathlib import Path

import numpy as np
import pytest
from helpers import T0_NS, read_bag, run_rover
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Ros2Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from test_aoa_capture import SQUARE_19MM, plane_wave

from rover.errors import BadInput
from rover.formats.csi_sources import read_capture, wiros
from rover.messages import deserialize

WIFI_MSG = """\
std_msgs/Header header
uint8 ap_id
uint8[] txmac
uint8 chan
uint32 n_sub
uint8 n_rows
uint8 n_cols
uint8 bw
uint8 mcs
int32 rssi
uint32 fc
uint32 seq_num
float64[] csi_real
float64[] csi_imag
string rx_id
uint32 msg_id
"""
"""rf_msgs/msg/Wifi as its public field list gives it"""
ANGLE_DEG = -130.0
CHANNEL = 155
CENTRE_HZ = 5775e6
"""channel 155: the 80 MHz channel over 149-161"""
BINS = np.arange(-128, 128)
EMPTY = np.r_[-128:-122, -1:2, 123:128]
MAC = bytes.fromhex("0a1b2c3d4e5f")
ROUTER = "192.168.43.1"


def truth() -> np.ndarray:
    """(P, 256, 4, 1) the plane wave on every FFT bin, as the antennas received it."""
    return plane_wave(SQUARE_19MM, ANGLE_DEG, CENTRE_HZ, BINS, EMPTY, seed=3).csi


def recorded(csi: np.ndarray) -> np.ndarray:
    """What the router reports of (P, 256, N, T): its lower 64 bins rotated by -1 at 80 MHz."""
    out = csi.copy()
    out[:, :64] *= -1
    return out


def store():
    s = get_typestore(Stores.ROS2_HUMBLE)
    s.register(get_types_from_msg(WIFI_MSG, "rf_msgs/msg/Wifi"))
    return s


def messages(csi: np.ndarray, s, *, bw: int = 80, chan: int = CHANNEL, macs: list[bytes] | None = None):
    """(stamp, Wifi) per packet of (P, K, N, T), the CSI flattened in Fortran order."""
    cls = s.types["rf_msgs/msg/Wifi"]
    header_cls, time_cls = s.types["std_msgs/msg/Header"], s.types["builtin_interfaces/msg/Time"]
    for p, h in enumerate(csi):
        stamp = T0_NS + p * 10_000_000
        flat = h.reshape(-1, order="F")
        yield (
            stamp,
            cls(
                header=header_cls(stamp=time_cls(sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id="asus"),
                ap_id=0,
                txmac=np.frombuffer(macs[p] if macs else MAC, np.uint8),
                chan=chan,
                n_sub=h.shape[0],
                n_rows=h.shape[1],
                n_cols=h.shape[2],
                bw=bw,
                mcs=0,
                rssi=-40 - p % 3,
                fc=0x88,
                seq_num=100 + p,
                csi_real=np.ascontiguousarray(flat.real),
                csi_imag=np.ascontiguousarray(flat.imag),
                rx_id=ROUTER,
                msg_id=p,
            ),
        )


def write_ros2(path: Path, csi: np.ndarray, storage=StoragePlugin.MCAP, **kw) -> Path:
    s = store()
    with Ros2Writer(path, version=9, storage_plugin=storage) as writer:
        conn = writer.add_connection("/csi", "rf_msgs/msg/Wifi", typestore=s)
        for stamp, msg in messages(csi, s, **kw):
            writer.write(conn, stamp, s.serialize_cdr(msg, "rf_msgs/msg/Wifi"))
    return path


def write_ros1(path: Path, csi: np.ndarray) -> Path:
    s = store()
    with Ros1Writer(path) as writer:
        conn = writer.add_connection("/csi", "rf_msgs/msg/Wifi", typestore=s)
        for stamp, msg in messages(csi, s):
            writer.write(conn, stamp, s.serialize_ros1(msg, "rf_msgs/msg/Wifi"))
    return path


def bare(bag: Path) -> Path:
    """The sqlite bag as ROS 2 releases before Jazzy record it: no message definitions."""
    (db,) = bag.glob("*.db3")
    with closing(sqlite3.connect(db)) as con, con:
        con.execute("DELETE FROM message_definitions")
    return bag


def kept(csi: np.ndarray) -> np.ndarray:
    """(P, 234, N, T) the truth at the subcarriers WiROS keeps."""
    return csi[:, wiros.KEPT_SUBCARRIERS[80e6] + 128]


def test_the_kept_subcarriers_are_the_data_ones():
    """802.11n/ac's data subcarriers, DC and pilots left out, as WiROS keeps them: 50/108/234."""
    k = wiros.KEPT_SUBCARRIERS
    assert [len(k[w]) for w in (20e6, 40e6, 80e6)] == [50, 108, 234]
    assert not np.isin([0, 7, 21, 28], np.abs(k[20e6])).any()
    assert not np.isin([0, 1, 11, 25, 53], np.abs(k[40e6])).any() and np.abs(k[40e6]).max() == 58
    assert not np.isin([0, 1, 11, 39, 75, 103], np.abs(k[80e6])).any() and np.abs(k[80e6]).max() == 122


@pytest.mark.parametrize(
    ("form", "write"),
    [
        ("ros1", lambda p, c: write_ros1(p / "wiros.bag", c)),
        ("ros2-mcap", lambda p, c: write_ros2(p / "wiros", c)),
        ("ros2-sqlite-no-definition", lambda p, c: bare(write_ros2(p / "wiros", c, StoragePlugin.SQLITE3))),
    ],
)
def test_a_recorded_bag_reads_as_the_antennas_received_it(tmp_path, form, write):
    """Each form of bag, raw bins: the lower 64 rotated back, the kept subcarriers picked; the
    sqlite bag carries no definition (Rover's copy decodes it)."""
    csi = truth()
    bag = write(tmp_path, recorded(csi))
    frames = read_capture(bag)
    assert frames.source == "wiros" and frames.dropped == {}
    np.testing.assert_array_equal(frames.subcarriers, wiros.KEPT_SUBCARRIERS[80e6])
    np.testing.assert_allclose(frames.csi, kept(csi), rtol=0, atol=1e-12)
    assert frames.bandwidth_hz == 80e6 and (frames.centre_freq_hz == CENTRE_HZ).all()
    assert frames.timestamp_ns[1] - frames.timestamp_ns[0] == 10_000_000
    assert frames.sequence[0] == 100 and frames.rssi_db[2].tolist() == [-42.0] * 4
    assert bytes(frames.mac[0]) == MAC


def test_rover_aoa_finds_the_wave_and_rover_info_says_what_the_bag_holds(tmp_path):
    bag = write_ros2(tmp_path / "wiros", recorded(truth()))
    rig = tmp_path / "rig.yaml"
    rig.write_text(f"receiver:\n  antenna_positions_m: {SQUARE_19MM.tolist()}\n")
    result = run_rover("aoa", str(bag), "--setup", str(rig), "--burst", "20")
    assert result.returncode == 0, result.stderr
    assert "wiros, 60 packets, 3 bursts of 20 packets, channel 155" in result.stdout
    angles = [float(line.split()[2]) for line in result.stdout.splitlines()[2:]]
    assert len(angles) == 3
    assert max(abs((a - ANGLE_DEG + 180) % 360 - 180) for a in angles) < 3.0, angles
    info = run_rover("info", str(bag))
    assert info.returncode == 0, info.stderr
    assert "234 subcarriers x 4 receive chains x 1 transmit streams" in info.stdout
    assert "5775 MHz" in info.stdout and "0a:1b:2c:3d:4e:5f" in info.stdout


def test_the_correction_nodes_kept_subcarriers_and_a_compensation_file(tmp_path):
    """A bag of the correction node's output (234 subcarriers, nothing to rotate) with each
    antenna's own phase per subcarrier left in it (the router's RF chains), and the compensation
    file WiROS would make of it (unit phasors undoing those phases) in a folder: the reader gives
    the wave back."""
    csi = kept(truth())
    rng = np.random.default_rng(7)
    chains = np.exp(1j * rng.uniform(-np.pi, np.pi, (234, 4)))
    bag = write_ros2(tmp_path / "wiros", csi * chains[None, :, :, None])
    folder = tmp_path / "compensation"
    folder.mkdir()
    np.save(folder / f"{ROUTER}-{CHANNEL}.npy", np.exp(-1j * np.angle(chains))[:, :, None])
    np.testing.assert_allclose(read_capture(bag, compensation=folder).csi, csi, rtol=0, atol=1e-12)
    assert not np.allclose(read_capture(bag).csi, csi)
    write_ros2(tmp_path / "other", csi, chan=149)
    with pytest.raises(BadInput, match=f"no compensation file {ROUTER}-149.npy"):
        read_capture(tmp_path / "other", compensation=folder)


def test_other_transmitters_and_channels_are_counted_not_mixed(tmp_path):
    csi = recorded(truth())
    macs = [MAC if p % 4 else bytes(6) for p in range(len(csi))]
    bag = write_ros2(tmp_path / "wiros", csi, macs=macs)
    frames = read_capture(bag)
    assert len(frames) == 15
    assert frames.dropped == {"messages of another transmitter than the first's (read one at a time)": 45}


def test_a_cut_bag_or_a_bag_without_wifi_gets_one_line_and_exit_2(tmp_path):
    bag = write_ros1(tmp_path / "wiros.bag", recorded(truth()))
    cut = tmp_path / "cut.bag"
    cut.write_bytes(bag.read_bytes()[: bag.stat().st_size // 2])
    rig = tmp_path / "rig.yaml"
    rig.write_text(f"receiver:\n  antenna_positions_m: {SQUARE_19MM.tolist()}\n")
    result = run_rover("aoa", str(cut), "--setup", str(rig), "--format", "wiros")
    assert result.returncode == 2
    assert len(result.stderr.strip().splitlines()) == 1 and str(cut) in result.stderr
    result = run_rover("aoa", str(tmp_path), "--setup", str(rig))
    assert result.returncode == 2 and "no ROS 2 bag of WiROS" in result.stderr


def test_the_message_copy_decodes_what_the_public_definition_encodes():
    """Rover's rf_msgs/msg/Wifi (used for bags without a definition) has the public field list's
    wire layout: a message serialized by the one deserializes by the other, every field equal."""
    s = store()
    _, msg = next(messages(truth()[:1], s))
    ours = wiros._typestore().deserialize_cdr(s.serialize_cdr(msg, "rf_msgs/msg/Wifi"), "rf_msgs/msg/Wifi")
    for field in WIFI_MSG.split("\n")[1:-1]:
        name = field.split()[1]
        a, b = getattr(msg, name), getattr(ours, name)
        assert np.array_equal(a, b) if isinstance(a, np.ndarray) else a == b, name


def robot_bag(path: Path, csi: np.ndarray, macs: list[bytes]) -> Path:
    """A robot's ROS 2 bag: WiROS's /csi (packets of `csi` from `macs`) and a resting IMU on /imu/data."""
    s = store()
    with Ros2Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {
            t: writer.add_connection(t, m, typestore=s)
            for t, m in (("/csi", "rf_msgs/msg/Wifi"), ("/imu/data", "sensor_msgs/msg/Imu"))
        }
        for stamp, msg in messages(csi, s, macs=macs):
            writer.write(conns["/csi"], stamp, s.serialize_cdr(msg, "rf_msgs/msg/Wifi"))
            imu_msg = s.types["sensor_msgs/msg/Imu"](
                header=msg.header,
                orientation=s.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=np.zeros(9),
                angular_velocity=s.types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                angular_velocity_covariance=np.zeros(9),
                linear_acceleration=s.types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=9.81),
                linear_acceleration_covariance=np.zeros(9),
            )
            writer.write(conns["/imu/data"], stamp, s.serialize_cdr(imu_msg, "sensor_msgs/msg/Imu"))
    return path


def test_rover_convert_writes_each_packet_as_rovers_csi_of_its_transmitters_tag(tmp_path):
    """Two transmitters interleaved: every packet on /csi/capture, its tag the MAC's last four bytes,
    its CSI the antennas' at the kept subcarriers (as float32), the channel's centre frequency."""
    csi = truth()
    macs = [MAC if p % 3 else bytes.fromhex("020000000007") for p in range(len(csi))]
    bag, out = robot_bag(tmp_path / "robot", recorded(csi), macs), tmp_path / "robot.mcap"
    setup = tmp_path / "setup.yaml"
    setup.write_text(f"receiver:\n  antenna_positions_m: {SQUARE_19MM.tolist()}\n")
    result = run_rover("convert", str(bag), "-o", str(out), "--setup", str(setup))
    assert result.returncode == 0, result.stderr
    assert "csi: /csi -> /csi/capture" in result.stdout and "wrote 60 messages on /csi/capture" in result.stdout
    packets = [deserialize(d, "rover_msgs/msg/Csi") for t, _s, d in read_bag(out) if t == "/csi/capture"]
    assert [p.tag_id for p in packets] == [int.from_bytes(m[-4:], "big") for m in macs]
    assert {p.tag_id for p in packets} == {7, 0x2C3D4E5F}
    first = packets[0]
    assert (first.channel, first.nrx, first.ntx, first.centre_freq_hz) == (CHANNEL, 4, 1, CENTRE_HZ)
    np.testing.assert_array_equal(first.subcarriers, wiros.KEPT_SUBCARRIERS[80e6])
    got = np.array([p.csi_real + 1j * p.csi_imag for p in packets]).reshape(len(packets), 234, 4, 1)
    np.testing.assert_allclose(got, kept(csi), rtol=0, atol=1e-6)


def test_rover_convert_of_wiros_csi_it_cannot_use_fails_and_writes_nothing(tmp_path):
    """Every packet's MAC cut short: all counted, none left, so exit 2 in one line and no dataset;
    a compensation given for CSI that is not WiROS's is refused."""
    csi = recorded(truth())[:10]
    bag, out = robot_bag(tmp_path / "robot", csi, [MAC[:4]] * len(csi)), tmp_path / "robot.mcap"
    setup = tmp_path / "setup.yaml"
    setup.write_text(f"receiver:\n  antenna_positions_m: {SQUARE_19MM.tolist()}\n")
    result = run_rover("convert", str(bag), "-o", str(out), "--setup", str(setup))
    assert result.returncode == 2 and not out.exists()
    assert result.stderr.splitlines() == [
        f"rover: error: {bag}: /csi: no packet of WiROS's rf_msgs/msg/Wifi left to write (10 messages whose txmac "
        "is not 6 bytes): nothing written"
    ]
    result = run_rover(
        "convert", str(bag), "-o", str(out), "--setup", str(setup), "--topic", "csi=/imu/data", "--compensation", "x"
    )
    assert result.returncode == 2 and not out.exists()


@pytest.mark.parametrize(("bw", "chan", "bins", "rotation"), [(40, 151, 128, 1j), (20, 149, 64, 1.0)])
def test_other_bandwidths_rotate_and_keep_as_the_chip_records_them(tmp_path, bw, chan, bins, rotation):
    """At 40 MHz the chip rotates its lower 64 bins by j (WiROS undoes it by -j); at 20 MHz it
    rotates none: the bag reads back as the antennas received it, at the 108 or 50 kept
    subcarriers, centred on the channel's frequency."""
    subcarriers = np.arange(-bins // 2, bins // 2)
    centre = 5000e6 + 5e6 * chan
    csi = plane_wave(SQUARE_19MM, ANGLE_DEG, centre, subcarriers, np.zeros(0), seed=5).csi
    chip = csi.copy()
    chip[:, :64] *= rotation
    frames = read_capture(write_ros2(tmp_path / "wiros", chip, bw=bw, chan=chan))
    kept = wiros.KEPT_SUBCARRIERS[bw * 1e6]
    assert len(kept) == {40: 108, 20: 50}[bw]
    np.testing.assert_array_equal(frames.subcarriers, kept)
    np.testing.assert_allclose(frames.csi, csi[:, kept + bins // 2], rtol=0, atol=1e-12)
    assert frames.bandwidth_hz == bw * 1e6 and (frames.centre_freq_hz == centre).all()
