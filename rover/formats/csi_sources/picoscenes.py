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

MAGIC = 0x20150315
LENGTH = struct.Struct("<I")
MAX_SHAPE = (2048, 8, 4)
"""the largest CSI (tones, receive chains, transmit streams) read: 160 MHz of an AX210 fits"""
MPDU_BYTES = 1522
DEVICES = {0x5300: "IWL5300", 0x9300: "QCA9300", 0x0200: "AX200", 0x0210: "AX210", 0x1234: "USRP"}


def looks_like(head: bytes) -> bool:
    """Whether these first bytes start a PicoScenes file: a frame length, then the magic."""
    return len(head) >= 8 and struct.unpack_from("<I", head, 4)[0] == MAGIC


def _frame_count(path: Path, data: bytes) -> int:
    """The frames' count from their length prefixes; BadInput if the last runs past the end. A walk
    over the frames' lengths, once per file."""
    at, count = 0, 0
    while at + LENGTH.size <= len(data):
        (length,) = LENGTH.unpack_from(data, at)
        if at + LENGTH.size + length > len(data):
            break
        at += LENGTH.size + length
        count += 1
    if at != len(data):
        raise BadInput(
            f"{path}: truncated: frame {count + 1} starts at byte {at:,} and the file ends "
            f"{len(data) - at:,} bytes into it"
        )
    return count


def read(path: Path) -> CsiFrames:
    """The file's frames of its commonest CSI shape."""
    import csiread

    data = path.read_bytes()
    if not looks_like(data[:8]):
        raise BadInput(f"{path}: not a PicoScenes file (no magic 0x{MAGIC:08x} after its first frame's length)")
    frames = _frame_count(path, data)
    tones, chains, streams = MAX_SHAPE
    pico = csiread.Picoscenes(str(path), {"CSI": [tones, chains, streams], "MPDU": MPDU_BYTES}, if_report=False)
    pico.read()
    if int(pico.count) != frames:
        raise BadInput(f"{path}: csiread read {pico.count} of its {frames} frames")
    raw = pico.raw
    info, basic, mac_header = raw["CSI"]["Info"], raw["RxSBasic"], raw["StandardHeader"]
    shape = np.stack([info["NumTones"], info["NumRx"], info["NumTx"]], axis=1).astype(np.int64)
    kinds, counts = np.unique(shape, axis=0, return_counts=True)
    k, n, t = (int(v) for v in kinds[np.lexsort((kinds[:, 1], counts))[-1]])  # the commonest; more chains on a tie
    keep = np.flatnonzero((shape == (k, n, t)).all(axis=1))
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
        dropped={f"frames of another CSI shape than the commonest ({k}x{n}x{t})": frames - len(keep)}
        if frames > len(keep)
        else {},
    )
