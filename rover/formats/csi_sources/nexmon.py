"""Nexmon CSI captures (Broadcom chips patched by nexmon_csi): a pcap of UDP frames to port 5500,
one frame per receive core and spatial stream of each packet, read through csiread and grouped
per packet here.

A frame's UDP payload: 2 magic bytes 0x1111, the RSSI (int8 dBm) and the frame control byte
(captures of 2017-2019 have four magic bytes 0x11111111 there and no RSSI), the source MAC, the
sequence number, the core and spatial stream (bits 0-2 and 3-5), the Broadcom chanspec (channel,
bandwidth and band) and the chip version, then the CSI: one 32-bit word per FFT bin, int16 pairs
on the 4339 and 43455c0, packed floating point on the 4358 and 4366c0 (which chip cannot be told
from the capture: it is given). The bins come in FFT order; here they are in increasing frequency
(fftshift), guard and DC bins included."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from rover.errors import BadInput
from rover.formats.csi_sources.frames import CsiFrames
from rover.formats.csi_sources.walk import record_starts
from rover.formats.wifi import SUBCARRIER_SPACING_HZ, channel_freq_hz

CHIPS = ("4339", "43455c0", "4358", "4366c0")
PCAP_MAGIC = {b"\xd4\xc3\xb2\xa1": "<", b"\xa1\xb2\xc3\xd4": ">", b"\x4d\x3c\xb2\xa1": "<", b"\xa1\xb2\x3c\x4d": ">"}
"""pcap's magic numbers (microsecond and nanosecond stamps, either byte order) -> byte order"""
PCAP_HEADER_BYTES = 24
RECORD_HEADER_BYTES = 16
UDP_PAYLOAD_AT = 42
"""Ethernet, IPv4 and UDP headers before the CSI frame (nexmon_csi's own framing)"""
CSI_HEADER_BYTES = 18
FRAME_HEAD_BYTES = UDP_PAYLOAD_AT + CSI_HEADER_BYTES
"""a frame's bytes before its CSI: the headers, then nexmon_csi's own"""
MAX_BINS = 256
"""FFT bins of an 80 MHz channel, the widest read"""
OLD_MAGIC = 0x11111111
BANDWIDTHS_HZ = {0x1000: 20e6, 0x1800: 40e6, 0x2000: 80e6}
"""chanspec bandwidth bits (0x3800) -> bandwidth"""


def looks_like(head: bytes) -> bool:
    """Whether these first bytes start a pcap whose first frame is a Nexmon CSI frame."""
    at = PCAP_HEADER_BYTES + RECORD_HEADER_BYTES + UDP_PAYLOAD_AT
    return head[:4] in PCAP_MAGIC and head[at : at + 2] == b"\x11\x11"


def bandwidth_hz(chanspec: int) -> float | None:
    return BANDWIDTHS_HZ.get(chanspec & 0x3800)


