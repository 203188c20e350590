"""The CSI captures of other tools (rover.formats.csi_sources): the real samples in the reference data
(csi/others) read as its README states, one record of each checked against a decode written here
from the format's public description, and the captures Rover must refuse: truncated, unknown, or
read as what they are not, each with one line and exit 2."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
from helpers import reference_data, run_rover

from rover.errors import BadInput
from rover.formats.csi_sources import detect_format, read_capture


def others() -> Path:
    return reference_data() / "csi" / "others"


ATHEROS, NEXMON = "ath_csi_1.dat", "example.pcap"
PICO_IWL, PICO_QCA = "rx_by_iwl5300.csi", "rx_by_qca9300.csi"


@pytest.mark.parametrize(
    ("name", "fmt"), [(ATHEROS, "atheros"), (NEXMON, "nexmon"), (PICO_IWL, "picoscenes"), (PICO_QCA, "picoscenes")]
)
def test_the_format_is_found_from_the_contents(name, fmt):
    assert detect_format(others() / name) == fmt


def test_the_atheros_sample_holds_what_the_data_readme_states():
    """401 records of 56 tones (20 MHz), 3 receive chains x 2 transmit, on 2437 MHz; the first
    record's RSSI 52 with chains 38, 52, 36; its timestamps in microseconds."""
    frames = read_capture(others() / ATHEROS)
    assert frames.source == "atheros" and frames.csi.shape == (401, 56, 3, 2) and frames.dropped == {}
    assert frames.bandwidth_hz == 20e6 and np.all(frames.centre_freq_hz == 2437e6)
    np.testing.assert_array_equal(frames.rssi_db[0], [38, 52, 36])
    np.testing.assert_array_equal(frames.subcarriers, [*range(-28, 0), *range(1, 29)])
    assert np.all(np.diff(frames.timestamp_ns) > 0) and frames.timestamp_ns[0] == 1_461_024_888_000


def test_an_atheros_record_decoded_by_hand_is_the_readers():
    """The Atheros CSI Tool's record (little-endian log): a 2-byte length, the 25-byte status, then
    the CSI as 10-bit two's-complement values, least significant bit first, imaginary before real,
    for each tone, receive chain and transmit stream in turn."""
    raw = (others() / ATHEROS).read_bytes()
    (length,) = struct.unpack_from("<H", raw)
    ts, csi_len, mhz, _err, _noise, _rate, bw, tones, nr, nc, rssi, r0, r1, r2, payload = struct.unpack_from(
        "<QHHBBBBBBBBBBBH", raw, 2
    )
    assert length == 25 + csi_len + payload and (bw, tones, nr, nc) == (0, 56, 3, 2)
    bits = np.unpackbits(np.frombuffer(raw, np.uint8, csi_len, 27), bitorder="little")
    values = (bits[: tones * nr * nc * 2 * 10].reshape(-1, 10) << np.arange(10)).sum(axis=1)
    values = np.where(values >= 512, values - 1024, values).reshape(tones, nr, nc, 2)
    frames = read_capture(others() / ATHEROS)
    np.testing.assert_array_equal(frames.csi[0], values[..., 1] + 1j * values[..., 0])
    assert frames.timestamp_ns[0] == ts * 1000 and frames.centre_freq_hz[0] == mhz * 1e6
    assert rssi == 52 and list(frames.rssi_db[0]) == [r0, r1, r2]


def nexmon_frames(raw: bytes) -> list[dict[str, object]]:
    """The header of each CSI frame of a Nexmon pcap, by hand: pcap's 24-byte header, each record's
    16 (its captured length third), Ethernet + IPv4 + UDP (42 bytes), then nexmon_csi's header."""
    out, at = [], 24
    while at < len(raw):
        caplen = struct.unpack_from("<I", raw, at + 8)[0]
        p = at + 16 + 42
        seq, conf, chanspec = struct.unpack_from("<HHH", raw, p + 10)
        out.append(
            {"magic": raw[p : p + 2], "mac": list(raw[p + 4 : p + 10]), "seq": seq, "core": conf & 7,
             "stream": (conf >> 3) & 7, "chanspec": chanspec}
        )  # fmt: skip
        at += 16 + caplen
    return out


