"""Which of a bearing's candidates (one per chain phase-jump combination) each bearing uses: a hidden
Markov model per tag over its bearings in time order.

The chains' jump state changes rarely, and a change is an event, not noise: a chain steps by pi at
some moment and stays so (CSI Tool issues #23, #295, #113). So the state is a sequence per tag (its
channel), and the window's bearings of a tag are decoded together (Viterbi): a switch costs
-log(p / (C - 1)) once, staying -log(1 - p), with p the tag's switch rate learned from the bearings
that left the window (`JumpMemory`); the window starts from the state its last bearing left in. A
step is then followed as soon as two or three bearings after it agree (the bearings before it keep
the old state), while one stray bearing does not flip it; a tag whose combination is drawn afresh at
every dwell learns a high p and chooses freely.

Each bearing's evidence for a combination is its candidate's likelihood at the estimate with the
burst's own std (the window's are scaled up for the errors consecutive bursts share, which weakens
each bearing in the fit, not the odds between its candidates), robust to multipath outliers: a
mixture of that Gaussian and a uniform share OUTLIER_SHARE. The state prior was a frequency weight
in units of the scaled stds: after a step on `paper` (3 steps a minute) it kept a tag on a candidate
75 deg off for 20 s and published it 2 m away at 13.6 sigma."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from rover.geometry import wrap_angle

OUTLIER_SHARE = 0.1
"""share of bearings whose candidate at the true combination is still far off (multipath)"""
HISTORY_BEARINGS = 200
"""bearings per tag the switch rate is learned from"""
PRIOR_SWITCHES, PRIOR_TRANSITIONS = 1.0, 30.0
"""the switch rate's prior: one switch in 30 bearings, outweighed by a few minutes of evidence"""
LOCK_BEARINGS = 30
LOCK_SHARE = 0.75
"""a tag holds a combination that is the choice of this share of its last LOCK_BEARINGS bearings
(reported with the tag; a jump at every retune spreads them over all, a quarter each at 5 GHz)"""


@dataclass
class JumpMemory:
    """Per tag slot, the combinations its last HISTORY_BEARINGS bearings used when they left the
    window (and the search's evidence): the state a window starts from, and the switch rate."""

    recent: dict[int, list[int]] = field(default_factory=dict)

    def learn(self, tag_slot: int, jump: int) -> None:
        """A bearing of the tag left the window using combination `jump`."""
        recent = self.recent.setdefault(tag_slot, [])
        recent.append(jump)
        del recent[:-HISTORY_BEARINGS]

    def start(self, tag_slot: int, jumps: np.ndarray) -> None:
        """The first history of a tag the search found: the combinations of its inlier bearings."""
        self.recent[tag_slot] = [int(j) for j in jumps[jumps >= 0][-HISTORY_BEARINGS:]]

    def locked(self, tag_slot: int) -> int | None:
        """The jump combination a tag's chains hold (the choice of LOCK_SHARE of its last LOCK_BEARINGS
        bearings), if any."""
        recent = self.recent.get(tag_slot, [])[-LOCK_BEARINGS:]
        if len(recent) < LOCK_BEARINGS:
            return None
        top = max(set(recent), key=recent.count)
        return top if recent.count(top) >= LOCK_SHARE * len(recent) else None

    def last(self, tag_slot: int) -> int:
        """The combination the tag's last bearing to leave the window used (-1: none yet)."""
        recent = self.recent.get(tag_slot)
        return recent[-1] if recent else -1

    def switch_rate(self, tag_slot: int) -> float:
        """The chance that the next bearing's combination differs from the last one's."""
        recent = np.asarray(self.recent.get(tag_slot, []), dtype=int)
        switches = float(np.count_nonzero(np.diff(recent))) if len(recent) > 1 else 0.0
        return (switches + PRIOR_SWITCHES) / (max(len(recent) - 1, 0) + PRIOR_TRANSITIONS)


