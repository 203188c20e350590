"""The rig description: the users' setup.yaml, every problem with its position, tags by channel or by shift."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import reference_data, run_rover

from rover.errors import BadInput, SpecError
from rover.formats.rig import (
    UNNAMED_CHANNEL_FREQ_HZ,
    RigInput,
    TagSpec,
    field_of_view_span_deg,
    load_rig,
    rig_from_text,
)
from rover.formats.wifi import channel_freq_hz
from rover.messages import make
from rover.operators.channel_sweep.operator import ChannelSweep, SweepParams

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


BARE = """\
receiver:
  antenna_positions_m: [[0, 0], [0, -0.1], [0, -0.2]]
  channel: 64
  phase_offsets_rad: [0.0, 0.5, -1.0]
  field_of_view_deg: [-60, 60]
"""


def test_a_bare_receiver_is_a_rig():
    rig = rig_from_text(BARE)
    assert rig.excitation_channel is None and rig.tags == () and rig.receiver_channel == 64
    assert rig.field_of_view_deg == (-60.0, 60.0) and rig.max_freq_hz == channel_freq_hz(64)
    np.testing.assert_allclose(rig.phase_offsets(64), [0.0, 0.5, -1.0])
    with pytest.raises(BadInput, match=r"^channel_sweep: the setup has no excitation channel: add excitation: \{"):
        rig.require_excitation("channel_sweep")
    assert rig_from_text(SETUP).require_excitation("channel_sweep") == 165


def test_the_frequency_the_array_is_checked_at_is_the_highest_it_listens_on():
    assert rig_from_text(SETUP).max_freq_hz == channel_freq_hz(153)
    assert rig_from_text(BARE + "tags: [{id: 1, channel: 36}]\n").max_freq_hz == channel_freq_hz(64)
    assert rig_from_text(BARE.replace("  channel: 64\n", "")).max_freq_hz == UNNAMED_CHANNEL_FREQ_HZ


def test_tags_without_an_excitation_channel_need_their_channel():
    rig = rig_from_text(BARE + "tags: [{id: 1, channel: 149}]\n")
    assert rig.tags == (TagSpec(1, 149, None),) and rig.tag_on(149) == rig.tags[0]
    with pytest.raises(SpecError) as info:
        rig_from_text(BARE + "tags: [{id: 1, shift_hz: 40000000}]\nexcitation: {}\n", "s.yaml")
    assert [str(d) for d in info.value.diagnostics] == [
        "s.yaml:7:13: excitation needs its channel: excitation: {channel: N}"
    ]
    with pytest.raises(SpecError) as info:
        rig_from_text(BARE + "tags: [{id: 1, shift_hz: 40000000}]\n", "s.yaml")
    (message,) = [str(d) for d in info.value.diagnostics]
    assert message.startswith("s.yaml:6:") and "tag 1: shift_hz needs the excitation channel" in message


def test_a_channel_sweep_needs_the_excitation_channel():
    """Live, at once; labelling a replay, at its first CSI Tool frame (a bare receiver's dataset holds
    another tool's capture, which the sweep never sees)."""
    setup = make("rover_msgs/msg/RigSetup", setup_yaml=BARE + "tags: [{id: 1, channel: 149}]\n")
    with pytest.raises(BadInput, match=r"^channel_sweep: the setup has no excitation channel"):
        list(ChannelSweep(SweepParams(mode="live")).on_input("setup", setup, 0))
    sweep = ChannelSweep()
    assert list(sweep.on_input("setup", setup, 0)) == []
    frame = make("rover_msgs/msg/CsiFrame", channel=149)
    with pytest.raises(BadInput, match=r"^channel_sweep: the setup has no excitation channel"):
        list(sweep.on_input("frames", frame, 1))


@pytest.mark.parametrize(
    ("field", "span"),
    [((-90, 90), 180), ((270, 90), 180), ((90, -90), 180), ((350, 10), 20), ((0, 360), 360), ((-180, 180), 360)],
)
def test_a_field_of_view_runs_counter_clockwise(field, span):
    assert field_of_view_span_deg(field) == span
    rig = rig_from_text(BARE.replace("[-60, 60]", f"[{field[0]}, {field[1]}]"))
    assert rig.field_of_view_deg == field


@pytest.mark.parametrize(
    ("value", "problem"),
    [
        ("[10, 10]", "covers less than 1 degree"),
        ("[10, 10.5]", "covers less than 1 degree"),
        ("[10]", "must be a list of 2 finite numbers"),
        ("right", "must be a list of 2 finite numbers"),
    ],
)
def test_a_bad_field_of_view_is_reported_at_its_position(value, problem):
    with pytest.raises(SpecError) as info:
        rig_from_text(BARE.replace("[-60, 60]", value), "s.yaml")
    (message,) = [str(d) for d in info.value.diagnostics]
    assert message.startswith("s.yaml:5:22: ") and problem in message


def test_antennas_at_one_position_are_refused():
    with pytest.raises(SpecError, match=r"s.yaml:2:.*the antennas are all at one position"):
        rig_from_text(BARE.replace("[[0, 0], [0, -0.1], [0, -0.2]]", "[[0.1, 0], [0.1, 0]]"), "s.yaml")
