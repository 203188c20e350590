"""`channel_hop`: tune the receiver through the sweep's channels, dwelling on each, and say when it did.

Each hop runs a command (by default `iw dev IFACE set channel N HT20`) and is announced as a
`ChannelHop` message stamped at the moment the radio was retuned, so `channel_sweep` can tell
which channel a live CSI frame was received on. `dry_run` prints the commands instead.
"""

from __future__ import annotations

import logging
import shlex
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

from rover.errors import BadInput, SpecError
from rover.formats.rig import load_rig
from rover.messages import header, make
from rover.operator import Emit, Out, Source, Watermark
from rover.pipeline.params import Checked, NonNegativeInt, PositiveFloat

log = logging.getLogger("rover.channel_hop")
DEFAULT_COMMAND = "iw dev {interface} set channel {channel} HT20"
PROMISE_MARGIN_S = 0.001
"""kept off the promise of the next hop's time: the dwell is timed on the monotonic clock, stamps on the wall clock"""


@dataclass(frozen=True)
class HopParams(Checked):
    setup: str = ""
    """setup.yaml giving the tags' channels and the interface; or give `channels`."""
    channels: list[int] = field(default_factory=list)
    interface: str = ""
    dwell_s: PositiveFloat = 0.05
    command: str = DEFAULT_COMMAND
    dry_run: bool = False
    rounds: NonNegativeInt = 0
    """Sweeps to make before ending; 0 = until stopped."""


Runner = Callable[[list[str]], None]


def run_command(argv: list[str]) -> None:
    """Run one hop command; a failure is BadInput naming the command."""
    try:
        done = subprocess.run(argv, capture_output=True, text=True, timeout=5)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise BadInput(f"channel_hop: cannot run {shlex.join(argv)}: {exc}") from None
    if done.returncode != 0:
        raise BadInput(f"channel_hop: {shlex.join(argv)} failed: {done.stderr.strip() or done.returncode}")


class ChannelHop(Source):
    """Cycles through the sweep's channels, `dwell_s` on each."""

    live = True

    outputs = {"hops": Out("rover_msgs/msg/ChannelHop")}
    Params = HopParams

    def __init__(self, params: HopParams | None = None, runner: Runner | None = None):
        super().__init__(params)
        p = self.params
        channels, interface = list(p.channels), p.interface
        if p.setup:
            try:
                rig = load_rig(p.setup)
            except SpecError as exc:
                raise BadInput(str(exc.diagnostics[0])) from None
            channels = channels or [t.channel for t in sorted(rig.tags, key=lambda t: t.channel)]
            interface = interface or rig.interface
        if not channels:
            raise BadInput("channel_hop: no channels to visit (give params.setup or params.channels)")
        try:
            self.commands = [
                shlex.split(p.command.format(interface=interface or "wlan0", channel=ch)) for ch in channels
            ]
        except (KeyError, IndexError, ValueError) as exc:
            raise BadInput(f"channel_hop: bad command template {p.command!r}: {exc}") from None
        self.channels = channels
        self.interface = interface or "wlan0"
        self.runner = runner or (self._print if p.dry_run else run_command)

    @staticmethod
    def _print(argv: list[str]) -> None:
        print(shlex.join(argv), flush=True)

    def run(self, stop: threading.Event) -> Iterator[Emit | Watermark]:
        rounds = 0
        while not stop.is_set() and (self.params.rounds == 0 or rounds < self.params.rounds):
            for channel, argv in zip(self.channels, self.commands, strict=True):
                self.runner(argv)
                now = time.time_ns()
                yield Emit(
                    "hops",
                    make(
                        "rover_msgs/msg/ChannelHop",
                        header=header(now, "base_link"),
                        interface=self.interface,
                        channel=channel,
                    ),
                )
                # the next hop comes a dwell from now at the earliest: promised at once, so the frames
                # of this dwell are labelled as they come, not a dwell later
                yield Watermark(now + int((self.params.dwell_s - PROMISE_MARGIN_S) * 1e9))
                if stop.wait(self.params.dwell_s):
                    return
                yield Watermark(time.time_ns())
            rounds += 1
