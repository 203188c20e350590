"""`csi_file`: a CSI Tool log read whole, or followed while another process appends to it."""

from __future__ import annotations

import threading

from conftest import read_bag, reference_data, run_rover

from rover.drivers.csi_file import CsiFile, CsiFileParams
from rover.formats.intel5300 import split_records
from rover.messages import deserialize
from rover.operator import Emit, Watermark


def test_a_whole_log_through_the_pipeline(tmp_path):
    log = reference_data() / "csi" / "sample_0x1_ap.dat"
    damaged = tmp_path / "damaged.dat"
    damaged.write_bytes(b"\x00\x05\xc1abcd" + log.read_bytes()[:-7])
    (tmp_path / "p.yaml").write_text(f"""\
name: dat
operators:
  log: {{uses: csi_file, params: {{path: "{damaged}", channel: 153}}}}
  record: {{uses: recorder, inputs: {{csi: log/csi}}, params: {{out: out}}}}
""")
    proc = run_rover("run", "p.yaml", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    frames = [deserialize(d, "rover_msgs/msg/CsiFrame") for _t, _s, d in read_bag(tmp_path / "out" / "results.mcap")]
    records, _ = split_records(log.read_bytes())
    assert [bytes(f.bfee) for f in frames] == records[:-1] and {f.channel for f in frames} == {153}
    assert f"operator 'log': dropped 1 records with other codes in {damaged}\n" in proc.stderr
    assert f"operator 'log': dropped 1 corrupt records in {damaged}\n" in proc.stderr


def test_following_a_growing_log(tmp_path):
    """The log grows by pieces that cut records; each is appended when the source has read all there was
    (it then sends a watermark and waits), so every cut is met, whatever the timing."""
    data = (reference_data() / "csi" / "log.all_csi.6.7.6.dat").read_bytes()
    path = tmp_path / "live.dat"
    path.write_bytes(b"")
    pieces = [data[start : start + 333] for start in range(0, len(data), 333)]
    source = CsiFile(CsiFileParams(path=str(path), follow=True, poll_s=0.001))
    stop = threading.Event()
    frames = []
    with path.open("ab") as log:
        for item in source.run(stop):
            if isinstance(item, Emit):
                frames.append(bytes(item.msg.bfee))
                if len(frames) == 29:
                    stop.set()
            elif isinstance(item, Watermark) and pieces:
                log.write(pieces.pop(0))
                log.flush()
            else:
                stop.set()
    source.close()
    assert frames == split_records(data)[0] and not pieces and not source.drops
