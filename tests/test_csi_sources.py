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
    # the DC bin is empty, the band's edges are guards: the strongest bins are inside the band
    power = np.abs(frames.csi[0]).sum(axis=(1, 2))
    assert power[128] < np.median(power) and np.argmax(power) not in range(128 - 3, 128 + 4)


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
        "log, Nexmon pcap, PicoScenes .csi; the Intel 5300's CSI Tool logs go to `rover aoa` and `rover calibrate`)\n"
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
