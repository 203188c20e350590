"""`rig_source`: a setup.yaml sent once as a RigSetup, as `dataset_replay` sends a dataset's rig."""

from __future__ import annotations

import threading

import pytest
from helpers import T0_NS, read_bag, reference_data, run_rover

from rover.cli.registry import BUILTINS
from rover.drivers.rig_source import RigSource, RigSourceParams
from rover.errors import BadInput
from rover.formats.rig import rig_from_message
from rover.messages import deserialize, stamp_ns
from rover.operator import Emit
from rover.operators.channel_sweep.operator import ChannelSweep
from rover.pipeline.resolve import resolve
from rover.testing import run_operator

LGTM_SETUP = """\
# LGTM's laptop: a uniform linear array, 0.10 m apart, listening on channel 64 (5.32 GHz)
receiver:
  antenna_positions_m: [[0, 0], [0, -0.1], [0, -0.2]]
  channel: 64
"""


def sent(params: RigSourceParams) -> list[Emit]:
    items = list(RigSource(params).run(threading.Event()))
    assert all(isinstance(item, Emit) for item in items)
    return [item for item in items if isinstance(item, Emit)]


def test_the_rig_goes_out_once_verbatim_before_everything():
    setup = reference_data() / "recording_sample" / "setup.yaml"
    (emit,) = sent(RigSourceParams(path=str(setup)))
    assert emit.port == "setup" and emit.stamp_ns == 0 == stamp_ns(emit.msg)
    assert emit.msg.header.frame_id == "base_link" and emit.msg.setup_yaml == setup.read_text()
    assert [t.channel for t in rig_from_message(emit.msg).tags] == [149, 153, 157]
    (later,) = sent(RigSourceParams(path=str(setup), stamp_ns=T0_NS))
    assert later.stamp_ns == T0_NS == stamp_ns(later.msg)
    stopped = threading.Event()
    stopped.set()
    assert list(RigSource(RigSourceParams(path=str(setup))).run(stopped)) == []


def test_operators_downstream_get_it_on_their_setup_input():
    (emit,) = sent(RigSourceParams(path=str(reference_data() / "recording_sample" / "setup.yaml")))
    out = run_operator(ChannelSweep(), {"setup": [emit.msg]})
    (schedule,) = [e.msg for e in out if e.port == "schedule"]
    assert schedule.excitation_channel == 165 and schedule.channels.tolist() == [149, 153, 157]


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        (None, "no such file"),
        ("receiver: {antenna_positions_m: [[0, 0]]}\nexcitation: {channel: 999}\n", "at least two antenna"),
        ("receiver: [", "YAML"),
    ],
)
def test_a_bad_setup_file_is_one_line_naming_it(tmp_path, text, problem):
    path = tmp_path / "setup.yaml"
    if text is not None:
        path.write_text(text)
    with pytest.raises(BadInput) as info:
        RigSource(RigSourceParams(path=str(path)))
    message = str(info.value)
    assert message.startswith(str(path)) and "\n" not in message and problem in message
    with pytest.raises(BadInput, match="no setup file given"):
        RigSource(RigSourceParams())


def test_a_bare_log_with_its_rig_through_the_pipeline(tmp_path):
    """`rig_source` by its short name beside `csi_file`: the rig is recorded first, at the log's start."""
    assert resolve("rig_source", BUILTINS) is RigSource
    log = next((reference_data() / "csi" / "lgtm").glob("*--1m-20-degrees--laptop-1--test-1.dat"))
    (tmp_path / "setup.yaml").write_text(LGTM_SETUP)
    (tmp_path / "p.yaml").write_text(f"""\
name: bare
operators:
  rig: {{uses: rig_source, params: {{path: setup.yaml}}}}
  log: {{uses: csi_file, params: {{path: "{log}", channel: 64}}}}
  record: {{uses: recorder, inputs: {{setup: rig/setup, csi: log/csi}}, params: {{out: out}}}}
""")
    proc = run_rover("run", "p.yaml", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    messages = read_bag(tmp_path / "out" / "results.mcap")
    setups = [(t, deserialize(d, "rover_msgs/msg/RigSetup")) for topic, t, d in messages if topic == "/setup"]
    frames = [t for topic, t, _d in messages if topic == "/csi"]
    assert len(setups) == 1 and setups[0][1].setup_yaml == LGTM_SETUP
    assert len(frames) > 1000 and setups[0][0] <= min(frames)