def test_the_nexmon_sample_holds_what_the_data_readme_states_grouped_per_packet():
    """Four frames of 256 bins (80 MHz), cores 0 0 1 1 and streams 0 1 0 1 of one packet, chanspec
    0xe29b (channel 155, 80 MHz, 5 GHz: 5775 MHz), with the source MAC and sequence number: one
    packet of 2 x 2, its bins in increasing frequency; the 2017 capture carries no RSSI."""
    raw = (others() / NEXMON).read_bytes()
    by_hand = nexmon_frames(raw)
    assert [f["core"] for f in by_hand] == [0, 0, 1, 1] and [f["stream"] for f in by_hand] == [0, 1, 0, 1]
    assert {f["chanspec"] for f in by_hand} == {0xE29B} and {f["magic"] for f in by_hand} == {b"\x11\x11"}
    frames = read_capture(others() / NEXMON, chip="4358")
    assert frames.source == "nexmon 4358" and frames.csi.shape == (1, 256, 2, 2) and frames.dropped == {}
    assert frames.bandwidth_hz == 80e6 and frames.centre_freq_hz[0] == 5775e6
    assert list(frames.mac[0]) == by_hand[0]["mac"] and frames.sequence[0] == by_hand[0]["seq"]
    np.testing.assert_array_equal(frames.subcarriers, np.arange(-128, 128))
    assert np.isnan(frames.rssi_db).all()
    # in increasing frequency, an 80 MHz channel's empty bins are its guards (-128..-123, 123..127)
    # and DC (-1..1), every other bin carries the channel: in FFT order they would sit elsewhere
    power = np.abs(frames.csi[0]).sum(axis=(1, 2))
    empty = np.isin(frames.subcarriers, [*range(-128, -122), -1, 0, 1, *range(123, 128)])
    assert power[empty].max() < 0.1 * np.median(power) < power[~empty].min()


def test_the_picoscenes_samples_hold_what_the_data_readme_states():
    """The QCA9300 file: 1,000 frames of 56 tones x 3 chains x 1 stream on 5200 MHz. The IWL5300
    file: 383 frames of 30 tones whose chains and streams vary per frame (up to 3 x 2): the
    commonest shape is kept and the others counted."""
    qca = read_capture(others() / PICO_QCA)
    assert qca.source == "picoscenes QCA9300" and qca.csi.shape == (1000, 56, 3, 1) and qca.dropped == {}
    assert np.all(qca.centre_freq_hz == 5200e6) and qca.bandwidth_hz == 20e6
    np.testing.assert_array_equal(qca.subcarriers, [*range(-28, 0), *range(1, 29)])
    iwl = read_capture(others() / PICO_IWL)
    assert iwl.source == "picoscenes IWL5300" and iwl.csi.shape[1] == 30
    assert len(iwl) + sum(iwl.dropped.values()) == 383
    np.testing.assert_array_equal(iwl.subcarriers, [*range(-28, -1, 2), -1, 1, *range(3, 28, 2), 28])


