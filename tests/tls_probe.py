"""Zenoh clients that try what an intruder would against hosts under `security:`, for
tests/test_security.py; run inside a lab namespace, they print one JSON object.

    tls_probe.py connect ENDPOINT CA [CERT KEY]         can a client open a session at all (one try)?
    tls_probe.py reach ENDPOINT CERTS IDENTITY          open a session as IDENTITY, retried until it listens
    tls_probe.py data PIPELINE ENDPOINT CERTS           who reads and writes which keys mid-run
    tls_probe.py forge PIPELINE ENDPOINT CERTS IDENTITY TOKEN_KEY
                                                        declare a presence token as IDENTITY, hold it

Clients connect the way `rover status` does (client mode, scouting off, mutual TLS with the
CA and the identity's certificate): rover.transport.session.tls_config.
"""

from __future__ import annotations

import json
import sys
import threading
import time

import zenoh

from rover.transport.session import TlsFiles, tls_config

WAIT_S = 60.0
"""The longest any step waits for data to arrive."""
SAMPLES = 50
"""Raw-CSI stand-ins the witness receives before and after the forgeries (1 s at 50 Hz)."""
FORGED = b"forged"


def client(endpoint: str, ca: str, cert: str | None = None, key: str | None = None) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    if cert and key:
        tls_config(conf, TlsFiles(ca, cert, key), listen=False)
    else:
        conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(ca))
    return zenoh.open(conf)


def identity(endpoint: str, certs: str, name: str) -> zenoh.Session:
    """A client with host (or monitor) `name`'s certificate, retried until the host listens."""
    deadline = time.monotonic() + WAIT_S
    while True:
        try:
            return client(endpoint, f"{certs}/ca.pem", f"{certs}/{name}.pem", f"{certs}/{name}.key")
        except zenoh.ZError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)


class Counter:
    """Samples received on a key, real and forged apart, with a condition to wait on."""

    def __init__(self) -> None:
        self.real = 0
        self.forged = 0
        self.cond = threading.Condition()

    def __call__(self, sample: zenoh.Sample) -> None:
        with self.cond:
            if sample.payload.to_bytes().startswith(FORGED):
                self.forged += 1
            else:
                self.real += 1
            self.cond.notify_all()

    def wait(self, what: str, predicate) -> None:
        with self.cond:
            if not self.cond.wait_for(lambda: predicate(self), timeout=WAIT_S):
                raise SystemExit(f"tls_probe: no {what} after {WAIT_S:g} s")


def connect(endpoint: str, ca: str, cert: str | None = None, key: str | None = None) -> dict:
    try:
        client(endpoint, ca, cert, key).close()
        return {"connected": True}
    except zenoh.ZError as exc:
        return {"connected": False, "error": str(exc).split(" at /")[0]}


def data(pipeline: str, endpoint: str, certs: str) -> dict:
    """Mid-run, with the NUC's `csi/imu` (raw CSI's stand-in, read by the laptop only) and base's
    `replay/imu` (read by the laptop) flowing: base's identity and the monitor's try to read the
    NUC's key and to write on keys; a client with the laptop's identity witnesses what arrives.

    Absence is shown by order, not by waiting: base's forgery on the NUC's key is sent before its
    (allowed) forgery on its own key, on one session over one link, so once the witness has the
    second, the first would have arrived too had the NUC let it through."""
    csi, replay = f"rover/{pipeline}/csi/imu", f"rover/{pipeline}/replay/imu"
    base, monitor, laptop = (identity(endpoint, certs, n) for n in ("base", "monitor", "laptop"))
    base_csi, monitor_csi, monitor_replay = Counter(), Counter(), Counter()
    keep = [
        base.declare_subscriber(csi, base_csi),
        monitor.declare_subscriber(csi, monitor_csi),
        monitor.declare_subscriber(replay, monitor_replay),
    ]
    seen_csi, seen_replay = Counter(), Counter()
    keep += [laptop.declare_subscriber(csi, seen_csi), laptop.declare_subscriber(replay, seen_replay)]
    seen_csi.wait("raw CSI at the witness", lambda c: c.real >= SAMPLES)
    status = [r.ok is not None for r in monitor.get(f"rover/{pipeline}/_status/*", timeout=10.0)]
    monitor.put(replay, FORGED + b" by the monitor")
    monitor.put(csi, FORGED + b" by the monitor")
    base.put(csi, FORGED + b" by base on the NUC's key")
    base.put(replay, FORGED + b" by base on its own key")
    seen_replay.wait("forgery by base on its own key at the witness", lambda c: c.forged >= 1)
    before = seen_csi.real
    seen_csi.wait("more raw CSI at the witness", lambda c: c.real >= before + SAMPLES)
    result = {
        "witness_csi": seen_csi.real,
        "witness_csi_forged": seen_csi.forged,
        "witness_replay_forged": seen_replay.forged,
        "base_csi": base_csi.real,
        "monitor_data": monitor_csi.real + monitor_replay.real,
        "monitor_status_replies": sum(status),
    }
    del keep
    for session in (base, monitor, laptop):
        session.close()
    return result


def forge(pipeline: str, endpoint: str, certs: str, name: str, token: str) -> None:
    """Declare `token` as identity `name`, say so, and hold it until stdin closes."""
    session = identity(endpoint, certs, name)
    held = session.liveliness().declare_token(token)
    print(json.dumps({"declared": token, "as": name}), flush=True)
    sys.stdin.read()
    held.undeclare()
    session.close()


def main(argv: list[str]) -> None:
    command, *args = argv
    if command == "connect":
        print(json.dumps(connect(*args)))
    elif command == "reach":
        identity(*args).close()
        print(json.dumps({"connected": True}))
    elif command == "data":
        print(json.dumps(data(*args)))
    elif command == "forge":
        forge(*args)
    else:
        raise SystemExit(f"tls_probe: unknown command {command!r}")


if __name__ == "__main__":
    main(sys.argv[1:])
