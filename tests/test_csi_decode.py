"""`csi_decode`: labelled frames of real records become Csi messages equal to the file decoder's output."""

from __future__ import annotations

import numpy as np
from helpers import T0_NS, reference_data

from rover.formats.intel5300 import read_dat, split_records
from rover.messages import deserialize, header, make, serialize
from rover.operators.csi_decode import CsiDecode, csi_array
from rover.testing import run_operator


def labelled(bfee: bytes, channel: int, i: int):
    return make(
        "rover_msgs/msg/LabelledCsiFrame",
        header=header(T0_NS + i * 1_000_000),
        tag_id=channel % 10,
        channel=channel,
        bfee=np.frombuffer(bfee, dtype=np.uint8),
    )


def test_decoded_messages_equal_the_file_decoder_and_keep_their_frame():
    path = reference_data() / "csi" / "sample_0x1_ap.dat"
    records, _ = split_records(path.read_bytes())
    whole = read_dat(path)
    op = CsiDecode()
    frames = [labelled(r, 149 if i < 300 else 153, i) for i, r in enumerate(records[:400])]
    frames.insert(10, labelled(b"\xc1garbage", 149, 10))
    out = run_operator(op, {"frames": frames})
    assert len(out) == 400
    msgs = [deserialize(serialize(e.msg), "rover_msgs/msg/Csi") for e in out]
    assert [m.bfee_count for m in msgs] == whole.bfee_count[:400].tolist()
    assert [m.channel for m in msgs] == [149] * 300 + [153] * 100
    for k in (0, 299, 399):
        np.testing.assert_allclose(csi_array(msgs[k]), whole.csi[k, :, :3, :2], rtol=1e-6)
        assert msgs[k].perm.tolist() == whole.perm[k].tolist()
    assert op.drops == {"frames that are not beamforming records": 1}


def test_a_batch_decoded_when_idle_gives_the_same_messages_and_says_what_it_held():
    """Live, frames trickle in: the runtime calls `on_idle` whenever none waits, and what the batch
    held comes out then, each message as a whole batch decodes it; `held_since_ns` is the held
    batch's first stamp (inf once it is sent), what the runtime promises downstream."""
    path = reference_data() / "csi" / "sample_0x1_ap.dat"
    records, _ = split_records(path.read_bytes())
    frames = [labelled(r, 149, i) for i, r in enumerate(records[:40])]
    whole = [serialize(e.msg) for e in run_operator(CsiDecode(), {"frames": frames})]
    op = CsiDecode()
    trickled = []
    assert op.held_since_ns() == float("inf")
    for i, frame in enumerate(frames):
        trickled += list(op.on_input("frames", frame, T0_NS + i * 1_000_000))
        assert op.held_since_ns() == T0_NS + (i // 3) * 3 * 1_000_000
        if i % 3 == 2:  # nothing came for a while after every third frame
            trickled += list(op.on_idle())
            assert op.held_since_ns() == float("inf")
    trickled += list(op.on_end())
    assert [serialize(e.msg) for e in trickled] == whole
    assert [e.stamp_ns for e in trickled] == [T0_NS + i * 1_000_000 for i in range(40)]
