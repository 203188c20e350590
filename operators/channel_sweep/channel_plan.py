"""Backscatter channel planning: where each tag's energy lands, which tags collide, and a plan without collisions.

A tag toggles its RF switch with a square wave at f_b, so it reflects the excitation at
f_c +- (2n-1) f_b with amplitude 1/(2n-1) relative to the first pair (paper Eq. 1-2): the tag's
own channel, its mirror sideband at 2 f_c - f_tag at the same power, and odd harmonics at
-9.5 dB (3rd), -14.0 dB (5th), -16.9 dB (7th), -19.1 dB (9th). Anything at or above -20 dB that
overlaps another tag's 20 MHz channel is a conflict.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from rover.formats.wifi import CHANNEL_WIDTH_HZ, INTEL5300_CHANNELS_5GHZ, channel_freq_hz

HARMONIC_FLOOR_DB = -20.0
"""Emissions weaker than this relative to the tag's own channel are not conflicts."""
ORDINALS = {3: "3rd", 5: "5th", 7: "7th", 9: "9th"}


@dataclass(frozen=True)
class Emission:
    """Energy a tag puts at one frequency: order 1 is its channel (side -1) or mirror (side +1)."""

    freq_hz: float
    order: int
    power_db: float

    @property
    def label(self) -> str:
        return "mirror sideband" if self.order == 1 else f"{ORDINALS.get(self.order, f'{self.order}th')} harmonic"


def emissions(excitation_hz: float, tag_hz: float) -> list[Emission]:
    """The tag's mirror and odd harmonics down to the floor (its own channel excluded)."""
    shift = tag_hz - excitation_hz
    out = [Emission(excitation_hz - shift, 1, 0.0)]
    order = 3
    while (power := -20.0 * math.log10(order)) >= HARMONIC_FLOOR_DB:
        out += [
            Emission(excitation_hz + order * shift, order, power),
            Emission(excitation_hz - order * shift, order, power),
        ]
        order += 2
    return out


def overlaps(f1_hz: float, f2_hz: float) -> bool:
    """Two 20 MHz channels share spectrum (adjacent channels touch but do not overlap)."""
    return abs(f1_hz - f2_hz) < CHANNEL_WIDTH_HZ - 1.0


@dataclass(frozen=True)
class Conflict:
    kind: str
    """`not_allowed`, `excitation`, `overlap`, `mirror` or `harmonic`."""
    tag: int
    other: int | None
    message: str


@dataclass
class Plan:
    excitation_channel: int
    channels: dict[int, int]
    """tag id -> channel"""
    conflicts: list[Conflict] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.conflicts


def conflicts(
    excitation_channel: int, channels: dict[int, int], allowed: Sequence[int] = INTEL5300_CHANNELS_5GHZ
) -> list[Conflict]:
    """Every conflict of an assignment of channels to tags, in a stable order."""
    f_c = channel_freq_hz(excitation_channel)
    found: list[Conflict] = []
    tags = sorted(channels)
    for tag in tags:
        ch = channels[tag]
        if ch not in allowed:
            found.append(
                Conflict("not_allowed", tag, None, f"tag {tag}'s channel {ch} is not in the allowed channel list")
            )
        if overlaps(channel_freq_hz(ch), f_c):
            found.append(
                Conflict(
                    "excitation",
                    tag,
                    None,
                    f"tag {tag}'s channel {ch} overlaps the excitation channel {excitation_channel}",
                )
            )
    for i, a in enumerate(tags):
        for b in tags[i + 1 :]:
            if overlaps(channel_freq_hz(channels[a]), channel_freq_hz(channels[b])):
                found.append(
                    Conflict(
                        "overlap", a, b, f"tags {a} and {b} use overlapping channels {channels[a]} and {channels[b]}"
                    )
                )
    for a in tags:
        for em in emissions(f_c, channel_freq_hz(channels[a])):
            for b in tags:
                if b != a and overlaps(em.freq_hz, channel_freq_hz(channels[b])):
                    found.append(
                        Conflict(
                            "mirror" if em.order == 1 else "harmonic",
                            a,
                            b,
                            f"tag {a}'s {em.label} ({em.freq_hz / 1e6:g} MHz, {em.power_db:.1f} dB) "
                            f"lands on channel {channels[b]}, tag {b}'s",
                        )
                    )
    return found


