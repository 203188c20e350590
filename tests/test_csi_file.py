"""`csi_file`: a CSI Tool log read whole, or followed while another process appends to it."""

from __future__ import annotations

import struct
import threading
import time

import numpy as np
import pytest
from helpers import T0_NS, read_bag, reference_data, run_rover

from rover.drivers import csi_file
from rover.drivers.csi_file import CsiFile, CsiFileParams
from rover.formats.intel5300 import RecordHeader, encode_record, read_dat, split_records
from rover.messages import deserialize, stamp_ns
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


LGTM_20_DEG = "lgtm/lgtm-monitor.dat--1m-20-degrees--laptop-1--test-1.dat"


def stamps_of(params: CsiFileParams) -> list[int]:
    return [stamp_ns(item.msg) for item in CsiFile(params).run(threading.Event()) if isinstance(item, Emit)]


@pytest.mark.parametrize("name", ["log.all_csi.6.7.6.dat", "sample_0x1_ap.dat", LGTM_20_DEG])
def test_a_whole_log_is_stamped_from_the_nics_clock(name):
    """The LGTM capture (1,019 records over 0.26 s) is read in several chunks."""
    path = reference_data() / "csi" / name
    low = read_dat(path).timestamp_low.astype(np.int64)
    assert (np.diff(low) >= 0).all(), "these logs do not wrap"
    stamps = np.array(stamps_of(CsiFileParams(path=str(path), start_ns=T0_NS)))
    assert (np.diff(stamps) >= 0).all() and stamps[0] == T0_NS
    assert stamps[-1] - stamps[0] == (low[-1] - low[0]) * 1000
    np.testing.assert_array_equal(stamps - T0_NS, (low - low[0]) * 1000)
    assert stamps_of(CsiFileParams(path=str(path)))[0] == 0


def synthetic_log(lows: list[int]) -> bytes:
    """A log of 3x1 records with these timestamp_low values."""
    csi = np.ones((30, 3, 1), complex)
    records = [
        encode_record(RecordHeader(low, i, (30, 30, 30), -90, 20, 0b100100, 0x101), csi) for i, low in enumerate(lows)
    ]
    return b"".join(struct.pack(">H", len(r)) + r for r in records)


@pytest.mark.parametrize("chunk_bytes", [100, 1 << 16])
def test_the_nics_clock_is_unwrapped_across_reads(tmp_path, monkeypatch, chunk_bytes):
    """Two wraps, one between records read apart when the file is read 100 bytes at a time."""
    monkeypatch.setattr(csi_file, "CHUNK_BYTES", chunk_bytes)
    lows = [2**32 - 3000, 2**32 - 1000, 500, 2_000_000_000, 4_000_000_000, 100]
    wraps = [0, 0, 1, 1, 1, 2]
    path = tmp_path / "wrapping.dat"
    path.write_bytes(synthetic_log(lows))
    stamps = stamps_of(CsiFileParams(path=str(path), start_ns=T0_NS))
    unwrapped = np.array(lows, dtype=np.int64) + np.array(wraps) * 2**32
    assert stamps == (T0_NS + (unwrapped - unwrapped[0]) * 1000).tolist()


def test_receive_stamps_on_request_and_watermarks_on_the_log_clock_when_following(tmp_path):
    path = tmp_path / "log.dat"
    path.write_bytes(synthetic_log([1000, 2000, 3000]))
    before = time.time_ns()
    received = stamps_of(CsiFileParams(path=str(path), stamps="receive"))
    assert len(received) == 3 and before <= received[0] <= received[-1] <= time.time_ns()

    source = CsiFile(CsiFileParams(path=str(path), follow=True, stamps="log", start_ns=T0_NS, poll_s=0.001))
    stop = threading.Event()
    items = []
    for item in source.run(stop):
        items.append(item)
        if isinstance(item, Watermark) and len(items) > 3:
            stop.set()
    source.close()
    stamps = [item.stamp_ns if isinstance(item, Watermark) else stamp_ns(item.msg) for item in items]
    assert stamps == sorted(stamps) and stamps[0] == T0_NS
    assert [stamp_ns(i.msg) for i in items if isinstance(i, Emit)] == [T0_NS, T0_NS + 1_000_000, T0_NS + 2_000_000]
    assert any(isinstance(i, Watermark) and i.stamp_ns == T0_NS + 1_000_000 for i in items)
