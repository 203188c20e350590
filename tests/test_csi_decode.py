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