def _compatible(excitation_channel: int, a: int, b: int) -> bool:
    return not conflicts(excitation_channel, {0: a, 1: b}, allowed=(a, b))


def usable_channels(
    excitation_channel: int, allowed: Sequence[int] = INTEL5300_CHANNELS_5GHZ, max_shift_hz: float | None = None
) -> list[int]:
    """Allowed channels a tag can shift into: clear of the excitation, within the tag's shift range."""
    f_c = channel_freq_hz(excitation_channel)
    return [
        ch
        for ch in allowed
        if not overlaps(channel_freq_hz(ch), f_c)
        and (max_shift_hz is None or abs(channel_freq_hz(ch) - f_c) <= max_shift_hz)
    ]


def _compatibility(excitation_channel: int, candidates: list[int]) -> dict[int, set[int]]:
    return {a: {b for b in candidates if b != a and _compatible(excitation_channel, a, b)} for a in candidates}


def _maximal_cliques(graph: dict[int, set[int]]):
    """Every maximal set of mutually compatible channels (Bron-Kerbosch with pivoting)."""

    def expand(clique: list[int], candidates: set[int], excluded: set[int]):
        if not candidates and not excluded:
            yield sorted(clique)
            return
        pivot = max(candidates | excluded, key=lambda v: len(graph[v] & candidates))
        for v in sorted(candidates - graph[pivot]):
            yield from expand(clique + [v], candidates & graph[v], excluded & graph[v])
            candidates = candidates - {v}
            excluded = excluded | {v}

    yield from expand([], set(graph), set())


def max_tags(
    excitation_channel: int, allowed: Sequence[int] = INTEL5300_CHANNELS_5GHZ, max_shift_hz: float | None = None
) -> list[int]:
    """A largest set of channels that tags can use at once without conflicts."""
    graph = _compatibility(excitation_channel, usable_channels(excitation_channel, allowed, max_shift_hz))
    return max(_maximal_cliques(graph), key=lambda c: (len(c), [-x for x in c]), default=[])


def propose(
    excitation_channel: int,
    wanted: dict[int, int],
    allowed: Sequence[int] = INTEL5300_CHANNELS_5GHZ,
    max_shift_hz: float | None = None,
) -> Plan | None:
    """A conflict-free assignment keeping as many tags on their wanted channels as possible (None if none).

    Any subset of a set of mutually compatible channels is compatible, so the best plan lives in
    one maximal clique: the one holding the most distinct wanted channels. Tags that cannot keep
    theirs take the clique's free channels nearest in frequency to what they wanted.
    """
    graph = _compatibility(excitation_channel, usable_channels(excitation_channel, allowed, max_shift_hz))
    wanted_channels = set(wanted.values())
    cliques = [c for c in _maximal_cliques(graph) if len(c) >= len(wanted)]
    if not cliques:
        return None
    clique = max(cliques, key=lambda c: (len(wanted_channels & set(c)), [-x for x in c]))
    free = set(clique)
    channels: dict[int, int] = {}
    for tag in sorted(wanted):
        if wanted[tag] in free:
            channels[tag] = wanted[tag]
            free.discard(wanted[tag])
    for tag in sorted(t for t in wanted if t not in channels):
        target = channel_freq_hz(wanted[tag])
        channels[tag] = min(free, key=lambda ch: (abs(channel_freq_hz(ch) - target), ch))
        free.discard(channels[tag])
    return Plan(excitation_channel, dict(sorted(channels.items())))


@dataclass(frozen=True)
class ExcitationChoice:
    channel: int
    max_tags: int
    channels: list[int]


def best_excitation(
    allowed: Sequence[int] = INTEL5300_CHANNELS_5GHZ,
    candidates: Iterable[int] | None = None,
    max_shift_hz: float | None = None,
) -> ExcitationChoice:
    """The excitation channel that lets the most tags work at once; ties go to the band edges, where
    one sideband of every tag falls outside the band (the paper's choice), then to the upper edge."""
    options = []
    for ch in candidates if candidates is not None else allowed:
        channels = max_tags(ch, allowed, max_shift_hz)
        options.append(ExcitationChoice(ch, len(channels), channels))
    low, high = min(allowed), max(allowed)
    return max(options, key=lambda o: (o.max_tags, max(o.channel - low, high - o.channel), o.channel))
