"""A generator's steps, some computed ahead of when they are taken.

The tag search is spread over epochs a few steps at a time (SEARCH_STEPS_PER_EPOCH), so that a
search starts and ends at the same epochs however fast the machine is: a replay gives the live
run's outputs. Taken inline, those steps delay the next epoch by their whole cost (20-50 ms on a
live laptop, as long as a dwell). While the operator waits for its next input it computes them
ahead (`Operator.on_idle`), in its own thread: the epoch that takes them then finds them done.
(A thread of their own was tried: it held the interpreter lock against the operator's update
and sent the live poses later, not sooner.)"""

from __future__ import annotations

from collections.abc import Generator, Iterator
from typing import Generic, TypeVar

T = TypeVar("T")


class StepsAhead(Iterator[None], Generic[T]):
    """Iterates like `steps` (each `next` one of its steps, then StopIteration with its value),
    whether or not `ahead` already computed them."""

    def __init__(self, steps: Generator[None, None, T]) -> None:
        self._steps = steps
        self._computed = 0
        """steps computed ahead and not taken yet"""
        self._finished = False
        self._value: T | None = None

    @property
    def pending(self) -> bool:
        """Whether steps remain to compute."""
        return not self._finished

    def ahead(self) -> None:
        """Compute the next step now (nothing once all are)."""
        if self._step():
            self._computed += 1

    def __next__(self) -> None:
        if self._computed:
            self._computed -= 1
            return
        if not self._step():
            raise StopIteration(self._value)

    def _step(self) -> bool:
        """Run one step; False once the generator has finished (its value kept)."""
        if self._finished:
            return False
        try:
            next(self._steps)
        except StopIteration as stop:
            self._finished, self._value = True, stop.value
            return False
        return True
