"""The window's side of the search for tags whose bearings carry several candidates: what it keeps
of their bearings, which search is due (a waiting tag's, or the check of a tag in use), the prior
a found tag starts with, and what a check says against the window's place for a tag. The search
itself is `tag_search` (pure functions over bearings)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from rover.operators.slam.epoch import padded_rows
from rover.operators.slam.search_scores import Bearings, model_costs
from rover.operators.slam.steps_ahead import StepsAhead
from rover.operators.slam.tag_search import Found, SearchSettings, elsewhere, search_steps

SEARCH_HISTORY = 400
"""bearings kept per tag with jump candidates, for its search and then its checks (the latest)"""
SEARCH_EVERY = 4
"""new bearings of a waiting tag between two searches"""
CHECK_EVERY = 40
"""new bearings of a tag in use between two searches that check the window's place for it
(`contradiction`): the search weighs every candidate of every bearing, where the window weighs
those it chose to fit its place (a place 2.7 m off, chosen into, explained its NLOS tag's bearings
at 24 deg of median residual against 59 at the true place; the search over the same bearings put
it 0.3 m from the truth)"""
SEARCH_INFO_SCALE = 0.25
"""share of the information of a found tag's earlier bearings kept as its prior (their robot
positions are taken as known, which they are not quite)"""


@dataclass(frozen=True)
class Doubt:
    """What a check search says against the window's place for a tag: why, and whether it puts the
    tag elsewhere on the evidence that settles a place (else the two places fit alike)."""

    reason: str
    decisive: bool


@dataclass
class Search:
    """A tag search under way: the tag slot, what it searches (the bearings and their stamps, for
    putting the tag in use), and its remaining steps (some perhaps computed ahead: StepsAhead)."""

    tag: int
    stamps: np.ndarray
    bearings: Bearings
    steps: StepsAhead[Found | None]
    check: bool = False
    """a search over the bearings of a tag in use, checking the window's place for it"""


@dataclass
class TagFinder:
    """The tags waiting for the search, by tag slot, and what the search found."""

    search: SearchSettings = field(default_factory=SearchSettings)
    history: dict[int, list[tuple[int, np.ndarray, np.ndarray, np.ndarray]]] = field(default_factory=dict)
    """per tag slot waiting for the search: (stamp, world candidate angles, stds, jumps) of its bearings"""
    heard: dict[int, int] = field(default_factory=dict)
    """per tag slot: bearings with several candidates heard so far"""
    searched: dict[int, int] = field(default_factory=dict)
    """per tag slot: `heard` at its last search"""
    final_xy: dict[int, np.ndarray] = field(default_factory=dict)
    """robot position of each epoch that left the window, by stamp"""
    found: list[tuple[int, Found]] = field(default_factory=list)
    """(tag id, search result) of every tag the search localized, in order"""
    last: dict[int, Found | None] = field(default_factory=dict)
    """per tag slot: what its latest search found, clear or not (None: too few bearings or no crossing)"""
    searching: Search | None = field(default=None, repr=False)
    """the tag search under way, if any"""
    placed: dict[int, int] = field(default_factory=dict)
    """per tag slot the search placed: the epoch count when it did, or when the window last relaxed
    its prior for disagreeing bearings (re-examined it)"""
    checked: dict[int, int] = field(default_factory=dict)
    """per tag slot in use: `heard` when the search placed it or its latest check started"""

    def reexamined(self, tag_slot: int, epochs: int) -> None:
        """The window relaxed the tag's prior at the epoch count `epochs`: if the search placed it,
        the convex passes start it again."""
        if tag_slot in self.placed:
            self.placed[tag_slot] = epochs

    def starting(self, localized: np.ndarray, epochs: int, window_epochs: int) -> np.ndarray:
        """Per tag slot, at the epoch count `epochs`: whether the window's convex program is still
        there to start it. A tag not localized is, unless the search placed (or the window
        re-examined) it more than `window_epochs` ago: by then the window's last estimate is as good
        a start for its Gauss-Newton steps (a tag never placed is started until localized)."""
        start = ~localized
        for t, at in self.placed.items():
            start[t] &= epochs - at <= window_epochs
        return start

    def hear(self, tag_slot: int, stamp_ns: int, angles: np.ndarray, stds: np.ndarray, jumps: np.ndarray) -> None:
        """A bearing with several candidates of a tag (world-frame angles, their raw stds, jumps)."""
        kept = self.history.setdefault(tag_slot, [])
        kept.append((stamp_ns, angles, stds, jumps))
        self.heard[tag_slot] = self.heard.get(tag_slot, 0) + 1
        del kept[:-SEARCH_HISTORY]

    def next_search(self, window_xy: dict[int, np.ndarray], active: list[bool]) -> Search | None:
        """The search of the tag waiting longest among those due (its history grew by SEARCH_EVERY
        since its last one), else the check of the tag in use longest unchecked among those due
        (CHECK_EVERY), started from the robot positions known now: those that left the window, and
        `window_xy` (by stamp) for the others. None: none is due."""
        due = [t for t in self.history if not active[t] and self.heard[t] >= self.searched.get(t, 0) + SEARCH_EVERY]
        for t in sorted(due, key=lambda t: self.searched.get(t, 0) - self.heard[t]):
            self.searched[t] = self.heard[t]
            if (run := self._search(t, window_xy, check=False)) is not None:
                return run
        checks = [t for t, at in self.checked.items() if active[t] and self.heard[t] >= at + CHECK_EVERY]
        for t in sorted(checks, key=lambda t: self.checked[t] - self.heard[t]):
            self.checked[t] = self.heard[t]
            if (run := self._search(t, window_xy, check=True)) is not None:
                return run
        return None

    def _search(self, t: int, window_xy: dict[int, np.ndarray], check: bool) -> Search | None:
        """A search over tag slot t's history (None: too few of its bearings have a robot position)."""
        known = ((st, self.final_xy.get(st, window_xy.get(st)), row) for st, *row in self.history[t])
        rows = [(st, xy, row) for st, xy, row in known if xy is not None]
        if len(rows) < self.search.min_bearings:
            return None
        width = max(len(row[0]) for _, _, row in rows)

        def padded(i: int, pad: float) -> np.ndarray:
            return padded_rows([row[i][None, :] for _, _, row in rows], width, pad)

        robot = np.array([xy for _, xy, _ in rows])
        angles, stds, jumps = padded(0, np.nan), padded(1, 1.0), padded(2, -1).astype(int)
        stamps = np.array([st for st, _, _ in rows])
        bearings = Bearings((stamps - stamps[0]) * 1e-9, robot, angles, stds, jumps)
        return Search(t, stamps, bearings, StepsAhead(search_steps(bearings, self.search)), check)

    def settle(self, tag_id: int, run: Search, found: Found) -> None:
        """The search found the tag (or a check placed it again): it waits no more, and its checks
        count its bearings from here. Its history is kept for them."""
        self.found.append((tag_id, found))
        self.checked[run.tag] = self.heard[run.tag]

    def contradiction(self, run: Search, found: Found | None, place: np.ndarray) -> Doubt | None:
        """What a check search over a tag's bearings says against the window's `place` for it
        (None: nothing; its best is the same place, or it found none). Its best elsewhere, the
        bearings, every candidate weighed, either cost at least the search's `min_margin` less there
        than at `place` (the evidence the search needs to settle a place: `decisive`), or fit both
        places within it: the evidence does not tell them apart."""
        if found is None or not elsewhere(run.bearings.robot, place, found.position, self.search):
            return None
        worse = float(model_costs(place[None], run.bearings, self.search.cap_sigma).min()) - found.score
        x, y = found.position
        away = float(np.linalg.norm(found.position - place))
        decides = self.search.min_margin
        where = f"a search over its {len(run.bearings)} bearings"
        there = f"({x:.2f}, {y:.2f}) m, {away:.2f} m away"
        if worse >= decides:
            return Doubt(
                f"{where} puts it at {there}, where they fit better by {worse:.0f} ({decides:.0f} decides)", True
            )
        return Doubt(
            f"{where} fits them about as well at {there} (within {max(worse, 0.0):.0f}; {decides:.0f} decides)", False
        )