def test_a_picoscenes_rxsbasic_segment_decoded_by_hand_is_the_readers():
    """PicoScenes' frame: a 4-byte length, the magic 0x20150315, a 2-byte version and a segment
    count; each segment a 4-byte length, a name (1-byte length), a 2-byte version and its body.
    RxSBasic version 1: device type, timestamp (us), centre frequency (MHz), packet format,
    bandwidth (MHz), guard interval, MCS, spatial streams, extension streams, receive chains,
    noise floor (dBm), then the RSSI and one per chain in dB over the noise floor."""
    raw = (others() / PICO_QCA).read_bytes()
    assert struct.unpack_from("<I", raw, 4)[0] == 0x20150315
    at = 4 + 4 + 2 + 1
    _seg_len, name_len = struct.unpack_from("<IB", raw, at)
    name = raw[at + 5 : at + 5 + name_len]
    body = at + 5 + name_len + 2
    assert name == b"RxSBasic" and struct.unpack_from("<H", raw, body - 2)[0] == 1
    device, stamp_us, centre_mhz, _fmt, cbw, _gi, _mcs, _sts, _ess, rx, noise, _rssi, *chains = struct.unpack_from(
        "<HQhBHHBBBBbBBBB", raw, body
    )
    frames = read_capture(others() / PICO_QCA)
    assert device == 0x9300 and rx == 3 and cbw == 20
    assert frames.timestamp_ns[0] == stamp_us * 1000 and frames.centre_freq_hz[0] == centre_mhz * 1e6
    assert frames.noise_dbm[0] == noise and list(frames.rssi_db[0]) == [noise + c for c in chains]


def truncated(tmp_path: Path, name: str, keep: int) -> Path:
    out = tmp_path / f"cut-{name}"
    out.write_bytes((others() / name).read_bytes()[:keep])
    return out


@pytest.mark.parametrize(
    ("name", "keep", "args", "what"),
    [
        # 52 whole records of 2 + 25 + 840 + 1,040 bytes: 99,164
        (ATHEROS, 100_000, [], "record 53 starts at byte 99,164 and the file ends 836 bytes into it"),
        # pcap's 24-byte header, then two whole frames of 16 + 1,084 bytes
        (NEXMON, 3_000, ["--chip", "4358"], "frame 3 starts at byte 2,224 and the file ends 776 bytes into it"),
        (PICO_QCA, 5_000, [], "frame 7 starts at byte"),
    ],
    ids=["atheros", "nexmon", "picoscenes"],
)
def test_a_truncated_capture_gives_one_line_and_exit_2(tmp_path, name, keep, args, what):
    cut = truncated(tmp_path, name, keep)
    result = run_rover("info", str(cut), *args)
    assert result.returncode == 2 and result.stdout == ""
    assert len(result.stderr.splitlines()) == 1 and result.stderr.startswith(f"rover: error: {cut}: truncated: {what}")


def test_unknown_and_mislabelled_captures_are_refused_naming_what_was_tried(tmp_path):
    junk = tmp_path / "junk.dat"
    junk.write_bytes(b"not a capture at all" * 10)
    result = run_rover("info", str(junk))
    assert result.returncode == 2 and len(result.stderr.splitlines()) == 1
    assert result.stderr == (
        f"rover: error: {junk}: neither an MCAP dataset nor a CSI capture Rover reads (tried: Atheros CSI Tool "
        "log, Nexmon pcap, PicoScenes .csi, a ROS bag of WiROS's rf_msgs/msg/Wifi; the Intel 5300's CSI Tool logs "
        "go to `rover aoa` and `rover calibrate`)\n"
    )
    intel = reference_data() / "csi" / "sample_0x1_ap.dat"
    assert "go to `rover aoa`" in run_rover("info", str(intel)).stderr
    result = run_rover("info", str(others() / ATHEROS), "--format", "picoscenes")
    assert result.returncode == 2 and "not a PicoScenes file" in result.stderr
    result = run_rover("info", str(others() / NEXMON))
    assert (
        result.returncode == 2
        and "does not say which chip wrote it" in result.stderr
        and "give --chip" in result.stderr
    )
    with pytest.raises(BadInput, match="--format ath: not one of atheros, nexmon, picoscenes"):
        read_capture(others() / ATHEROS, "ath")


def test_rover_info_summarizes_a_capture_as_text_and_json():
    result = run_rover("info", str(others() / PICO_QCA), "--json")
    assert result.returncode == 0, result.stderr
    import json

    info = json.loads(result.stdout)
    assert info["source"] == "picoscenes QCA9300" and info["packets"] == 1000
    assert (info["subcarriers"], info["receive_chains"], info["transmit_streams"]) == (56, 3, 1)
    assert info["centre_freqs_mhz"] == [5200.0] and info["transmitters"] == ["00:0e:8e:59:8a:de"]
    text = run_rover("info", str(others() / ATHEROS)).stdout
    assert "56 subcarriers x 3 receive chains x 2 transmit streams" in text and "2437 MHz" in text


