"""AoA on another tool's capture (rover.operators.aoa.capture, `rover aoa CAPTURE`): a plane wave
written here from the physics (not by the simulator) is found at its angle with any array and
subcarrier plan the sources give; the real captures run through `rover aoa`."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers import reference_data, run_rover

from rover.formats.csi_sources import CsiFrames
from rover.formats.rig import Rig, rig_from_text
from rover.operators.aoa.capture import capture_bursts, occupied

C_M_S = 299_792_458.0
SPACING_HZ = 312_500.0


def plane_wave(
    antennas_m: np.ndarray, angle_deg: float, centre_hz: float, subcarriers: np.ndarray, empty: np.ndarray, seed: int
) -> CsiFrames:
    """60 packets of a wave from `angle_deg` (the direction of its source): antenna m at p_m sees it
    exp(+j 2 pi f p_m . u / c) earlier than the origin, at every subcarrier's own frequency f, after
    a 20 ns delay; each packet a random common phase and timing offset (the receiver's), and noise
    20 dB under the signal; the subcarriers in `empty` carry nothing (DC and guards)."""
    rng = np.random.default_rng(seed)
    f = centre_hz + subcarriers * SPACING_HZ
    u = np.array([math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))])
    lead_s = antennas_m @ u / C_M_S
    packets = 60
    h = np.exp(2j * np.pi * f[None, :, None] * (lead_s[None, None, :] - 20e-9))
    common = np.exp(1j * rng.uniform(-np.pi, np.pi, packets))[:, None, None]
    timing = np.exp(
        -2j * np.pi * subcarriers[None, :, None] * SPACING_HZ * rng.normal(0, 30e-9, packets)[:, None, None]
    )
    shape = (packets, len(subcarriers), len(antennas_m), 1)
    noise = 0.1 * (rng.normal(size=shape) + 1j * rng.normal(size=shape)) / math.sqrt(2)
    csi = (h * common * timing)[..., None] + noise
    csi[:, np.isin(subcarriers, empty)] = 0
    n = len(antennas_m)
    return CsiFrames(
        source="test",
        csi=csi,
        subcarriers=subcarriers,
        bandwidth_hz=float(np.ptp(subcarriers) + 1) * SPACING_HZ,
        centre_freq_hz=np.full(packets, centre_hz),
        timestamp_ns=np.arange(packets, dtype=np.int64) * 10_000_000,
        rssi_db=np.full((packets, n), np.nan),
        noise_dbm=np.full(packets, np.nan),
        mac=np.zeros((packets, 6), np.uint8),
        sequence=np.arange(packets),
        dropped={},
    )


def rig(antennas_m: np.ndarray) -> Rig:
    return rig_from_text(f"receiver:\n  antenna_positions_m: {antennas_m.tolist()}\n", "test rig")


SQUARE_19MM = np.array([[0.0, 0.0], [0.019, 0.0], [0.019, 0.019], [0.0, 0.019]])
"""WiROS's square of four for all directions (19 mm sides)"""
LINE_26MM = np.array([[0.0, 0.0], [0.026, 0.0], [0.052, 0.0]])
TRIANGLE = np.array([[0.0, 0.0], [0.0258, 0.0], [0.0129, -0.0224]])


@pytest.mark.parametrize(
    ("antennas", "angle_deg", "centre_hz", "subcarriers", "empty"),
    [
        # Nexmon's 4366c0 at 80 MHz: 256 bins, DC and guards empty
        (SQUARE_19MM, -130.0, 5775e6, np.arange(-128, 128), np.r_[-128:-122, -1:2, 123:128]),
        # the Atheros CSI Tool at 20 MHz: 56 tones, a line (its field of view is a half plane)
        (LINE_26MM, 60.0, 2437e6, np.r_[-28:0, 1:29], np.zeros(0)),
        # PicoScenes' QCA9300 at 5200 MHz
        (TRIANGLE, 150.0, 5200e6, np.r_[-28:0, 1:29], np.zeros(0)),
    ],
    ids=["nexmon-square-80MHz", "atheros-line-20MHz", "qca-triangle-5GHz"],
)
def test_a_plane_wave_is_found_at_its_angle_with_any_array_and_plan(antennas, angle_deg, centre_hz, subcarriers, empty):
    frames = plane_wave(antennas, angle_deg, centre_hz, subcarriers, empty, seed=1)
    assert not np.isin(frames.subcarriers[occupied(frames)], empty).any()
    channel = round((centre_hz - (5000e6 if centre_hz > 3e9 else 2407e6)) / 5e6)
    bursts = capture_bursts(frames, rig(antennas), channel, centre_hz, burst_packets=20)
    assert len(bursts) == 3
    errors = [abs((math.degrees(b.angle_rad) - angle_deg + 180) % 360 - 180) for b in bursts]
    assert max(errors) < 3.0, errors


def test_rover_aoa_reads_the_real_captures_and_refuses_a_rig_of_another_antenna_count(tmp_path):
    others = reference_data() / "csi" / "others"
    setup = tmp_path / "rig.yaml"
    setup.write_text(f"receiver:\n  antenna_positions_m: {TRIANGLE.tolist()}\n")
    csv = tmp_path / "aoa.csv"
    result = run_rover("aoa", str(others / "rx_by_qca9300.csi"), "--setup", str(setup), "--csv", str(csv))
    assert result.returncode == 0, result.stderr
    assert "picoscenes QCA9300, 1000 packets, 20 bursts of 50 packets, channel 40" in result.stdout
    assert len(csv.read_text().splitlines()) == 21
    result = run_rover("aoa", str(others / "rx_by_iwl5300.csi"), "--setup", str(setup))
    assert result.returncode == 2
    assert result.stderr.splitlines()[-1] == (
        f"rover: error: {others / 'rx_by_iwl5300.csi'}: its packets have 2 receive chains, the setup 3 antennas"
    )
    result = run_rover("aoa", str(others / "ath_csi_1.dat"), "--setup", str(setup))
    assert result.returncode == 0 and "atheros, 401 packets, 8 bursts of 50 packets, channel 6" in result.stdout
