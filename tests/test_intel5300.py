"""The CSI Tool decoder against the tool's own MATLAB output, in whole files, in chunks, and through damage.

The real captures are the reference data in ../shared/data (ROVER_TEST_DATA); damaged inputs are
built from them in tmp_path or in memory, never stored in the repository.
"""

from __future__ import annotations

import itertools
import struct

import numpy as np
import pytest
from helpers import reference_data
from hypothesis import given, settings
from hypothesis import strategies as st

from rover.formats.intel5300 import (
    CsiFormatError,
    CsiRecords,
    RecordHeader,
    StreamDecoder,
    concat,
    decode_bfee,
    decode_log,
    encode_record,
    read_dat,
    split_records,
)

FIELDS = (
    "timestamp_low",
    "bfee_count",
    "nrx",
    "ntx",
    "rssi",
    "noise",
    "agc",
    "antenna_sel",
    "perm",
    "rate",
    "csi",
    "offset",
)
COUNTS = ("n_skipped", "n_corrupt", "n_garbage_bytes")
IDENTITY_SEL = 0b100100
"""antenna_sel of perm [1 2 3]"""
ANTENNA_SEL_OFFSET = 15
"""antenna_sel's place in the notification header"""


@pytest.fixture(scope="module")
def small() -> bytes:
    """29 records, Ntx 1, 2 and 3, perms [3 2 1] and [2 3 1]."""
    return (reference_data() / "csi" / "log.all_csi.6.7.6.dat").read_bytes()


@pytest.fixture(scope="module")
def sample() -> bytes:
    """540 records, 3x2, perm [2 3 1]."""
    return (reference_data() / "csi" / "sample_0x1_ap.dat").read_bytes()


def records_of(data: bytes) -> list[bytes]:
    """The records of an undamaged log, each with its length prefix (an independent, naive framing)."""
    out, pos = [], 0
    while pos + 2 <= len(data):
        (n,) = struct.unpack_from(">H", data, pos)
        out.append(data[pos : pos + 2 + n])
        pos += 2 + n
    return out


def assert_same(a: CsiRecords, b: CsiRecords) -> None:
    assert len(a) == len(b)
    for name in FIELDS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
        assert getattr(a, name).dtype == getattr(b, name).dtype, name
    assert [getattr(a, c) for c in COUNTS] == [getattr(b, c) for c in COUNTS]


def streamed(data: bytes, cuts: list[int], scaled: bool = True) -> CsiRecords:
    """Decode `data` fed in pieces split at `cuts`."""
    dec = StreamDecoder(scaled)
    bounds = [0, *sorted(cuts), len(data)]
    parts = [dec.feed(data[a:b]) for a, b in itertools.pairwise(bounds)]
    parts.append(dec.close())
    out = concat(parts)
    assert [getattr(out, c) for c in COUNTS] == [dec.n_skipped, dec.n_corrupt, dec.n_garbage_bytes]
    return out


def other_record(payload: bytes, code: int = 0xC1) -> bytes:
    return struct.pack(">HB", len(payload) + 1, code) + payload


# ---------------------------------------------------------------------------------------------
# Against the CSI Tool's own output


