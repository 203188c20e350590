"""The CSI Tool decoder against the tool's own MATLAB output, in whole files, in chunks, and through damage."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conftest import reference_data
from rover.drivers.intel5300 import CsiFormatError, StreamDecoder, concat, decode_bfee, decode_log, read_dat, split_records

FIELDS = ("timestamp_low", "bfee_count", "nrx", "ntx", "rssi", "noise", "agc", "perm", "rate", "csi")


@pytest.fixture(scope="module")
def small() -> bytes:
    return (reference_data() / "csi" / "log.all_csi.6.7.6.dat").read_bytes()


@pytest.fixture(scope="module")
def sample() -> bytes:
    return (reference_data() / "csi" / "sample_0x1_ap.dat").read_bytes()


def same(a, b) -> None:
    assert len(a) == len(b)
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)
    assert (a.n_skipped, a.n_corrupt) == (b.n_skipped, b.n_corrupt)


def records_of(data: bytes) -> list[bytes]:
    out, pos = [], 0
    while pos + 2 <= len(data):
        (n,) = struct.unpack_from(">H", data, pos)
        out.append(data[pos:pos + 2 + n])
        pos += 2 + n
    return out


def test_matches_the_csi_tools_matlab_output_exactly():
    from scipy.io import loadmat

    ref = loadmat(str(reference_data() / "csi" / "log.all_csi.6.7.6.reference.mat"))
    raw = read_dat(reference_data() / "csi" / "log.all_csi.6.7.6.dat", scaled=False)
    scaled = read_dat(reference_data() / "csi" / "log.all_csi.6.7.6.dat")
    assert len(raw) == 29 and raw.n_skipped == raw.n_corrupt == 0
    for i in range(29):
        e = ref["csi"][i, 0]
        value = lambda name: int(e[name][0, 0][0, 0])
        nrx, ntx = value("Nrx"), value("Ntx")
        assert (raw.nrx[i], raw.ntx[i]) == (nrx, ntx)
        for name, mine in (("timestamp_low", raw.timestamp_low), ("bfee_count", raw.bfee_count), ("agc", raw.agc),
                           ("rate", raw.rate), ("noise", raw.noise), ("rssi_a", raw.rssi[:, 0]),
                           ("rssi_b", raw.rssi[:, 1]), ("rssi_c", raw.rssi[:, 2])):
            assert int(mine[i]) == value(name), (i, name)
        assert raw.perm[i].tolist() == e["perm"][0, 0][0].tolist()
        np.testing.assert_array_equal(raw.csi[i, :, :nrx, :ntx].transpose(2, 1, 0), e["csi"][0, 0])
        assert not raw.csi[i, :, nrx:, :].any() and not raw.csi[i, :, :, ntx:].any()
        np.testing.assert_allclose(scaled.csi[i, :, :nrx, :ntx].transpose(2, 1, 0), ref["csi_scaled"][i, 0],
                                   rtol=0, atol=1e-9)
    assert set(raw.ntx.tolist()) == {1, 2, 3} and (raw.noise == -127).all()


def test_sample_first_record_tells_scatter_from_gather(sample):
    raw = decode_log(sample, scaled=False)
    assert len(raw) == 540 and raw.bfee_count[0] == 6224
    assert raw.perm[0].tolist() == [2, 3, 1]
    assert raw.csi[0, 0, 0, 0] == 13 - 10j


def test_decode_bfee_equals_the_file(small):
    whole = decode_log(small)
    same(decode_bfee([r[2:] for r in records_of(small)]), whole)
    split, framing = split_records(small)
    assert split == [r[2:] for r in records_of(small)] and framing.skipped == framing.corrupt == 0


def stream(data: bytes, cuts: list[int], scaled: bool = True):
    dec = StreamDecoder(scaled)
    parts, last = [], 0
    for cut in sorted(cuts):
        parts.append(dec.feed(data[last:cut]))
        last = cut
    parts.append(dec.feed(data[last:]))
    parts.append(dec.close())
    return concat(parts)


def test_streaming_equals_whole_file_at_every_split_point(small):
    whole = decode_log(small)
    for cut in range(len(small) + 1):
        same(stream(small, [cut]), whole)


def test_streaming_equals_whole_file_at_random_split_points(sample):
    rng = np.random.default_rng(2015)
    whole = decode_log(sample, scaled=False)
    for cut in rng.integers(0, len(sample) + 1, 2000):
        same(stream(sample, [int(cut)], scaled=False), whole)
    same(stream(sample, rng.integers(0, len(sample) + 1, 300).tolist()), decode_log(sample))


def test_zero_length_and_truncated_files(tmp_path, small):
    empty = tmp_path / "empty.dat"
    empty.write_bytes(b"")
    nothing = read_dat(empty)
    assert len(nothing) == 0 and nothing.csi.shape == (0, 30, 1, 1)
    recs = records_of(small)
    ends = np.cumsum([len(r) for r in recs])
    for cut in (1, 2, 3, 50, len(small) // 2, len(small) - 1):
        part = decode_log(small[:cut])
        complete = int(np.searchsorted(ends, cut, side="right"))
        assert part.bfee_count.tolist() == decode_log(small).bfee_count[:complete].tolist()
        cut_short = cut - (ends[complete - 1] if complete else 0) >= 23
        assert part.n_corrupt == int(cut_short)


def test_other_codes_are_skipped_and_counted(small):
    recs = records_of(small)
    other = struct.pack(">H", 9) + b"\xc1" + b"payload!"
    data = b"".join(recs[:5]) + other + b"".join(recs[5:]) + other
    out = decode_log(data)
    assert len(out) == 29 and out.n_skipped == 2 and out.n_corrupt == 0


def test_a_len_field_that_disagrees_is_corrupt_not_decoded(small):
    recs = [bytearray(r) for r in records_of(small)]
    bad = recs[3]
    struct.pack_into("<H", bad, 2 + 1 + 16, 100)              # len field no longer matches Nrx/Ntx...
    struct.pack_into(">H", bad, 0, 1 + 20 + 100)              # ...though the framing is consistent
    del bad[2 + 1 + 20 + 100:]
    out = decode_log(b"".join(bytes(r) for r in recs))
    assert len(out) == 28 and out.n_corrupt == 1
    assert out.bfee_count.tolist() == [b for i, b in enumerate(decode_log(small).bfee_count) if i != 3]


def test_a_flipped_length_byte_loses_only_that_record(small):
    recs = [bytearray(r) for r in records_of(small)]
    recs[10][0] ^= 0x40
    out = decode_log(b"".join(bytes(r) for r in recs))
    expected = [b for i, b in enumerate(decode_log(small).bfee_count) if i != 10]
    assert out.bfee_count.tolist() == expected


def test_garbage_between_records_is_skipped(small):
    rng = np.random.default_rng(7)
    recs = records_of(small)
    data = b"".join(r + rng.integers(0, 256, int(rng.integers(1, 300)), dtype=np.uint8).tobytes() for r in recs)
    out = decode_log(data)
    assert out.bfee_count.tolist() == decode_log(small).bfee_count.tolist()
    assert out.n_garbage_bytes > 0
    same(stream(data, rng.integers(0, len(data), 40).tolist()), out)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.binary(max_size=3000))
def test_arbitrary_bytes_never_raise_anything_else(data):
    try:
        out = decode_log(data)
    except CsiFormatError:
        return
    assert len(out) >= 0


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(junk=st.lists(st.binary(max_size=400), min_size=29, max_size=29), cut=st.integers(0, 20000))
def test_valid_records_after_damage_are_never_lost(small, junk, cut):
    recs = records_of(small)
    data = b"".join(j + r for j, r in zip(junk, recs))
    out = decode_log(data)
    found = out.bfee_count.tolist()
    expected = decode_log(small).bfee_count.tolist()
    it = iter(found)
    assert all(b in it for b in expected), "a valid record after damage was lost"
    same(stream(data, [min(cut, len(data))]), out)


def test_encoding_is_the_exact_inverse(small):
    from rover.drivers.intel5300 import RecordHeader, encode_record

    raw = decode_log(small, scaled=False)
    for i, record in enumerate(records_of(small)):
        n, t = int(raw.nrx[i]), int(raw.ntx[i])
        head = RecordHeader(int(raw.timestamp_low[i]), int(raw.bfee_count[i]), tuple(int(v) for v in raw.rssi[i]),
                            int(raw.noise[i]), int(raw.agc[i]), int(raw.antenna_sel[i]), int(raw.rate[i]))
        assert encode_record(head, raw.csi[i, :, :n, :t]) == record[2:]
    rng = np.random.default_rng(5)
    for sel in (0b100100, 0b011000, 0b001001, 0b010010, 0b000110, 0b100001):
        for n, t in ((3, 1), (3, 2), (2, 2), (1, 3)):
            csi = rng.integers(-128, 128, (30, n, t)) + 1j * rng.integers(-128, 128, (30, n, t))
            head = RecordHeader(7, 9, (30, 31, 32), -92, 40, sel, 0x1101)
            back = decode_bfee([encode_record(head, csi)], scaled=False)
            np.testing.assert_array_equal(back.csi[0], csi)
    with pytest.raises(CsiFormatError):
        encode_record(RecordHeader(0, 0, (0, 0, 0), 0, 0, 0, 0), np.full((30, 3, 1), 200.0))