def read(path: Path, chip: str) -> CsiFrames:
    """The capture's packets, each the frames of one sequence number (cores x spatial streams)."""
    import csiread

    if chip not in CHIPS:
        given = f"--chip {chip} is none of them" if chip else "give --chip"
        raise BadInput(
            f"{path}: a Nexmon capture does not say which chip wrote it, and its CSI's encoding depends on it "
            f"({', '.join(CHIPS)}): {given}"
        )
    data = path.read_bytes()
    if not looks_like(data[: PCAP_HEADER_BYTES + RECORD_HEADER_BYTES + UDP_PAYLOAD_AT + 2]):
        raise BadInput(f"{path}: not a Nexmon CSI capture (a pcap whose frames start with 0x1111)")
    record = struct.Struct(PCAP_MAGIC[data[:4]] + "IIII")  # seconds, microseconds, captured, original length
    offsets = record_starts(path, data, PCAP_HEADER_BYTES, record, 2, "frame") + RECORD_HEADER_BYTES
    buf = np.frombuffer(data, np.uint8)
    payload = offsets + UDP_PAYLOAD_AT
    if len(payload) == 0 or (payload + CSI_HEADER_BYTES > len(buf)).any():
        raise BadInput(f"{path}: a frame too short for a Nexmon CSI header")
    magic = buf[payload] | (buf[payload + 1].astype(np.int64) << 8)
    if (magic != 0x1111).any():
        first = int(np.flatnonzero(magic != 0x1111)[0]) + 1
        raise BadInput(f"{path}: frame {first} is not a Nexmon CSI frame (no 0x1111): capture port 5500 only")

    def u16(at: np.ndarray) -> np.ndarray:
        value: np.ndarray = buf[at].astype(np.int64) | (buf[at + 1].astype(np.int64) << 8)
        return value

    chanspec = u16(payload + 14)
    width = bandwidth_hz(int(chanspec[0]))
    if width is None:
        raise BadInput(f"{path}: frame 1's chanspec 0x{int(chanspec[0]):04x} names no 20, 40 or 80 MHz channel")
    try:  # the chanspec's channel number is the centre's, of the frames read (the first's channel)
        centre_hz = channel_freq_hz(int(chanspec[0]) & 0xFF)
    except ValueError:
        raise BadInput(f"{path}: frame 1's chanspec 0x{int(chanspec[0]):04x} names no WiFi channel") from None
    nfft = round(width / SUBCARRIER_SPACING_HZ)
    endian = PCAP_MAGIC[data[:4]]
    caplen = buf[offsets[:, None] - 8 + np.arange(4)].copy().view(endian + "u4").ravel().astype(np.int64)
    odd = (caplen < FRAME_HEAD_BYTES) | (caplen > FRAME_HEAD_BYTES + 4 * MAX_BINS)
    if odd.any():
        at = int(np.flatnonzero(odd)[0])
        raise BadInput(f"{path}: frame {at + 1} is {int(caplen[at]):,} bytes: no Nexmon CSI frame of up to 80 MHz")
    capture = csiread.Nexmon(str(path), chip=chip, bw=int(width / 1e6), if_report=False)
    capture.read()
    if int(capture.count) != len(offsets):
        raise BadInput(f"{path}: csiread read {capture.count} of its {len(offsets)} frames")
    old = (buf[payload + 2] == 0x11) & (buf[payload + 3] == 0x11)
    rssi = np.where(old, np.nan, buf[payload + 2].astype(np.int8).astype(np.float64))
    mac = buf[payload[:, None] + 4 + np.arange(6)]
    seq = u16(payload + 10)
    conf = buf[payload + 12]
    core, stream = conf & 0x7, (conf >> 3) & 0x7
    whole = caplen == FRAME_HEAD_BYTES + 4 * nfft
    used = np.flatnonzero((chanspec == chanspec[0]) & whole)
    if len(used) == 0:
        raise BadInput(f"{path}: no whole CSI frame of its first frame's channel (captured with a short snap length?)")
    # a packet: consecutive frames (of the first's channel) of one sequence number and source
    seq_u, mac_u = seq[used], mac[used]
    starts = np.concatenate([[True], (seq_u[1:] != seq_u[:-1]) | (mac_u[1:] != mac_u[:-1]).any(axis=1)])
    packet = np.cumsum(starts) - 1
    packets = int(packet[-1]) + 1
    chains, streams = int(core[used].max()) + 1, int(stream[used].max()) + 1
    slot = packet * 64 + core[used] * 8 + stream[used]
    repeated = len(slot) - len(np.unique(slot))
    csi = np.full((packets, nfft, chains, streams), np.nan + 0j)
    csi[packet, :, core[used], stream[used]] = capture.csi[used]
    rssi_chains = np.full((packets, chains), np.nan)
    rssi_chains[packet, core[used]] = rssi[used]
    keep = np.flatnonzero(np.isfinite(csi).all(axis=(1, 2, 3)))
    k = used[np.flatnonzero(starts)[keep]]
    dropped = {
        "frames of another channel than the first's": int((chanspec != chanspec[0]).sum()),
        f"frames cut short (not the {FRAME_HEAD_BYTES + 4 * nfft:,} bytes of a whole frame)": int(
            ((chanspec == chanspec[0]) & ~whole).sum()
        ),
        "frames repeating their packet's core and stream (a retransmission: the last kept)": repeated,
        f"packets missing the frame of some core or stream ({chains}x{streams})": packets - len(keep),
    }
    stamps = capture.sec.astype(np.int64) * 10**9 + capture.usec.astype(np.int64) * (1 if capture.nano else 1000)
    return CsiFrames(
        source=f"nexmon {chip}",
        csi=np.fft.fftshift(csi[keep], axes=1),
        subcarriers=np.arange(-nfft // 2, nfft // 2),
        bandwidth_hz=width,
        centre_freq_hz=np.full(len(k), centre_hz),
        timestamp_ns=stamps[k],
        rssi_db=rssi_chains[keep],
        noise_dbm=np.full(len(keep), np.nan),
        mac=mac[k].astype(np.uint8),
        sequence=seq[k],
        dropped={why: n for why, n in dropped.items() if n},
    )