def test_matches_the_csi_tools_matlab_output_exactly():
    from scipy.io import loadmat

    log = reference_data() / "csi" / "log.all_csi.6.7.6.dat"
    ref = loadmat(str(reference_data() / "csi" / "log.all_csi.6.7.6.reference.mat"))
    raw, scaled = read_dat(log, scaled=False), read_dat(log)
    assert len(raw) == 29 and (raw.n_skipped, raw.n_corrupt, raw.n_garbage_bytes) == (0, 0, 0)
    assert raw.csi.shape == (29, 30, 3, 3) and raw.csi.dtype == np.complex128
    for i in range(29):
        entry = ref["csi"][i, 0]
        value = {name: int(entry[name][0, 0][0, 0]) for name in entry.dtype.names if name not in ("perm", "csi")}
        nrx, ntx = value["Nrx"], value["Ntx"]
        assert (raw.nrx[i], raw.ntx[i]) == (nrx, ntx)
        for name, mine in (
            ("timestamp_low", raw.timestamp_low),
            ("bfee_count", raw.bfee_count),
            ("agc", raw.agc),
            ("rate", raw.rate),
            ("noise", raw.noise),
            ("rssi_a", raw.rssi[:, 0]),
            ("rssi_b", raw.rssi[:, 1]),
            ("rssi_c", raw.rssi[:, 2]),
        ):
            assert int(mine[i]) == value[name], (i, name)
        assert raw.perm[i].tolist() == entry["perm"][0, 0][0].tolist()
        np.testing.assert_array_equal(raw.csi[i, :, :nrx, :ntx].transpose(2, 1, 0), entry["csi"][0, 0])
        assert not raw.csi[i, :, nrx:, :].any() and not raw.csi[i, :, :, ntx:].any()
        np.testing.assert_allclose(
            scaled.csi[i, :, :nrx, :ntx].transpose(2, 1, 0), ref["csi_scaled"][i, 0], rtol=0, atol=1e-9
        )
        assert not scaled.csi[i, :, nrx:, :].any() and not scaled.csi[i, :, :, ntx:].any()
    assert set(raw.ntx.tolist()) == {1, 2, 3} and (raw.noise == -127).all()
    assert raw.offset.tolist() == np.cumsum([0] + [len(r) for r in records_of(log.read_bytes())])[:-1].tolist()
    assert {tuple(p) for p in raw.perm.tolist()} == {(3, 2, 1), (2, 3, 1)}
    for name, dtype in (
        ("timestamp_low", np.uint32),
        ("bfee_count", np.uint16),
        ("noise", np.int8),
        ("rate", np.uint16),
        ("rssi", np.uint8),
        ("agc", np.uint8),
    ):
        assert getattr(raw, name).dtype == dtype, name


def test_sample_first_record_tells_scatter_from_gather():
    raw = read_dat(reference_data() / "csi" / "sample_0x1_ap.dat", scaled=False)
    assert len(raw) == 540 and raw.bfee_count[0] == 6224 and raw.antenna_sel[0] == 9
    assert raw.perm[0].tolist() == [2, 3, 1]
    assert raw.csi[0, 0, 0, 0] == 13 - 10j
    assert raw.csi.shape == (540, 30, 3, 2)


def matlab_arrangement(raw: np.ndarray, perm: list[int]) -> np.ndarray:
    """read_bf_file's antenna arrangement of one record's raw (30, Nrx, Ntx) CSI, transcribed per record.

    Where its perm would index past antenna Nrx (MATLAB widens the matrix or fails) the decoder
    documents that it keeps the chains in order; that is what this returns too.
    """
    nrx = raw.shape[1]
    if nrx == 1:
        return raw
    perm = list(perm)
    if sum(perm) != (1, 3, 6)[nrx - 1]:
        if nrx == 2:
            perm[:2] = [1, 2] if perm[1] >= perm[0] else [2, 1]
        elif perm.count(1) == 3:
            perm = [1, 2, 3]
        else:
            perm[2] = 6 - perm[0] - perm[1]
    if not all(1 <= t <= nrx for t in perm[:nrx]):
        return raw
    out = raw.copy()
    for chain in range(nrx):
        out[:, perm[chain] - 1] = raw[:, chain]
    return out


