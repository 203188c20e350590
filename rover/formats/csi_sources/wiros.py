"""WiROS bags: ROS 1 or ROS 2 bags of `rf_msgs/msg/Wifi` (Nexmon CSI from a 4x4 Broadcom
BCM4366c0 router, as WiROS's CSI node records it), read as `CsiFrames`.

A message is one packet: `csi_real` and `csi_imag` hold n_sub x n_rows x n_cols values (subcarriers x
receive x transmit antennas) in Fortran order, the subcarriers fft-shifted (lowest frequency first).
As recorded by the CSI node (`n_sub` the FFT's 64/128/256 bins at 20/40/80 MHz) the chip's lower 64
bins come rotated (by -1 at 80 MHz, by j at 40 MHz: WiROS undoes it by -1 and -j); then only the
data subcarriers carry a channel estimate (DC, the pilots and the band edges do not), WiROS keeps
50/108/234 of them and its correction node republishes them (`n_sub` 50/108/234). Both layouts are
read, to the kept subcarriers. WiROS's static calibration ("compensation") is one unit phasor per
kept subcarrier and receive antenna, per router and channel, in `RX_ID-CHAN.npy` (n_sub, n_rows, 1),
multiplied into the CSI; given a file or a folder of them, it is applied to each packet by its
router and channel.

The bag's own definition of the message decodes it where the bag carries one (ROS 1 bags, MCAP);
Rover's copy (`rf_msgs/Wifi.msg`, written from the message's public field list) otherwise.
"""

from __future__ import annotations

from collections import Counter
from functools import cache
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from rover.errors import BadInput
from rover.formats.bag import MAGIC as MCAP_MAGIC
from rover.formats.csi_sources.frames import CsiFrames
from rover.formats.wifi import SUBCARRIER_SPACING_HZ, channel_freq_hz

WIFI_TYPE = "rf_msgs/msg/Wifi"
MAC_BYTES = 6
ID_BYTES = 4
"""the MAC's last bytes that make a transmitter's tag id"""
BEARING_TYPE = "rf_msgs/msg/Bearing"
ROS1_MAGIC = b"#ROSBAG V2.0"


def _kept(edge: int, dc: int, pilots: tuple[int, ...]) -> np.ndarray:
    """Subcarrier indices -edge..edge without the DC ones (|k| <= dc) and the pilots."""
    k = np.arange(-edge, edge + 1)
    return k[(np.abs(k) > dc) & ~np.isin(np.abs(k), pilots)]


KEPT_SUBCARRIERS = {
    20e6: _kept(27, 0, (7, 21)),
    40e6: _kept(58, 1, (11, 25, 53)),
    80e6: _kept(122, 1, (11, 39, 75, 103)),
}
"""the data subcarriers WiROS keeps (802.11n/ac's, without the two outermost at 20 MHz, weaker
on the router): 50, 108 and 234"""
LOWER_BINS = 64
"""the fft-shifted bins that come rotated from the chip at 40 and 80 MHz"""
LOWER_BINS_UNDO = {40e6: -1j, 80e6: -1.0}
"""what those bins are multiplied by to undo the rotation"""


@cache
def _typestore() -> Typestore:
    """ROS 2's standard types and Rover's copies of the rf_msgs messages."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    folder = resources.files("rover.formats.csi_sources").joinpath("rf_msgs")
    for name in ("Wifi", "Bearing"):
        store.register(get_types_from_msg(folder.joinpath(f"{name}.msg").read_text(), f"rf_msgs/msg/{name}"))
    return store


def looks_like_bag(path: Path) -> bool:
    """Whether the path is a ROS bag by its form: a ROS 1 bag or MCAP file, or a ROS 2 bag folder."""
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    try:
        with path.open("rb") as f:
            head = f.read(len(ROS1_MAGIC))
    except OSError:
        return False
    return head.startswith((ROS1_MAGIC, MCAP_MAGIC))


def _open(path: Path) -> AnyReader:
    reader = AnyReader([path], default_typestore=_typestore())
    try:
        reader.open()
    except Exception as exc:  # noqa: BLE001 - any failure of the library on untrusted bytes
        raise BadInput(f"{path}: cannot read as a ROS bag: {type(exc).__name__}: {exc}") from None
    return reader


def wifi_topics(path: Path) -> list[str]:
    """The bag's topics of rf_msgs/msg/Wifi (BadInput when it is no readable bag)."""
    reader = _open(path)
    try:
        return sorted({c.topic for c in reader.connections if c.msgtype == WIFI_TYPE})
    finally:
        reader.close()


