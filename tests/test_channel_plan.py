"""Channel planning from the square-wave model: the paper's set-up, constructed conflicts, proposals."""

from __future__ import annotations

import pytest

from rover.formats.wifi import channel_freq_hz
from rover.operators.channel_sweep.channel_plan import best_excitation, conflicts, emissions, max_tags, propose

PAPER = {1: 149, 2: 153, 3: 157, 4: 161}


def test_paper_setup_has_exactly_one_conflict_tag4_third_harmonic_on_tag2():
    found = conflicts(165, PAPER)
    assert len(found) == 1
    c = found[0]
    assert (c.kind, c.tag, c.other) == ("harmonic", 4, 2)
    assert c.message == "tag 4's 3rd harmonic (5765 MHz, -9.5 dB) lands on channel 153, tag 2's"


def test_the_planner_proposes_an_assignment_without_it():
    plan = propose(165, PAPER)
    assert plan is not None and conflicts(165, plan.channels) == []
    assert sum(plan.channels[t] == ch for t, ch in PAPER.items()) == 3, "moves only one tag"
    assert len(set(plan.channels.values())) == 4


def test_harmonic_powers_follow_the_square_wave():
    ems = emissions(channel_freq_hz(165), channel_freq_hz(161))
    powers = sorted({round(e.power_db, 1) for e in ems})
    assert powers == [-19.1, -16.9, -14.0, -9.5, 0.0]
    mirror = [e for e in ems if e.order == 1]
    assert mirror[0].freq_hz == 2 * channel_freq_hz(165) - channel_freq_hz(161)


@pytest.mark.parametrize(
    "excitation, channels, kind",
    [
        (165, {1: 149, 2: 149}, "overlap"),
        (165, {1: 161, 2: 165}, "excitation"),
        (165, {1: 150, 2: 36}, "not_allowed"),
        (64, {1: 56, 2: 72}, "mirror"),  # 56 is 40 MHz below the excitation, its mirror 40 MHz above, on 72
        (165, {1: 161, 2: 153}, "harmonic"),
    ],
)
def test_constructed_conflicts_of_each_kind(excitation, channels, kind):
    allowed = (56, 64, 72, 36, 149, 153, 161, 165)
    found = conflicts(excitation, channels, allowed)
    assert {c.kind for c in found} == {kind}, found


def test_no_assignment_when_too_many_tags():
    limit = len(max_tags(165))
    assert propose(165, {i: 149 for i in range(limit + 1)}) is None
    plan = propose(165, {i: 149 for i in range(limit)})
    assert plan is not None and conflicts(165, plan.channels) == []


def test_band_edge_excitation_and_its_maximum():
    edge = best_excitation(candidates=[36, 100, 165])
    assert edge.channel in (36, 165)
    assert edge.max_tags == len(max_tags(edge.channel)) >= 4
    assert conflicts(edge.channel, dict(enumerate(edge.channels))) == []
    limited = max_tags(165, max_shift_hz=80e6)
    assert limited == [149, 153, 157] or len(limited) == 3
