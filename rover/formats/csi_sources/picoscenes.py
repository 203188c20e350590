"""PicoScenes `.csi` files (its IWL5300, QCA9300, AX200/AX210 and SDR front ends), read through
csiread's experimental PicoScenes reader.

A file is a sequence of frames, each a 4-byte length, the magic 0x20150315, a version and its
segments (RxSBasic: device, timestamp, frequencies, bandwidth, noise floor and RSSI per chain;
CSI: the tones' indices and values per receive chain and transmit stream; the 802.11 header:
addresses and sequence). Frames of other shapes than the commonest (the IWL5300 reports as many
chains as it heard) are counted, not kept."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from rover.errors import BadInput
from rover.formats.csi_sources.frames import CsiFrames
from rover.formats.csi_sources.walk import record_starts
from rover.formats.wifi import SUBCARRIER_SPACING_HZ

MAGIC = 0x20150315
LENGTH = struct.Struct("<I")
MPDU_BYTES = 1522
DEVICES = {0x5300: "IWL5300", 0x9300: "QCA9300", 0x2000: "AX200", 0x2100: "AX210"}


def looks_like(head: bytes) -> bool:
    """Whether these first bytes start a PicoScenes file: a frame length, then the magic."""
    return len(head) >= 8 and struct.unpack_from("<I", head, 4)[0] == MAGIC


def read(path: Path) -> CsiFrames:
    """The file's frames of its commonest CSI shape."""
    import csiread

    data = path.read_bytes()
    if not looks_like(data[:8]):
        raise BadInput(f"{path}: not a PicoScenes file (no magic 0x{MAGIC:08x} after its first frame's length)")
    frames = len(record_starts(path, data, 0, LENGTH, 0, "frame"))
    # a first pass reads the headers only, so that the CSI array is allocated at the file's own size
    headers = csiread.Picoscenes(str(path), {"CSI": [0, 0, 0], "MPDU": 0}, if_report=False)
    headers.read()
    if int(headers.count) != frames:
        raise BadInput(f"{path}: csiread read {headers.count} of its {frames} frames")
    info = headers.raw["CSI"]["Info"]
    shape = np.stack([info["NumTones"], info["NumRx"], info["NumTx"]], axis=1).astype(np.int64)
    usable = (shape > 0).all(axis=1) & (info["SubcarrierBandwidth"] == SUBCARRIER_SPACING_HZ)
    if not usable.any():
        raise BadInput(
            f"{path}: no frame with CSI of 312.5 kHz subcarriers (a CSI segment csiread reads; HE frames' "
            "78.125 kHz subcarriers are not supported yet)"
        )
    kinds, counts = np.unique(shape[usable], axis=0, return_counts=True)
    k, n, t = (int(v) for v in kinds[np.lexsort((kinds[:, 1], counts))[-1]])  # the commonest; more chains on a tie
    keep = np.flatnonzero(usable & (shape == (k, n, t)).all(axis=1))
    pico = csiread.Picoscenes(str(path), {"CSI": [k, n, t], "MPDU": MPDU_BYTES}, if_report=False)
    pico.read()
    raw = pico.raw
    info, basic, mac_header = raw["CSI"]["Info"], raw["RxSBasic"], raw["StandardHeader"]
    device = DEVICES.get(int(info["DeviceType"][keep[0]]), f"device 0x{int(info['DeviceType'][keep[0]]):04x}")
    rssi = np.stack([basic["RSSI1"], basic["RSSI2"], basic["RSSI3"]], axis=1)[keep].astype(np.float64)
    rssi = np.pad(rssi, ((0, 0), (0, max(n - 3, 0))), constant_values=np.nan)[:, :n]
    return CsiFrames(
        source=f"picoscenes {device}",
        csi=np.asarray(raw["CSI"]["CSI"][keep, :k, :n, :t], dtype=np.complex128),
        subcarriers=np.asarray(raw["CSI"]["SubcarrierIndex"][keep[0], :k], dtype=np.int64),
        bandwidth_hz=float(info["CBW"][keep[0]]) * 1e6,
        centre_freq_hz=basic["CenterFreq"][keep].astype(np.float64) * 1e6,
        timestamp_ns=basic["Timestamp"][keep].astype(np.int64) * 1000,
        rssi_db=rssi,
        noise_dbm=basic["NoiseFloor"][keep].astype(np.float64),
        mac=np.asarray(mac_header["Addr2"][keep], dtype=np.uint8),
        sequence=mac_header["Sequence"][keep].astype(np.int64),
        dropped={
            why: count
            for why, count in (
                ("frames without CSI, or of HE's 78.125 kHz subcarriers", int((~usable).sum())),
                (f"frames of another CSI shape than the commonest ({k}x{n}x{t})", int(usable.sum()) - len(keep)),
            )
            if count
        },
    )
