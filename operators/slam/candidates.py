"""The max-mixture choice among a bearing's candidates (one per chain phase-jump combination): each
bearing of a tag in use takes the candidate likeliest at the current estimate, weighted by how often
its tag's recent bearings chose that combination (`JumpMemory`).

The weights are a switch prior, not a lock: a combination its last LOCK_BEARINGS bearings all chose
is about 30 times likelier than another (3.4 nats, a candidate 2.6 standard deviations closer), so a
jump state held for the run dominates, yet a chain that steps at some moment and stays so is
followed as soon as its bearings say so. A hard lock onto the held combination, as there was, kept
every bearing after such a step on the wrong candidate until the recent choices had turned: on
`paper` with 3 steps a minute it published tags 2 m off at 20-27 standard deviations."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from rover.geometry import wrap_angle

SELECT_CAP_SIGMA = 3.0
"""in the max-mixture, a candidate further off than this many stds is as unlikely as any other"""
LOCK_BEARINGS = 30
LOCK_SHARE = 0.75
"""a tag holds a combination that is the choice of this share of its last LOCK_BEARINGS bearings (a
jump at every retune spreads them over all, a quarter each at 5 GHz)"""


@dataclass
class JumpMemory:
    """Per tag slot, the combinations of its last LOCK_BEARINGS free choices (bearings that left the
    window, and the search's evidence): the mixture's weights and the lock."""

    recent: dict[int, list[int]] = field(default_factory=dict)

    def learn(self, tag_slot: int, jump: int) -> None:
        """A bearing of the tag left the window having freely chosen combination `jump`."""
        recent = self.recent.setdefault(tag_slot, [])
        recent.append(jump)
        del recent[:-LOCK_BEARINGS]

    def start(self, tag_slot: int, jumps: np.ndarray) -> None:
        """The first counts of a tag the search found: the combinations of its inlier bearings."""
        self.recent[tag_slot] = [int(j) for j in jumps[jumps >= 0][-LOCK_BEARINGS:]]

    def locked(self, tag_slot: int) -> int | None:
        """The jump combination a tag's chains hold (the choice of LOCK_SHARE of its last LOCK_BEARINGS
        bearings), if any: the discrete state a jump once per run leaves, reported with the tag."""
        recent = self.recent.get(tag_slot, [])
        if len(recent) < LOCK_BEARINGS:
            return None
        top = max(set(recent), key=recent.count)
        return top if recent.count(top) >= LOCK_SHARE * len(recent) else None

    def log_weights(self, tag: np.ndarray, jumps: np.ndarray, tags: int) -> np.ndarray:
        """log of each candidate's combination weight for its tag: its count among the tag's last
        LOCK_BEARINGS free choices plus one, normalized (recent only, so a later jump can be followed)."""
        combinations = max(int(jumps.max()) + 1, 1)
        table = np.zeros((tags, combinations))  # per tag slot and combination
        for t in np.unique(tag):
            recent = np.asarray(self.recent.get(int(t), []), dtype=int)
            counts = np.bincount(recent[recent < combinations], minlength=combinations)
            table[t] = np.log((counts + 1.0) / (len(recent) + combinations))
        return np.where(jumps >= 0, table[tag[:, None], np.maximum(jumps, 0)], -math.log(combinations))


@dataclass(frozen=True)
class Choice:
    """Per bearing: the candidate it uses, and the variance (rad^2) the other candidates' chances add
    to the chosen one's angle."""

    choice: np.ndarray
    doubt: np.ndarray


def choose(
    offset: np.ndarray,
    tag: np.ndarray,
    angles: np.ndarray,
    stds: np.ndarray,
    jumps: np.ndarray,
    active: list[bool],
    memory: JumpMemory,
    aoa_std_scale: float,
    kept: Choice,
) -> Choice:
    """Max-mixture over stacked bearings: robot-to-tag vectors `offset` at the estimate, each
    bearing's tag slot, candidates (rows, K; NaN-padded) with their window stds and combinations.
    Bearings of tags not in use keep what `kept` says."""
    predicted = np.arctan2(offset[:, 1], offset[:, 0])
    r = wrap_angle(predicted[:, None] - angles) / stds
    prior = np.log(stds) - memory.log_weights(tag, jumps, len(active))  # a wide candidate, a rare combination
    cost = 0.5 * np.minimum(r**2, SELECT_CAP_SIGMA**2) + prior
    cost = np.where(np.isfinite(r), cost, np.inf)
    choice = np.argmin(cost, axis=1)
    rows = np.arange(len(choice))
    # odds of each candidate against the chosen one, uncapped and with the bursts' own stds (the
    # window's are scaled up for the errors consecutive bursts share, which is no doubt about a choice)
    raw = r * aoa_std_scale
    likely = np.where(np.isfinite(raw), 0.5 * raw**2 + prior, np.inf)
    # normalized against each row's most likely candidate, so no exponent overflows (inf / inf)
    low = likely.min(axis=1, keepdims=True)
    finite = np.isfinite(likely)
    chance = np.exp(-(np.where(finite, likely, 0.0) - np.where(np.isfinite(low), low, 0.0))) * finite
    chance /= np.maximum(chance.sum(axis=1, keepdims=True), np.finfo(float).tiny)
    apart = np.where(np.isfinite(angles), wrap_angle(angles - angles[rows, choice][:, None]), 0.0)
    doubt = np.sum(chance * apart**2, axis=1)
    use = np.array(active, bool)[tag]
    return Choice(np.where(use, choice, kept.choice), np.where(use, doubt, kept.doubt))