def holds_wifi(path: Path) -> bool:
    """Whether the path is a ROS bag with a topic of rf_msgs/msg/Wifi."""
    if not looks_like_bag(path):
        return False
    try:
        return bool(wifi_topics(path))
    except BadInput:
        return False


DEFAULT_TOPICS = {WIFI_TYPE: "/csi", BEARING_TYPE: "/bearing"}
"""where WiROS's nodes publish each message"""


def _topic(path: Path, reader: AnyReader, topic: str | None, msgtype: str, choose: str) -> str:
    """The topic of `msgtype` to read: `topic`, else the bag's one, else WiROS's among several
    (`choose`: the option that names one)."""
    found = sorted({c.topic for c in reader.connections if c.msgtype == msgtype})
    listing = ", ".join(f"{c.topic} ({c.msgtype})" for c in reader.connections) or "none"
    default = DEFAULT_TOPICS[msgtype]
    if topic is not None:
        if topic not in found:
            raise BadInput(f"{path}: no {msgtype} on {topic}; topics there: {listing}")
        return topic
    if not found:
        raise BadInput(f"{path}: no {msgtype} topic; topics there: {listing}")
    if len(found) > 1 and default not in found:
        raise BadInput(f"{path}: several {msgtype} topics ({', '.join(found)}): choose one with {choose}")
    return default if default in found else found[0]


def messages_of(
    path: Path, topic: str | None, msgtype: str = WIFI_TYPE, choose: str = "--topic"
) -> tuple[list[Any], str]:
    """The messages of `msgtype` on the topic (decoded), and the topic; BadInput naming the message
    that cannot be read, or `choose`, the option that names a topic, among several."""
    reader = _open(path)
    try:
        chosen = _topic(path, reader, topic, msgtype, choose)
        connections = [c for c in reader.connections if c.topic == chosen]
        messages: list[Any] = []
        records = iter(reader.messages(connections=connections))
        while True:
            try:
                conn, _stamp, raw = next(records)
                msg = reader.deserialize(raw, conn.msgtype)
            except StopIteration:
                break
            except Exception as exc:  # noqa: BLE001 - the library on untrusted bytes
                at = f"message {len(messages) + 1} of {chosen}"
                raise BadInput(f"{path}: {at}: cannot read: {type(exc).__name__}: {exc}") from None
            messages.append(msg)
    finally:
        reader.close()
    return messages, chosen


def _fields(path: Path, topic: str, msg: Any) -> None:
    """BadInput when the bag's own definition of the message lacks a field Rover reads."""
    needed = ("header", "txmac", "chan", "n_sub", "n_rows", "n_cols", "bw", "rssi", "seq_num", "csi_real", "csi_imag")
    missing = [f for f in needed if not hasattr(msg, f)]
    if missing:
        raise BadInput(f"{path}: {topic}: its {WIFI_TYPE} has no {', '.join(missing)}: not WiROS's layout")


