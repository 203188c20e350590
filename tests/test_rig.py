"""The rig description: the users' setup.yaml, every problem with its position, tags by channel or by shift."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import reference_data, run_rover

from rover.errors import BadInput, SpecError
from rover.formats.rig import RigInput, load_rig, rig_from_text
from rover.messages import make

SETUP = """\
receiver:
  antenna_positions_m: [[0.0, 0.0], [0.0258, 0.0], [0.0129, -0.02234]]
  phase_offsets_rad: {149: [0.0, 0.9, -1.7], 153: [0.0, 1.0, -1.6]}
excitation: {channel: 165}
tags: [{id: 1, channel: 149}, {id: 2, shift_hz: 60.0e+6}]
imu: {frame_id: imu_link, rate_hz: 200, rotation_rpy_deg: [0, 0, 90]}
"""


def test_the_sample_recordings_setup():
    rig = load_rig(reference_data() / "recording_sample" / "setup.yaml")
    assert rig.excitation_channel == 165
    assert [(t.id, t.channel) for t in rig.tags] == [(1, 149), (2, 153), (3, 157)]
    assert rig.antenna_positions_m.shape == (3, 2)
    np.testing.assert_allclose(rig.phase_offsets(157), [0.0, 0.9834, -2.7039])
    assert rig.topics == {"csi": "/csi", "imu": "/imu/data", "odom": "/odom"}


def test_per_channel_calibration_and_tags_by_shift():
    rig = rig_from_text(SETUP)
    np.testing.assert_allclose(rig.phase_offsets(153), [0.0, 1.0, -1.6])
    np.testing.assert_allclose(rig.phase_offsets(157), [0.0, 0.0, 0.0])
    tag = rig.tag_on(153)
    assert tag is not None and tag.id == 2 and rig.tags[1].shift_hz == 60e6
    assert rig.imu.rotation_rpy_deg == (0.0, 0.0, 90.0) and rig.text == SETUP


def test_every_problem_with_its_position():
    text = SETUP.replace("[0.0129, -0.02234]", "[0.0129]").replace("{channel: 165}", "{channel: 999}")
    text = text.replace("rate_hz: 200", "rate_hz: -1").replace("imu:", "imu:\n  fram_id: x\nimus:")
    with pytest.raises(SpecError) as info:
        rig_from_text(text, "s.yaml")
    messages = [str(d) for d in info.value.diagnostics]
    assert any(m.startswith("s.yaml:2:") and "antenna positions" in m for m in messages), messages
    assert any(m.startswith("s.yaml:4:23:") and "999 is not a WiFi channel" in m for m in messages), messages
    assert any("unknown key 'imus'" in m for m in messages), messages


def test_the_setup_input_parses_a_text_once_and_names_itself_in_errors():
    setup = RigInput()
    first = setup.update(make("rover_msgs/msg/RigSetup", setup_yaml=SETUP))
    assert setup.update(make("rover_msgs/msg/RigSetup", setup_yaml=SETUP)) is first
    other = setup.update(make("rover_msgs/msg/RigSetup", setup_yaml=SETUP.replace("165", "161")))
    assert other is not first and other.excitation_channel == 161
    with pytest.raises(BadInput, match=r"^rig description on the setup input: RigSetup:2:.*antenna positions"):
        setup.update(make("rover_msgs/msg/RigSetup", setup_yaml=SETUP.replace("[0.0129, -0.02234]", "[0.0129]")))
    assert setup.rig is other


def test_cli_check_reports_the_plans_conflicts(tmp_path):
    setup = tmp_path / "setup.yaml"
    setup.write_text(SETUP.replace("{id: 2, shift_hz: 60.0e+6}", "{id: 2, channel: 153}, {id: 4, channel: 161}"))
    proc = run_rover("check", str(setup))
    assert proc.returncode == 0
    assert (
        "ok: rig with 3 antennas, excitation channel 165 (at most 15 tags at once; channel 36 would allow 17), 3 tags"
        in proc.stdout
    )
    assert "tag 4's 3rd harmonic (5765 MHz, -9.5 dB) lands on channel 153, tag 2's" in proc.stderr
