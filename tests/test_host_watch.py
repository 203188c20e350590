"""Host presence: who is ready, done or lost, and how a loss is explained, on real Zenoh sessions."""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator

import pytest
import zenoh
from helpers import free_port, wait_until

from rover.errors import TransportError
from rover.operator import LostHost
from rover.pipeline.validation import unreachable_without
from rover.runtime.hosts import HostWatch, attribute_to_hubs, describe_loss
from rover.transport import keys
from rover.transport.session import SessionSpec, open_session

HUB = {"nuc": {"base", "laptop"}, "base": {"nuc"}, "laptop": {"nuc"}}
MESH = {"nuc": {"base", "laptop"}, "base": {"nuc", "laptop"}, "laptop": {"nuc", "base"}}
WAIT_S = 10.0


TIMEOUTS = {"nuc": 15.0, "base": 15.0, "laptop": 15.0}


def lost(*names: str, reason: str = "gone") -> dict[str, LostHost]:
    return {n: LostHost(n, reason, "2026-12-01T00:00:00+00:00") for n in names}


def test_the_hub_is_named_with_the_hosts_behind_it():
    assert unreachable_without(HUB, "laptop", "nuc") == {"base"}
    assert unreachable_without(HUB, "nuc", "base") == set()
    together = {"nuc": 100.0, "base": 100.01}
    text = describe_loss(HUB, "laptop", lost("nuc", "base", reason="stopped by SIGINT"), together)
    assert text == "hub nuc was lost (stopped by SIGINT); host base became unreachable with it"
    assert describe_loss(HUB, "nuc", lost("base"), {"base": 5.0}) == "host base was lost (gone)"
    blamed = attribute_to_hubs(HUB, "base", lost("nuc", "laptop"), {"nuc": 7.0, "laptop": 7.0})
    assert blamed["laptop"].reason == "unreachable once hub nuc was lost" and blamed["nuc"].reason == "gone"


def test_a_host_lost_well_before_the_hub_keeps_its_own_reason():
    """base killed at 10 s, the NUC stopped at 20 s: base was not lost with the hub (nobody else was)."""
    losses = {"base": LostHost("base", "gone without a word", "t1"), "nuc": LostHost("nuc", "stopped by SIGINT", "t2")}
    at = {"base": 10.0, "nuc": 20.0}
    assert describe_loss(HUB, "laptop", losses, at) == (
        "host base was lost (gone without a word); host nuc was lost (stopped by SIGINT)"
    )
    assert attribute_to_hubs(HUB, "laptop", losses, at)["base"].reason == "gone without a word"


def test_with_a_direct_link_the_nuc_is_no_hub():
    assert unreachable_without(MESH, "laptop", "nuc") == set()
    assert describe_loss(MESH, "laptop", lost("nuc"), {"nuc": 1.0}) == "host nuc was lost (gone)"


@pytest.fixture
def sessions() -> Iterator[tuple[zenoh.Session, zenoh.Session]]:
    """Two routers on loopback: the watching host's and the other processes'."""
    port = free_port()
    with (
        open_session(SessionSpec([f"tcp/127.0.0.1:{port}"], [], 15.0, "a")) as mine,
        open_session(SessionSpec([], [f"tcp/127.0.0.1:{port}"], 15.0, "b")) as theirs,
    ):
        yield mine, theirs


def token(session: zenoh.Session, host: str, state: str, digest: str = "d1", zid: str = "") -> zenoh.LivelinessToken:
    key = keys.host_token("p", keys.HostKey(host, digest, zid or str(session.zid()), state))
    return session.liveliness().declare_token(key)


def watch_of(session: zenoh.Session) -> HostWatch:
    return HostWatch(session, "p", "laptop", TIMEOUTS, "d1")