def atheros_record(nr: int, nc: int, *, tones: int = 56, bw: int = 0, payload: bytes = b"", seed: int = 1) -> bytes:
    """One record of an Atheros CSI Tool log (little-endian), as its format is described above."""
    csi_len = -(-tones * nr * nc * 2 * 10 // 8)
    csi = np.random.default_rng(seed).integers(0, 256, csi_len, dtype=np.uint8).tobytes()
    status = struct.pack(
        "<QHHBBBBBBBBBBBH", seed, csi_len, 2437, 0, 0, 143, bw, tones, nr, nc, 50, 40, 41, 42, len(payload)
    )
    return struct.pack("<H", len(status) + csi_len + len(payload)) + status + csi + payload


def test_atheros_logs_csiread_alone_would_crash_on_are_read_or_refused_in_one_line(tmp_path):
    """Small records (csiread sizes its buffers for records of 420 bytes), a record of other chains
    and streams, mixed bandwidths, a payload over csiread's 4 KB buffer: read, counted, or refused
    naming the record, never a crash."""
    small = tmp_path / "small.dat"
    small.write_bytes(b"".join(atheros_record(1, 1, seed=i + 1) for i in range(2000)))
    assert read_capture(small).csi.shape == (2000, 56, 1, 1)
    sample = (others() / ATHEROS).read_bytes()
    mixed = tmp_path / "mixed.dat"
    mixed.write_bytes(atheros_record(3, 1) + sample)
    frames = read_capture(mixed)
    assert frames.csi.shape == (401, 56, 3, 2)
    assert frames.dropped == {"records of other chains or streams than the commonest (3x2)": 1}
    for name, data, why in [
        ("bandwidths.dat", sample + atheros_record(3, 2, tones=114, bw=1), "its records mix 56 and 114 tones"),
        ("amsdu.dat", atheros_record(3, 2, payload=bytes(5000)) + sample, "record 1 (at byte 0): its payload or CSI"),
    ]:
        path = tmp_path / name
        path.write_bytes(data)
        result = run_rover("info", str(path))
        assert result.returncode == 2 and len(result.stderr.splitlines()) == 1 and why in result.stderr


def test_nexmon_retransmissions_are_counted_and_a_capture_without_a_whole_packet_is_refused(tmp_path):
    raw = (others() / NEXMON).read_bytes()
    twice = tmp_path / "twice.pcap"
    twice.write_bytes(raw + raw[24:])  # the packet's four frames again, the same sequence number
    frames = read_capture(twice, chip="4358")
    assert frames.csi.shape == (1, 256, 2, 2)
    assert frames.dropped == {"frames repeating their packet's core and stream (a retransmission: the last kept)": 4}
    three = tmp_path / "three.pcap"
    three.write_bytes(raw[: 24 + 3 * (16 + 1084)])  # the fourth frame lost
    with pytest.raises(BadInput, match=r"no packet Rover can use \(1 packets missing the frame of some core"):
        read_capture(three, chip="4358")


def test_a_picoscenes_file_without_a_csi_segment_is_refused(tmp_path):
    """The QCA9300 sample with its CSI segments renamed: no frame has CSI (csiread skips the segment
    silently), so one line and exit 2, not a summary of 0 x 0 x 0 packets."""
    path = tmp_path / "no-csi.csi"
    path.write_bytes((others() / PICO_QCA).read_bytes().replace(b"\x03CSI", b"\x03XSI"))
    result = run_rover("info", str(path))
    assert result.returncode == 2 and len(result.stderr.splitlines()) == 1
    assert "no frame with CSI of 312.5 kHz subcarriers" in result.stderr
