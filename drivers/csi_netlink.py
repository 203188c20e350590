"""`csi_netlink`: live CSI from the Intel 5300 CSI Tool's netlink connector, as its `log_to_file` reads it.

The patched iwlwifi driver multicasts each beamforming record on the connector group
CN_IDX_IWLAGN; every datagram is a `nlmsghdr`, a `cn_msg` and the record (code byte and
notification). Frames are stamped with the host's receive time. The raw log can be written
alongside, in the tool's own format, for replay later. Linux only, and it needs root.
"""

from __future__ import annotations

import logging
import os
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from rover.errors import BadInput
from rover.messages import header, make
from rover.operator import COMPLETE, Emit, Out, RunOutcome, Source, Watermark
from rover.pipeline.params import Checked, NonNegativeInt

log = logging.getLogger("rover.csi_netlink")

NETLINK_CONNECTOR = 11
SOL_NETLINK = 270
NETLINK_ADD_MEMBERSHIP = 1
CN_NETLINK_USERS = 11
CN_IDX_IWLAGN = CN_NETLINK_USERS + 0xF
CN_VAL_IWLAGN = 0x1
NLMSGHDR = struct.Struct("=IHHII")
CN_MSG = struct.Struct("=IIIIHH")
MAX_DATAGRAM_BYTES = 4096
POLL_S = 0.1


class NetlinkFormatError(ValueError):
    """A datagram that is not a CSI Tool connector message."""


def parse_datagram(datagram: bytes) -> bytes:
    """The record (code byte + notification) carried by one connector datagram."""
    if len(datagram) < NLMSGHDR.size + CN_MSG.size:
        raise NetlinkFormatError(f"datagram of {len(datagram)} bytes is shorter than its headers")
    nl_len, _type, _flags, _seq, _pid = NLMSGHDR.unpack_from(datagram)
    idx, val, _cseq, _ack, length, _cflags = CN_MSG.unpack_from(datagram, NLMSGHDR.size)
    if (idx, val) != (CN_IDX_IWLAGN, CN_VAL_IWLAGN):
        raise NetlinkFormatError(f"connector id {idx}:{val} is not the CSI Tool's {CN_IDX_IWLAGN}:{CN_VAL_IWLAGN}")
    start = NLMSGHDR.size + CN_MSG.size
    if nl_len > len(datagram) or start + length > len(datagram) or length == 0:
        raise NetlinkFormatError(f"cn_msg length {length} overruns the {len(datagram)}-byte datagram")
    return datagram[start : start + length]


def pack_datagram(record: bytes, seq: int = 0) -> bytes:
    """A connector datagram carrying `record`, as the kernel sends it (used by tests and replays)."""
    body = CN_MSG.pack(CN_IDX_IWLAGN, CN_VAL_IWLAGN, seq, 0, len(record), 0) + record
    return NLMSGHDR.pack(NLMSGHDR.size + len(body), 0, 0, seq, 0) + body


def open_connector() -> socket.socket:
    """Subscribe to the CSI Tool's connector group, as log_to_file does."""
    if not hasattr(socket, "AF_NETLINK"):
        raise BadInput("csi_netlink: the CSI Tool's netlink socket exists only on Linux")
    try:
        sock = socket.socket(socket.AF_NETLINK, socket.SOCK_DGRAM, NETLINK_CONNECTOR)
        sock.bind((os.getpid(), CN_IDX_IWLAGN))
        sock.setsockopt(SOL_NETLINK, NETLINK_ADD_MEMBERSHIP, CN_IDX_IWLAGN)
    except OSError as exc:
        raise BadInput(
            f"csi_netlink: cannot subscribe to the CSI Tool's netlink connector (group "
            f"{CN_IDX_IWLAGN}; needs root and the patched iwlwifi driver): {exc.strerror or exc}"
        ) from None
    return sock


@dataclass(frozen=True)
class NetlinkParams(Checked):
    channel: NonNegativeInt = 0
    """The channel the NIC is tuned to, or 0 when `channel_hop` announces the hops."""
    log: str = ""
    """Also write the raw records to this file, in the CSI Tool's log format."""


class CsiNetlink(Source):
    """Publishes every CSI record the NIC reports, stamped with the receive time."""

    live = True

    outputs = {"csi": Out("rover_msgs/msg/CsiFrame")}
    Params = NetlinkParams

    def __init__(self, params: NetlinkParams | None = None, connect: Callable[[], socket.socket] = open_connector):
        super().__init__(params)
        self.sock = connect()
        self.sock.settimeout(POLL_S)
        self._log = None
        if self.params.log:
            try:
                self._log = open(self.params.log, "wb")  # noqa: SIM115 - open until close()
            except OSError as exc:
                self.sock.close()
                raise BadInput(f"{self.params.log}: cannot write: {exc.strerror or exc}") from None

    def run(self, stop: threading.Event) -> Iterator[Emit | Watermark]:
        while not stop.is_set():
            try:
                datagram = self.sock.recv(MAX_DATAGRAM_BYTES)
            except TimeoutError:
                yield Watermark(time.time_ns())
                continue
            except OSError as exc:
                raise BadInput(f"csi_netlink: reading the connector failed: {exc.strerror or exc}") from None
            if not datagram:
                return
            now = time.time_ns()
            try:
                record = parse_datagram(datagram)
            except NetlinkFormatError as exc:
                self.drop("datagrams that are not CSI Tool records")
                log.debug("csi_netlink: dropped a datagram: %s", exc)
                continue
            if self._log is not None:
                self._log.write(struct.pack(">H", len(record)) + record)
            yield Emit(
                "csi",
                make(
                    "rover_msgs/msg/CsiFrame",
                    header=header(now, "base_link"),
                    channel=self.params.channel,
                    bfee=np.frombuffer(record, dtype=np.uint8),
                ),
            )

    def close(self, outcome: RunOutcome = COMPLETE) -> None:
        self.sock.close()
        if self._log is not None:
            self._log.close()
