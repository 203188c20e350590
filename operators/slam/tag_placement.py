"""What the tag searches' results do to the window: a tag found is put in use at its place, and a
check search over a tag in use may move it there or hold it unpublished. The searches are
`tag_finder` (which is due) and `tag_search` (the search itself); this is where their ends change
the window's states, prior and integrity."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from rover.operators.slam.layout import positions, prior_tag
from rover.operators.slam.tag_finder import Search, found_tag_info, gone_bearings
from rover.operators.slam.tag_search import Found

if TYPE_CHECKING:
    from rover.operators.slam.sliding_window import SlidingWindow


def find_tags(w: SlidingWindow, steps: int | None = None) -> int:
    """Advance the searches due by at most `steps` steps (None: until every search due has run);
    returns the steps taken. The tag waiting longest goes first, then the checks of tags in use,
    one search at a time, each from the robot positions of when it started; a tag found is in use
    from the next update (TagFinder).

    Done between updates, not in them, a few steps at a time (tag_search.search_steps): a whole
    search costs several updates' time, and no pose need wait for it. Steps computed ahead
    (StepsAhead.ahead, in the operator's idle time) are taken here at no cost."""
    finder = w.finder
    taken = 0
    while steps is None or taken < steps:
        if finder.searching is None:
            xy = positions(w.x, len(w.epochs))
            finder.searching = finder.next_search({e.stamp_ns: xy[k] for k, e in enumerate(w.epochs)}, w.active)
            if finder.searching is None:
                break
        taken += 1
        try:
            next(finder.searching.steps)
        except StopIteration as done:
            run, finder.searching = finder.searching, None
            if run.check:
                _checked(w, run, done.value)
                continue
            finder.last[run.tag] = done.value
            if done.value is not None and done.value.clear(finder.search):
                _place(w, run, done.value)
    return taken


def _checked(w: SlidingWindow, run: Search, found: Found | None) -> None:
    """A check search over a tag in use ended (TagFinder.contradiction). Put elsewhere decisively by
    a search whose place is clear, the tag is put there as a found tag is, its jump history started
    again from the search's choices; otherwise doubted (put elsewhere, or another place fitting as
    well), it is not published as localized until a check finds its place the search's best
    (`TagIntegrity.doubt`)."""
    t = run.tag
    doubt = w.finder.contradiction(run, found, w.x[w.shape.tag(t)])
    if doubt is not None and doubt.decisive and found is not None and found.clear(w.finder.search):
        _place(w, run, found)  # where the search puts it, on the evidence a found tag needs
        doubt = None
    w.integrity.doubt(t, None if doubt is None else doubt.reason)


def _place(w: SlidingWindow, run: Search, found: Found) -> None:
    """Put the tag the search found in use at its place (also after a check moved it)."""
    oldest = w.epochs[0].stamp_ns if w.epochs else 0
    s = w.settings
    info = found_tag_info(run, found, oldest, s.tag_prior_std_m, s.aoa_std_scale)
    _activate(w, run.tag, found, info, run.bearings.jumps)
    robot, angles, stds = gone_bearings(run, found, oldest)
    w.integrity.start(run.tag, robot, angles, stds * s.aoa_std_scale)
    w.finder.settle(w.tag_ids[run.tag], run, found)


def _activate(w: SlidingWindow, t: int, found: Found, info: np.ndarray, jumps: np.ndarray) -> None:
    """Put a found tag in use: at its position, with `info` as its prior, and its bearings' jump
    combinations as the first history of its jump state."""
    w.x[w.shape.tag(t)] = found.position
    p = w.prior
    assert p is not None, "a search runs only once the window has epochs"
    at = np.arange(p.info.shape[0])[prior_tag(t)]
    p.info[at, :] = 0.0
    p.info[:, at] = 0.0
    p.info[np.ix_(at, at)] = info
    p.mean[at] = found.position
    p.grad[at] = 0.0
    w.active[t] = True
    w.finder.placed[t] = len(w.finals) + len(w.epochs)
    inlier = found.choice >= 0
    w.jumps.start(t, jumps[np.flatnonzero(inlier), found.choice[inlier]])  # the search's evidence