def test_a_host_withdrawn_before_done_is_lost_with_its_reason(sessions):
    mine, theirs = sessions
    watch = watch_of(mine)
    lost_hosts: list[str] = []
    noticed = threading.Event()

    def on_lost(host: str) -> None:
        lost_hosts.append(host)
        noticed.set()

    watch.on_lost = on_lost
    nuc = HostWatch(theirs, "p", "nuc", TIMEOUTS, "d1")
    nuc.declare("ready")
    base = token(theirs, "base", "ready")
    watch.declare("ready")
    assert watch.wait_ready(["nuc", "base", "laptop"], threading.Event(), WAIT_S, "")
    # as a host does before it runs: the NUC has seen the laptop ready, so the laptop's subscriber
    # (declared before its token) has reached the NUC's session and the bye is not put to nobody
    assert nuc.wait_ready(["nuc", "laptop"], threading.Event(), WAIT_S, "")
    nuc.say_bye("stopped by SIGINT")
    wait_until(lambda: "nuc" in watch.byes, "the bye arrived", timeout_s=WAIT_S, poll_s=0.01)
    nuc.close()
    assert noticed.wait(WAIT_S)
    assert lost_hosts == ["nuc"] and watch.lost["nuc"].reason == "stopped by SIGINT"
    done = token(theirs, "base", "done")
    give_up = threading.Timer(WAIT_S, (stop := threading.Event()).set)
    give_up.start()
    watch.wait_done(["nuc", "base", "laptop"], stop)
    give_up.cancel()
    assert not stop.is_set() and watch.done == {"base"}
    done.undeclare()
    base.undeclare()
    watch.wait_gone(["base"], WAIT_S)
    watch.close()
    assert watch.gone == {"base"} and set(watch.lost) == {"nuc"}, "a host withdrawn after it was done is not lost"


def test_a_restarted_host_takes_over_before_the_run_begins(sessions, caplog):
    """The laptop restarted while its old process still holds its token: the new one is ignored
    while the old one is there, and takes over as soon as the old one leaves."""
    mine, theirs = sessions
    watch = HostWatch(mine, "p", "nuc", TIMEOUTS, "d1")
    old = token(theirs, "laptop", "ready", zid="01d")
    wait_until(lambda: watch.ready.get("laptop") == "01d", "the old laptop is seen", timeout_s=WAIT_S, poll_s=0.01)
    new = token(theirs, "laptop", "ready", zid="2e3")
    wait_until(
        lambda: watch.claims.get("laptop") == ["01d", "2e3"], "the new laptop is seen", timeout_s=WAIT_S, poll_s=0.01
    )
    assert watch.ready["laptop"] == "01d"
    old.undeclare()
    wait_until(lambda: watch.ready.get("laptop") == "2e3", "the new laptop takes over", timeout_s=WAIT_S, poll_s=0.01)
    base = token(theirs, "base", "ready")
    assert watch.wait_ready(["nuc", "base", "laptop"], threading.Event(), WAIT_S, "")
    for t in (new, base):
        t.undeclare()
    watch.close()


def test_tokens_not_from_a_host_of_this_run_are_ignored(sessions, caplog):
    """Another pipeline version (digest), an undeclared host, a malformed key, a second process
    claiming a host: none of them makes the run start."""
    mine, theirs = sessions
    watch = watch_of(mine)
    forged = [
        token(theirs, "nuc", "ready", digest="other"),
        token(theirs, "intruder", "ready"),
        theirs.liveliness().declare_token("rover/p/_hosts/nuc/ready"),
    ]
    real_base = token(theirs, "base", "ready")
    with caplog.at_level(logging.WARNING, logger="rover"), pytest.raises(TransportError) as info:
        watch.wait_ready(["nuc", "base", "laptop"], threading.Event(), 1.0, "")
    assert "waiting for host(s) nuc" in str(info.value) and "base" not in str(info.value)
    assert sum("ignored the presence token" in r.message for r in caplog.records) == 3
    second = token(theirs, "base", "ready", zid="f00d")
    nuc = token(theirs, "nuc", "ready")
    assert watch.wait_ready(["nuc", "base", "laptop"], threading.Event(), WAIT_S, "")
    assert watch.ready["base"] == str(theirs.zid())
    for t in (*forged, real_base, second, nuc):
        t.undeclare()
    watch.close()


def test_a_stop_ends_the_wait_and_a_host_that_left_is_waited_for_again(sessions, caplog):
    mine, theirs = sessions
    watch = watch_of(mine)
    nuc = token(theirs, "nuc", "ready")
    caplog.set_level(logging.WARNING, logger="rover")
    with pytest.raises(TransportError, match=r"after 0.5 s \(wait_timeout_s\) waiting for host\(s\) base \(hint\)"):
        watch.wait_ready(["nuc", "base", "laptop"], threading.Event(), 0.5, " (hint)")
    nuc.undeclare()
    wait_until(
        lambda: any("host nuc left before the run began" in r.message for r in caplog.records),
        "nuc left",
        timeout_s=WAIT_S,
        poll_s=0.01,
    )
    with pytest.raises(TransportError, match="waiting for host.s. nuc"):
        watch.wait_ready(["nuc", "laptop"], threading.Event(), 0.5, "")
    assert not watch.lost
    stop = threading.Event()
    stop.set()
    assert not watch.wait_ready(["nuc", "laptop"], stop, WAIT_S, "")
    watch.close()
