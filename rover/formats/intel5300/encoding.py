"""Encoding beamforming records, the exact inverse of decoding. Only the simulator and tests write
records, so the encoder lives apart from the decoder and shares with it only the format (`records`).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from rover.formats.intel5300.records import (
    BFEE_CODE,
    SUBCARRIERS,
    CsiFormatError,
    _antenna_sources,
    _value_bits,
    antenna_perm,
    payload_bytes,
)


@dataclass(frozen=True)
class RecordHeader:
    """Header fields of one beamforming record to encode (antenna_sel gives the permutation)."""

    timestamp_low: int
    bfee_count: int
    rssi: tuple[int, int, int]
    noise: int
    agc: int
    antenna_sel: int
    rate: int


def encode_record(head: RecordHeader, csi: np.ndarray) -> bytes:
    """One record (code byte + notification) that decodes to `csi`.

    `csi` is (30, Nrx, Ntx) of int8-valued complex numbers, antennas after the permutation, so
    the chains are written in the order the decoder reads them back. Raises CsiFormatError for a
    shape the 5300 cannot report, values outside int8, or an antenna_sel that maps two chains to
    one antenna (not invertible).
    """
    csi = np.asarray(csi)
    if csi.ndim != 3 or csi.shape[0] != SUBCARRIERS or not (1 <= csi.shape[1] <= 3 and 1 <= csi.shape[2] <= 3):
        raise CsiFormatError(f"CSI must be (30, Nrx, Ntx) with 1..3 chains and streams, not {csi.shape}")
    _, nrx, ntx = csi.shape
    values = np.rint(np.stack([csi.real, csi.imag], axis=-1)).astype(np.int64)
    if values.min() < -128 or values.max() > 127:
        raise CsiFormatError("CSI values must fit in int8")
    sources = _antenna_sources(antenna_perm([head.antenna_sel]), np.array([nrx]))[0, :nrx]
    if sorted(sources.tolist()) != list(range(nrx)):
        raise CsiFormatError(f"antenna_sel {head.antenna_sel:#x} maps two chains to one antenna for Nrx={nrx}")
    bit = _value_bits(nrx, ntx, tuple(sources.tolist()))[:, None] + np.arange(8)
    length = payload_bytes(nrx, ntx)
    bits = np.zeros(length * 8, dtype=np.uint8)
    bits[bit.ravel()] = ((values.ravel().astype(np.uint8)[:, None] >> np.arange(8, dtype=np.uint8)) & 1).ravel()
    payload = np.packbits(bits, bitorder="little").tobytes()
    header = struct.pack(
        "<IHHBBBBBbBBHH",
        head.timestamp_low & 0xFFFFFFFF,
        head.bfee_count & 0xFFFF,
        0,
        nrx,
        ntx,
        *head.rssi,
        head.noise,
        head.agc,
        head.antenna_sel,
        length,
        head.rate,
    )
    return bytes([BFEE_CODE]) + header + payload