@dataclass(frozen=True)
class Choice:
    """Per bearing: the candidate it uses, and the variance (rad^2) the other candidates' chances add
    to the chosen one's angle."""

    choice: np.ndarray
    doubt: np.ndarray


def _evidence(predicted: np.ndarray, angles: np.ndarray, stds: np.ndarray) -> np.ndarray:
    """-log likelihood of each candidate (rows, K) at the predicted bearing: a Gaussian of its std
    mixed with a uniform outlier share (inf where there is no candidate)."""
    r = wrap_angle(predicted[:, None] - angles) / stds
    there = np.isfinite(r)
    r, stds = np.where(there, r, 0.0), np.where(there, stds, 1.0)
    inlier = math.log1p(-OUTLIER_SHARE) - 0.5 * r**2 - np.log(stds) - 0.5 * math.log(2 * math.pi)
    cost = -np.logaddexp(inlier, math.log(OUTLIER_SHARE / (2 * math.pi)))
    return np.where(there, cost, np.inf)


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
    """The candidates of stacked bearings (rows in time order): robot-to-tag vectors `offset` at the
    estimate, each bearing's tag slot, candidates (rows, K; NaN-padded) with their window stds and
    combinations. Bearings of tags not in use keep what `kept` says."""
    use = np.array(active, bool)[tag] if len(tag) else np.zeros(0, bool)
    rows = np.flatnonzero(use)
    if len(rows) == 0:
        return kept
    predicted = np.arctan2(offset[rows, 1], offset[rows, 0])
    cost = _evidence(predicted, angles[rows], stds[rows] / aoa_std_scale)
    cand_jumps = jumps[rows]
    slots = tag[rows]
    lasts = {int(t): memory.last(int(t)) for t in np.unique(slots)}
    combos = max(int(cand_jumps.max()) + 1, max(lasts.values()) + 1, 1)
    # per bearing and combination: its candidate's cost; a combination with no candidate of its own
    # (merged into one of the same direction, or no estimate) counts as an outlier
    outlier = -math.log(OUTLIER_SHARE / (2 * math.pi))
    per_combo = np.full((len(rows), combos), np.inf)
    has = (cand_jumps >= 0) & np.isfinite(cost)
    at_row, at_k = np.nonzero(has)
    np.minimum.at(per_combo, (at_row, cand_jumps[at_row, at_k]), cost[at_row, at_k])
    per_combo = np.where(np.isfinite(per_combo), per_combo, outlier)
    state, posterior = _decode(per_combo, slots, lasts, memory)
    # the best candidate of the decoded combination (or the row's best, when it has none); a
    # combination's chance shared among its candidates (a direction and its mirror image) by their
    # likelihoods
    match = has & (cand_jumps == state[:, None])
    pick = np.argmin(np.where(match.any(axis=1)[:, None] & ~match, np.inf, cost), axis=1)
    row_index, combo_of = np.arange(len(rows))[:, None], np.maximum(cand_jumps, 0)
    share = np.where(has, np.exp(-(cost - per_combo[row_index, combo_of])), 0.0)
    within = np.zeros_like(per_combo)
    np.add.at(within, (at_row, cand_jumps[at_row, at_k]), share[at_row, at_k])
    chance = np.where(has, posterior[row_index, combo_of] * share / np.maximum(within[row_index, combo_of], 1e-300), 0)
    chance /= np.maximum(chance.sum(axis=1, keepdims=True), np.finfo(float).tiny)
    mine = angles[rows, pick]
    apart = np.where(has, wrap_angle(angles[rows] - mine[:, None]), 0.0)
    choice, doubt = kept.choice.copy(), kept.doubt.copy()
    choice[rows] = pick
    doubt[rows] = np.sum(chance * apart**2, axis=1)
    return Choice(choice, doubt)