def why_waiting(found: Found | None, s: SearchSettings) -> str:
    """Why a tag the search has not localized is not: what its latest search found."""
    if found is None:
        return f"its bearings did not triangulate (fewer than {s.min_bearings}, or rays that never crossed)"
    missing = []
    if found.margin < s.min_margin:
        missing.append(f"another place fits within {found.margin:.0f} of its cost ({s.min_margin:.0f} needed)")
    if found.inliers < s.min_inliers:
        missing.append(f"{100 * found.inliers:.0f}% of its bearings agree ({100 * s.min_inliers:.0f}% needed)")
    if found.parallax_deg < s.min_parallax_deg:
        missing.append(f"seen over {found.parallax_deg:.0f} deg ({s.min_parallax_deg:.0f} needed)")
    x, y = found.position
    return f"the search's best place ({x:.2f}, {y:.2f}) m is not clear: " + "; ".join(missing)


def gone_bearings(run: Search, found: Found, oldest_stamp_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The found tag's inlier bearings that already left the window (before `oldest_stamp_ns`):
    robot positions (n, 2), the world angles of the candidates the search chose, their stds."""
    gone = np.flatnonzero((found.choice >= 0) & (run.stamps < oldest_stamp_ns))
    b = run.bearings
    return b.robot[gone], b.angles[gone, found.choice[gone]], b.stds[gone, found.choice[gone]]


def found_tag_info(
    run: Search, found: Found, oldest_stamp_ns: int, tag_prior_std_m: float, aoa_std_scale: float
) -> np.ndarray:
    """The 2x2 information a found tag starts with: the new-tag prior, plus the information of its
    bearings that already left the window (before `oldest_stamp_ns`), their robot positions taken as
    known, so weighed down by SEARCH_INFO_SCALE."""
    robot, _, stds = gone_bearings(run, found, oldest_stamp_ns)
    info = np.eye(2) * tag_prior_std_m**-2
    if len(robot):
        d = found.position[None, :] - robot
        std = stds * aoa_std_scale
        jac = np.stack([-d[:, 1], d[:, 0]], axis=1) / (np.maximum(np.sum(d**2, axis=1), 1e-6) * std)[:, None]
        info = info + SEARCH_INFO_SCALE * jac.T @ jac
    return info