def test_every_antenna_sel_is_arranged_as_read_bf_file_does():
    rng = np.random.default_rng(3)
    bfee, expected = [], []
    for nrx in (1, 2, 3):
        for ntx in (1, 2):
            raw = rng.integers(-128, 128, (30, nrx, ntx)) + 1j * rng.integers(-128, 128, (30, nrx, ntx))
            record = bytearray(encode_record(RecordHeader(1, 2, (40, 41, 42), -90, 30, IDENTITY_SEL, 0x4101), raw))
            for sel in range(64):
                record[1 + ANTENNA_SEL_OFFSET] = sel
                bfee.append(bytes(record))
                perm = [((sel >> (2 * k)) & 3) + 1 for k in range(3)]
                expected.append(matlab_arrangement(raw, perm))
    out = decode_bfee(bfee, scaled=False)
    assert len(out) == len(bfee) and out.csi.shape == (len(bfee), 30, 3, 2)
    for i, want in enumerate(expected):
        np.testing.assert_array_equal(out.csi[i, :, : want.shape[1], : want.shape[2]], want, err_msg=str(i))


def test_scaling_of_unusual_headers_follows_get_scaled_csi():
    csi = np.full((30, 2, 1), 3 + 4j)
    quiet = RecordHeader(0, 0, (0, 0, 0), -127, 10, IDENTITY_SEL, 0)
    loud = RecordHeader(0, 0, (50, 0, 60), -95, 20, IDENTITY_SEL, 0)
    out = decode_bfee([encode_record(quiet, csi), encode_record(loud, csi)])
    assert not out.csi[0].any()  # no RSSI: no signal power
    rss_dbm = 10 * np.log10(10**5 + 10**6) - 44 - 20  # rssi_b = 0 is left out
    csi_pwr = 30 * 2 * abs(3 + 4j) ** 2
    scale = 10 ** (rss_dbm / 10) / (csi_pwr / 30)
    factor = np.sqrt(scale / (10 ** (-95 / 10) + scale * 2 * 1))  # thermal + quantization noise
    np.testing.assert_allclose(out.csi[1, :, :2, 0], csi[:, :, 0] * factor, rtol=1e-12)


# ---------------------------------------------------------------------------------------------
# Whole files, record batches and streams agree


def test_decode_bfee_judges_each_input_on_its_own(small):
    whole = decode_log(small)
    bodies = [r[2:] for r in records_of(small)]
    batch = decode_bfee(bodies)
    for name in FIELDS[:-1]:
        np.testing.assert_array_equal(getattr(batch, name), getattr(whole, name), err_msg=name)
    assert batch.offset.tolist() == list(range(29))
    split, counts = split_records(small)
    assert split == bodies and (counts.n_skipped, counts.n_corrupt, counts.n_garbage_bytes) == (0, 0, 0)

    bad_len = bytearray(bodies[2])
    struct.pack_into("<H", bad_len, 1 + 16, 100)
    damaged = [
        b"",
        b"\xc1abc",
        bodies[0],
        bodies[1][:50],
        bodies[1] + b"\x00",
        bytes(bad_len),
        b"\xbb",
        bodies[3],
        bodies[4] * 400,
        b"\x00" * 70_000,
        bodies[5],
    ]
    out = decode_bfee(damaged, scaled=False)
    assert out.offset.tolist() == [2, 7, 10]
    assert out.bfee_count.tolist() == decode_log(small, scaled=False).bfee_count[[0, 3, 5]].tolist()
    assert (out.n_skipped, out.n_corrupt) == (2, 6)
    empty = decode_bfee([])
    assert len(empty) == 0 and empty.csi.shape == (0, 30, 0, 0)


@pytest.mark.slow
def test_streaming_equals_whole_file_at_every_split_point(small):
    whole = decode_log(small)
    for cut in range(len(small) + 1):
        assert_same(streamed(small, [cut]), whole)


@pytest.mark.slow
def test_streaming_equals_whole_file_at_random_split_points(sample):
    rng = np.random.default_rng(2015)
    whole = decode_log(sample, scaled=False)
    for cut in rng.integers(0, len(sample) + 1, 2000):
        assert_same(streamed(sample, [int(cut)], scaled=False), whole)
    assert_same(streamed(sample, rng.integers(0, len(sample) + 1, 300).tolist()), decode_log(sample))