def _decode(
    cost: np.ndarray, slots: np.ndarray, lasts: dict[int, int], memory: JumpMemory
) -> tuple[np.ndarray, np.ndarray]:
    """Viterbi path and posterior marginals of each tag's combination over its bearings (rows in
    time order, `cost` (rows, C) -log likelihoods), all tags at once: per row its state and (rows, C)
    probabilities."""
    n, combos = cost.shape
    order = np.argsort(slots, kind="stable")
    tags, starts, counts = np.unique(slots[order], return_index=True, return_counts=True)
    which = np.repeat(np.arange(len(tags)), counts)
    pos = np.arange(n) - np.repeat(starts, counts)
    length = int(counts.max())
    padded = np.zeros((len(tags), length, combos))
    padded[which, pos] = cost[order]
    rate = np.array([memory.switch_rate(int(t)) for t in tags])
    stay = -np.log1p(-np.minimum(rate, 0.999))[:, None]
    switch = -np.log(rate / max(combos - 1, 1))[:, None]
    last = np.array([lasts[int(t)] for t in tags])
    start = np.where(last[:, None] < 0, 0.0, np.where(np.arange(combos)[None, :] == last[:, None], stay, switch))
    # Viterbi: from each combination, stay or come from the best of all at the switch cost; a tag's
    # rows past its last hold padding, never read back
    best = start + padded[:, 0]
    history = np.empty((len(tags), length, combos))
    history[:, 0] = best
    for k in range(1, length):
        best = np.minimum(best + stay, best.min(axis=1, keepdims=True) + switch) + padded[:, k]
        history[:, k] = best
    # the way back: row k-1 kept row k's combination unless coming from its best was cheaper
    kept = history + stay[:, :, None] <= history.min(axis=2, keepdims=True) + switch[:, :, None]
    leaders = history.argmin(axis=2)
    ends = counts - 1
    rows = np.arange(len(tags))
    path = np.zeros((len(tags), length), dtype=int)
    s = leaders[rows, ends]
    for k in range(length - 1, -1, -1):
        path[:, k] = s
        if k:
            s = np.where(k <= ends, np.where(kept[rows, k - 1, s], s, leaders[:, k - 1]), s)
    # forward-backward in scaled probabilities, the same transitions: from a vector p the chance of
    # each next combination is sum(p) p_switch + p (p_stay - p_switch). The backward recursion is
    # the forward one over a tag's bearings from its last, so both run as one, stacked: the forward
    # from the start's odds, the backward from its last bearing (its padding past its first is 1)
    like = np.exp(-(padded - padded.min(axis=2, keepdims=True)))
    p_stay, p_switch = np.exp(-stay), np.exp(-switch)
    gain = p_stay - p_switch
    back = np.ones_like(like)
    back[which, counts[which] - 1 - pos] = like[which, pos]
    both, both_switch, both_gain = np.concatenate([like, back]), np.tile(p_switch, (2, 1)), np.tile(gain, (2, 1))
    chain = np.empty_like(both)
    a = np.concatenate([np.exp(-(start - start.min(axis=1, keepdims=True))), np.ones_like(start)]) * both[:, 0]
    chain[:, 0] = a / a.sum(axis=1, keepdims=True)
    for k in range(1, length):
        prev = chain[:, k - 1]
        a = (prev.sum(axis=1, keepdims=True) * both_switch + prev * both_gain) * both[:, k]
        chain[:, k] = a / a.sum(axis=1, keepdims=True)
    # a row's backward message is the transition applied to the next row's (its last row's: ones)
    after = counts[which] - 2 - pos
    following = chain[len(tags) + which, np.maximum(after, 0)]
    message = following.sum(axis=1, keepdims=True) * p_switch[which] + following * gain[which]
    post = chain[which, pos] * np.where(after[:, None] >= 0, message, 1.0)
    post /= post.sum(axis=1, keepdims=True)
    state = np.empty(n, dtype=int)
    posterior = np.empty((n, combos))
    state[order] = path[which, pos]
    posterior[order] = post
    return state, posterior
