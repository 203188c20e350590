"""StepsAhead: a generator's steps taken one at a time, whether or not some were computed ahead."""

import numpy as np
import pytest

from rover.operators.slam.steps_ahead import StepsAhead


def counted(steps: int, log: list[int]):
    for k in range(steps):
        log.append(k)
        yield
    return f"after {steps}"


def taken(steps) -> tuple[int, object]:
    n = 0
    while True:
        try:
            next(steps)
        except StopIteration as stop:
            return n, stop.value
        n += 1


@pytest.mark.parametrize("seed", range(5))
def test_steps_computed_ahead_or_not_are_taken_alike(seed):
    """Whatever steps were computed ahead, and when: the caller takes as many steps and gets the
    same value as from the generator itself, and no step is computed twice."""
    rng = np.random.default_rng(seed)
    for steps in (0, 1, 7):
        log: list[int] = []
        ahead = StepsAhead(counted(steps, log))
        n = 0
        while True:
            for _ in range(int(rng.integers(0, 4))):
                ahead.ahead()
            try:
                next(ahead)
            except StopIteration as stop:
                value = stop.value
                break
            n += 1
        assert (n, value) == taken(counted(steps, [])) == (steps, f"after {steps}")
        assert log == list(range(steps))
        assert not ahead.pending


def test_steps_computed_ahead_are_done_when_taken():
    log: list[int] = []
    ahead = StepsAhead(counted(3, log))
    assert ahead.pending and log == []
    ahead.ahead()
    ahead.ahead()
    assert log == [0, 1]
    next(ahead)
    next(ahead)
    assert log == [0, 1], "the steps computed ahead are not computed again"
    next(ahead)
    assert log == [0, 1, 2]
    ahead.ahead()  # the generator ends: its value is kept for the caller
    assert not ahead.pending
    with pytest.raises(StopIteration) as stop:
        next(ahead)
    assert stop.value.value == "after 3"