def read(
    path: str | Path,
    topic: str | None = None,
    compensation: str | Path | None = None,
    every_transmitter: bool = False,
) -> CsiFrames:
    """The bag's packets of the first packet's channel and shape, and of its transmitter unless
    `every_transmitter` (the others counted in `dropped`), at the kept subcarriers, compensated when
    `compensation` (a file or a folder of WiROS's `RX_ID-CHAN.npy`) is given."""
    path = Path(path)
    messages, chosen = messages_of(path, topic)
    if not messages:
        raise BadInput(f"{path}: {chosen} holds no message")
    _fields(path, chosen, messages[0])
    first = messages[0]
    shape = (int(first.n_sub), int(first.n_rows), int(first.n_cols), int(first.bw), int(first.chan))
    mac = bytes(first.txmac)
    dropped: Counter[str] = Counter()
    keep: list[Any] = []
    for m in messages:
        values = int(m.n_sub) * int(m.n_rows) * int(m.n_cols)
        if len(m.csi_real) != values or len(m.csi_imag) != values:
            dropped["messages whose CSI does not hold n_sub x n_rows x n_cols values"] += 1
        elif (int(m.n_sub), int(m.n_rows), int(m.n_cols), int(m.bw), int(m.chan)) != shape:
            dropped["messages of another channel, bandwidth or shape than the first's (read one at a time)"] += 1
        elif every_transmitter and len(bytes(m.txmac)) != MAC_BYTES:
            dropped[f"messages whose txmac is not {MAC_BYTES} bytes"] += 1
        elif not every_transmitter and bytes(m.txmac) != mac:
            dropped["messages of another transmitter than the first's (read one at a time)"] += 1
        else:
            keep.append(m)
    n_sub, n_rows, n_cols, bw_mhz, chan = shape
    width = bw_mhz * 1e6
    if width not in KEPT_SUBCARRIERS:
        raise BadInput(f"{path}: {chosen}: bandwidth {bw_mhz} MHz is not 20, 40 or 80")
    try:
        centre_hz = channel_freq_hz(chan)
    except ValueError:
        raise BadInput(f"{path}: {chosen}: channel {chan} is no WiFi channel") from None
    real = np.array([m.csi_real for m in keep], dtype=np.float64)
    imag = np.array([m.csi_imag for m in keep], dtype=np.float64)
    csi = (real + 1j * imag).reshape(len(keep), n_cols, n_rows, n_sub).transpose(0, 3, 2, 1)
    csi = _kept_columns(path, chosen, csi, width)
    rx_ids = np.array([str(getattr(m, "rx_id", "")) for m in keep])
    if compensation is not None:
        csi = _compensated(Path(compensation), csi, rx_ids, chan)
    rssi = np.array([float(m.rssi) for m in keep])
    return CsiFrames(
        source="wiros",
        csi=csi,
        subcarriers=KEPT_SUBCARRIERS[width],
        bandwidth_hz=width,
        centre_freq_hz=np.full(len(keep), centre_hz),
        timestamp_ns=np.array([m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in keep], dtype=np.int64),
        rssi_db=np.repeat(rssi[:, None], n_rows, axis=1),
        noise_dbm=np.full(len(keep), np.nan),
        mac=np.array(
            [np.frombuffer(bytes(m.txmac).ljust(MAC_BYTES, b"\0")[:MAC_BYTES], np.uint8) for m in keep], np.uint8
        ).reshape(-1, MAC_BYTES),
        sequence=np.array([int(m.seq_num) for m in keep], dtype=np.int64),
        dropped=dict(dropped),
    )


def _kept_columns(path: Path, topic: str, csi: np.ndarray, width: float) -> np.ndarray:
    """(P, K, N, T) at the kept subcarriers: the raw FFT bins rotated back and picked, or the
    correction node's kept ones as they are."""
    kept = KEPT_SUBCARRIERS[width]
    bins = round(width / SUBCARRIER_SPACING_HZ)
    n_sub = csi.shape[1]
    if n_sub == len(kept):
        return csi
    if n_sub != bins:
        raise BadInput(
            f"{path}: {topic}: n_sub {n_sub} is neither the {bins} FFT bins of {width / 1e6:g} MHz nor the "
            f"{len(kept)} subcarriers WiROS keeps"
        )
    csi = csi.copy()
    csi[:, :LOWER_BINS] *= LOWER_BINS_UNDO.get(width, 1.0)
    return csi[:, kept + bins // 2]


def _compensated(where: Path, csi: np.ndarray, rx_ids: np.ndarray, chan: int) -> np.ndarray:
    """The CSI times WiROS's compensation of each packet's router on the channel."""
    out = csi.copy()
    for rx in np.unique(rx_ids):
        file = where if where.is_file() else where / f"{rx}-{chan}.npy"
        if not file.is_file():
            raise BadInput(f"{where}: no compensation file {file.name} for router {rx!r} on channel {chan}")
        try:
            comp = np.load(file, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise BadInput(f"{file}: not a compensation array (.npy): {exc}") from None
        k, n = csi.shape[1:3]
        if comp.ndim not in (2, 3) or comp.shape[:2] != (k, n) or (comp.ndim == 3 and comp.shape[2] != 1):
            raise BadInput(f"{file}: its shape {comp.shape} is not ({k}, {n}, 1): {k} subcarriers, {n} antennas")
        mine = rx_ids == rx
        out[mine] *= comp.reshape(k, n)[None, :, :, None]
    return out


def tag_ids(path: Path, macs: list[bytes]) -> np.ndarray:
    """Each transmitter's tag id: its MAC's last ID_BYTES bytes as an unsigned integer
    (`02:00:00:00:00:07` is tag 7, the id a truth's tags.csv gives it); BadInput when two MACs share one."""
    ids: dict[bytes, int] = {mac: int.from_bytes(mac[-ID_BYTES:], "big") for mac in set(macs)}
    owner: dict[int, bytes] = {}
    for mac, tag in sorted(ids.items()):
        if tag in owner:
            a, b = (":".join(f"{x:02x}" for x in m) for m in (owner[tag], mac))
            raise BadInput(f"{path}: transmitters {a} and {b} share their last {ID_BYTES} bytes, the tag id {tag}")
        owner[tag] = mac
    return np.array([ids[m] for m in macs], dtype=np.int64)