def test_undecoded_stream_records_equal_split_records(sample):
    dec = StreamDecoder()
    got = [r for start in range(0, len(sample), 1000) for r in dec.records(sample[start : start + 1000])]
    assert got + dec.records(b"", final=True) == split_records(sample)[0]


# ---------------------------------------------------------------------------------------------
# Damaged files (built in tmp_path from the real ones)


def test_zero_length_and_missing_files(tmp_path):
    empty = tmp_path / "empty.dat"
    empty.write_bytes(b"")
    nothing = read_dat(empty)
    assert len(nothing) == 0 and (nothing.n_skipped, nothing.n_corrupt, nothing.n_garbage_bytes) == (0, 0, 0)
    assert nothing.csi.shape == (0, 30, 0, 0) and nothing.rssi.shape == nothing.perm.shape == (0, 3)
    assert nothing.timestamp_low.dtype == np.uint32 and nothing.csi.dtype == np.complex128
    with pytest.raises(FileNotFoundError):
        read_dat(tmp_path / "missing.dat")


def test_truncated_files(tmp_path, small):
    whole = decode_log(small)
    ends = np.cumsum([len(r) for r in records_of(small)])
    first = int(ends[0])
    for cut in (1, 2, 3, 22, 23, 50, first - 1, first + 22, first + 23, len(small) // 2, len(small) - 1):
        path = tmp_path / f"cut{cut}.dat"
        path.write_bytes(small[:cut])
        part = read_dat(path)
        complete = int(np.searchsorted(ends, cut, side="right"))
        left = cut - (int(ends[complete - 1]) if complete else 0)
        assert part.bfee_count.tolist() == whole.bfee_count[:complete].tolist(), cut
        assert (part.n_corrupt, part.n_garbage_bytes) == ((1, 0) if left >= 23 else (0, left)), cut


def test_a_record_cut_short_inside_a_file_loses_no_other(tmp_path, small):
    recs = records_of(small)
    whole = decode_log(small).bfee_count.tolist()
    for keep in (5, 30, 100, len(recs[3]) - 23, len(recs[3]) - 22, len(recs[3]) - 1):
        path = tmp_path / f"short{keep}.dat"
        path.write_bytes(b"".join(recs[:3]) + recs[3][:keep] + b"".join(recs[4:]))
        out = read_dat(path)
        # the next record's header lies inside the cut one or overlaps its claimed end: it is refused
        assert out.bfee_count.tolist() == whole[:3] + whole[4:], keep
        assert out.n_corrupt == (1 if keep >= 23 else 0), keep
        assert_same(streamed(path.read_bytes(), [len(b"".join(recs[:3])) + keep // 2]), out)


def test_other_codes_are_skipped_and_counted(tmp_path, small):
    recs = records_of(small)
    path = tmp_path / "with_c1.dat"
    path.write_bytes(
        other_record(b"frame!") + b"".join(recs[:5]) + other_record(b"x" * 300) + b"".join(recs[5:]) + other_record(b"")
    )
    out = read_dat(path)
    assert_same(out, streamed(path.read_bytes(), [7, 500, 2000]))
    assert out.bfee_count.tolist() == decode_log(small).bfee_count.tolist()
    assert (out.n_skipped, out.n_corrupt, out.n_garbage_bytes) == (3, 0, 0)


def test_a_len_that_disagrees_is_corrupt_not_decoded(tmp_path, small):
    recs = [bytearray(r) for r in records_of(small)]
    bad = recs[3]
    struct.pack_into("<H", bad, 2 + 1 + 16, 100)  # len no longer matches Nrx/Ntx...
    struct.pack_into(">H", bad, 0, 1 + 20 + 100)  # ...though the framing is consistent
    del bad[2 + 1 + 20 + 100 :]
    path = tmp_path / "bad_len.dat"
    path.write_bytes(b"".join(bytes(r) for r in recs))
    out = read_dat(path)
    assert out.bfee_count.tolist() == [b for i, b in enumerate(decode_log(small).bfee_count) if i != 3]
    assert (out.n_corrupt, out.n_garbage_bytes) == (1, 0)


@pytest.mark.parametrize("flip", [0x40, 0x01, 0x80])
def test_a_flipped_length_byte_loses_only_that_record(tmp_path, small, flip):
    recs = [bytearray(r) for r in records_of(small)]
    recs[10][0 if flip != 0x01 else 1] ^= flip
    path = tmp_path / "flipped.dat"
    path.write_bytes(b"".join(bytes(r) for r in recs))
    out = read_dat(path)
    assert out.bfee_count.tolist() == [b for i, b in enumerate(decode_log(small).bfee_count) if i != 10]
    assert out.n_garbage_bytes == len(recs[10])


def test_garbage_between_records_is_skipped(tmp_path, small):
    rng = np.random.default_rng(7)
    recs = records_of(small)
    junk = [rng.integers(0, 256, int(rng.integers(1, 300)), dtype=np.uint8).tobytes() for _ in recs]
    path = tmp_path / "garbage.dat"
    path.write_bytes(b"".join(j + r for j, r in zip(junk, recs, strict=True)))
    out = read_dat(path)
    assert out.bfee_count.tolist() == decode_log(small).bfee_count.tolist()
    assert out.n_garbage_bytes + out.n_skipped > 0
    data = path.read_bytes()
    assert_same(streamed(data, rng.integers(0, len(data), 40).tolist()), out)


def cut_end(recs: list[bytes], i: int, k: int) -> bytes:
    """The log of `recs` with the last k bytes of record i lost (its length prefix unchanged)."""
    return b"".join(recs[:i]) + recs[i][:-k] + b"".join(recs[i + 1 :])


@pytest.mark.parametrize("i", [0, 1, 270, 538, 539])
@pytest.mark.parametrize("k", [1, 5, 22, 23, 40])
def test_a_record_cut_short_is_corrupt_and_alters_no_other(sample, i, k):
    """Issue 13 item 8: a record cut short by fewer bytes than a header (k < 23) was decoded with
    the next record's first k bytes as its tail, plausible but wrong, and counted valid."""
    intact, recs = decode_log(sample, scaled=False), records_of(sample)
    data = cut_end(recs, i, k)
    out = decode_log(data, scaled=False)
    assert len(out) == 539 and (out.n_skipped, out.n_corrupt, out.n_garbage_bytes) == (0, 1, 0)
    kept = np.array([j for j in range(540) if j != i])
    for name in FIELDS[:-1]:
        np.testing.assert_array_equal(getattr(out, name), getattr(intact, name)[kept], err_msg=name)
    np.testing.assert_array_equal(out.offset, intact.offset[kept] - np.where(kept > i, k, 0))
    end = int(intact.offset[i]) + len(recs[i]) - k
    assert_same(streamed(data, [end - 1, end + 10]), decode_log(data))


@pytest.mark.parametrize("k", [1, 22, 23, 40])
def test_a_cut_short_record_next_to_a_0xc1_record_is_told_too(k):
    """LGTM's real logs interleave 0xC1 records with the beamforming ones: a short record before
    one is told by the 0xC1 record ending where the next beamforming record starts."""
    log = min((reference_data() / "csi" / "lgtm").glob("*.dat"))
    data = log.read_bytes()
    recs, intact = records_of(data), decode_log(data, scaled=False)
    codes = [r[2] for r in recs]
    bfee, frame = codes.index(0xBB, 100), codes.index(0xC1, 100)
    assert (len(intact), codes.count(0xC1)) == (1025, 1025)
    out = decode_log(cut_end(recs, bfee, k), scaled=False)
    assert (len(out), out.n_skipped, out.n_corrupt, out.n_garbage_bytes) == (1024, 1025, 1, 0)
    assert out.bfee_count.tolist() == np.delete(intact.bfee_count, codes[:bfee].count(0xBB)).tolist()
    np.testing.assert_array_equal(out.csi, np.delete(intact.csi, codes[:bfee].count(0xBB), axis=0))
    out = decode_log(cut_end(recs, frame, k), scaled=False)
    assert (len(out), out.n_skipped, out.n_corrupt, out.n_garbage_bytes) == (1025, 1024, 0, len(recs[frame]) - k)
    np.testing.assert_array_equal(out.csi, intact.csi)


def test_a_real_log_interleaving_0xc1_records_frames_as_one_read_record_by_record():
    """LGTM's log alternates 0xC1 and 0xBB records: the whole file (its runs taken at once, each
    0xC1 record bridged) frames as a naive walk does, and as a stream cut at random points does
    (each cut sends the records around it through the record-by-record path)."""
    data = min((reference_data() / "csi" / "lgtm").glob("*.dat")).read_bytes()
    recs = records_of(data)
    starts = np.cumsum([0] + [len(r) for r in recs[:-1]])
    whole = decode_log(data)
    assert whole.offset.tolist() == [int(a) for a, r in zip(starts, recs, strict=True) if r[2] == 0xBB]
    assert (whole.n_skipped, whole.n_corrupt, whole.n_garbage_bytes) == (1025, 0, 0)
    rng = np.random.default_rng(2016)
    for _ in range(20):
        assert_same(streamed(data, rng.integers(0, len(data) + 1, 50).tolist()), whole)


def test_what_framing_cannot_tell_is_decoded_as_it_is(sample):
    """The documented limit: a record cut short and followed by bytes that start no provable record
    keeps those bytes as its tail. It counts as valid; only its last subcarriers are wrong."""
    recs, intact = records_of(sample), decode_log(sample, scaled=False)
    k, junk = 22, b"\xff" * 30
    out = decode_log(b"".join(recs[:100]) + recs[100][:-k] + junk + b"".join(recs[101:]), scaled=False)
    assert len(out) == 540 and (out.n_skipped, out.n_corrupt, out.n_garbage_bytes) == (0, 0, len(junk) - k)
    wrong = int((out.csi[100] != intact.csi[100]).any(axis=(1, 2)).sum())
    assert wrong in (1, 2) and (out.csi[100, : 30 - wrong] == intact.csi[100, : 30 - wrong]).all()
    np.testing.assert_array_equal(np.delete(out.csi, 100, axis=0), np.delete(intact.csi, 100, axis=0))


# ---------------------------------------------------------------------------------------------
# Generated damage


@settings(max_examples=200, deadline=None)
@given(data=st.binary(max_size=3000), cuts=st.lists(st.integers(0, 10_000), max_size=4))
def test_arbitrary_bytes_never_raise_and_stream_as_whole(data, cuts):
    try:
        whole = decode_log(data)
        assert_same(streamed(data, [c % (len(data) + 1) for c in cuts]), whole)
        decode_bfee([data, data[:1], data[1:]])
    except CsiFormatError:
        pass


def junk_piece(recs: list[bytes]) -> st.SearchStrategy[bytes]:
    """Damage found in real logs: random bytes, a record cut short, a record of another code."""
    cut_record = st.tuples(st.sampled_from(recs), st.integers(0, 600)).map(lambda rc: rc[0][: rc[1]])
    return st.one_of(st.binary(max_size=300), cut_record, st.binary(max_size=40).map(other_record))


@settings(max_examples=150, deadline=None)
@given(data=st.data())
def test_valid_records_after_damage_are_never_lost(small, data):
    recs = records_of(small)
    junk = data.draw(st.lists(st.lists(junk_piece(recs), max_size=3).map(b"".join), min_size=29, max_size=29))
    damaged = b"".join(j + r for j, r in zip(junk, recs, strict=True))
    out = decode_log(damaged)
    found = iter(out.bfee_count.tolist())
    assert all(b in found for b in decode_log(small).bfee_count.tolist()), "a valid record after damage was lost"
    cuts = data.draw(st.lists(st.integers(0, len(damaged)), max_size=3))
    assert_same(streamed(damaged, cuts), out)


def rows(records: CsiRecords) -> list[tuple[int, int, bytes]]:
    """Each decoded record as (timestamp_low, bfee_count, raw CSI bytes of its own shape)."""
    n, t = records.nrx, records.ntx
    return [
        (int(records.timestamp_low[j]), int(records.bfee_count[j]), records.csi[j, :, : n[j], : t[j]].tobytes())
        for j in range(len(records))
    ]


@settings(max_examples=150, deadline=None)
@given(data=st.data())
def test_a_cut_record_never_adds_or_alters_a_record(small, sample, data):
    """Bytes lost from one record of a real log (its end, its middle, its head): no record is made
    up or altered, and no other record is lost, whole or streamed."""
    log = data.draw(st.sampled_from([small, sample]), label="log")
    recs = records_of(log)
    i = data.draw(st.integers(0, len(recs) - 1), label="record")
    size = len(recs[i])
    b = data.draw(st.one_of(st.just(size), st.integers(1, size)), label="cut to")
    a = data.draw(st.integers(max(0, b - 60), b - 1) | st.integers(0, b - 1), label="cut from")
    damaged = b"".join(recs[:i]) + recs[i][:a] + recs[i][b:] + b"".join(recs[i + 1 :])
    out = decode_log(damaged, scaled=False)
    original = iter(rows(decode_log(log, scaled=False)))
    assert len(out) <= len(recs) and all(row in original for row in rows(out)), "a record was made up or altered"
    assert len(out) >= len(recs) - 1, "another record was lost"
    cuts = data.draw(st.lists(st.integers(0, len(damaged)), max_size=3), label="stream cuts")
    assert_same(streamed(damaged, cuts, scaled=False), out)


# ---------------------------------------------------------------------------------------------
# Encoding


def test_encoding_is_the_exact_inverse(small):
    raw = decode_log(small, scaled=False)
    for i, record in enumerate(records_of(small)):
        n, t = int(raw.nrx[i]), int(raw.ntx[i])
        rssi_a, rssi_b, rssi_c = (int(v) for v in raw.rssi[i])
        head = RecordHeader(
            int(raw.timestamp_low[i]),
            int(raw.bfee_count[i]),
            (rssi_a, rssi_b, rssi_c),
            int(raw.noise[i]),
            int(raw.agc[i]),
            int(raw.antenna_sel[i]),
            int(raw.rate[i]),
        )
        assert encode_record(head, raw.csi[i, :, :n, :t]) == record[2:]
    rng = np.random.default_rng(5)
    for sel in (0b100100, 0b011000, 0b001001, 0b010010, 0b000110, 0b100001):
        for n, t in ((3, 1), (3, 2), (2, 2), (1, 3)):
            csi = rng.integers(-128, 128, (30, n, t)) + 1j * rng.integers(-128, 128, (30, n, t))
            head = RecordHeader(7, 9, (30, 31, 32), -92, 40, sel, 0x1101)
            back = decode_bfee([encode_record(head, csi)], scaled=False)
            np.testing.assert_array_equal(back.csi[0], csi)
    zeros = RecordHeader(0, 0, (0, 0, 0), 0, 0, IDENTITY_SEL, 0)
    with pytest.raises(CsiFormatError):
        encode_record(zeros, np.full((30, 3, 1), 200.0))
    with pytest.raises(CsiFormatError):
        encode_record(zeros, np.zeros((30, 4, 1)))
    with pytest.raises(CsiFormatError):
        encode_record(RecordHeader(0, 0, (0, 0, 0), 0, 0, 0b010101, 0), np.zeros((30, 3, 1)))
