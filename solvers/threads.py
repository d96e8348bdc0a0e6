"""The threads mpe3d's own solver passes may use: the reduced camera system
of bundle adjustment, split by views, and the two-view tests of wrong
matches, split by view pairs.

Every pass splits work whose pieces are computed alone, each in a fixed
order, and draws its random numbers in one order whatever the split, so a
result is the same bits for any thread count. BLAS is left alone
(``threadpoolctl`` limits it): its sums do depend on its thread count.

A user's command (``mpe3d reconstruct``) uses every core this process may
run on; a sweep's worker runs with :func:`limit` (1), because a sweep gets
its parallelism from running several runs at once.
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor

import numpy as np

_limit: int | None = None  # None: every core this process may run on


def available() -> int:
    """The cores this process may run on (its CPU affinity where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


def count() -> int:
    """The threads a solver pass may use now: :func:`limit`'s, else :func:`available`."""
    return _limit if _limit is not None else available()


@contextlib.contextmanager
def limit(threads: int) -> Iterator[None]:
    """Solver passes inside the block use at most ``threads`` threads (>= 1)."""
    global _limit
    if int(threads) < 1:
        raise ValueError(f"threads: expected at least 1, got {threads}")
    previous, _limit = _limit, int(threads)
    try:
        yield
    finally:
        _limit = previous


def map_in_order(func: Callable, items: Iterable, threads: int | None = None) -> list:
    """[func(item) for item in items], on up to ``threads`` threads (default
    :func:`count`); ``func`` must release the GIL for most of its time (a
    ``nogil`` kernel, large numpy operations) to gain anything."""
    items = list(items)
    threads = min(count() if threads is None else threads, len(items))
    if threads <= 1:
        return [func(item) for item in items]
    with ThreadPoolExecutor(threads) as pool:
        return list(pool.map(func, items))


def map_drawn(draw: Callable, func: Callable, items: Iterable, threads: int | None = None) -> list:
    """[func(item, draw(item)) for item in items], on up to ``threads`` threads
    (:func:`map_in_order`), every ``draw(item)`` called in the items' order:
    ``draw`` takes an item's random numbers from one generator, so each item
    gets the numbers it gets on one thread, and the result is the same bits
    for any thread count."""
    turns = InTurn()

    def job(numbered):
        number, item = numbered
        with turns.turn(number):
            drawn = draw(item)
        return func(item, drawn)

    return map_in_order(job, enumerate(items), threads)


def even_split(work: np.ndarray, parts: int) -> np.ndarray:
    """Bounds 0 = b_0 <= ... <= b_m = len(work) of at most ``parts`` ranges of
    about equal total ``work``."""
    parts = max(1, min(int(parts), len(work)))
    cumulative = np.cumsum(work)
    if parts == 1 or not len(work) or cumulative[-1] <= 0:
        return np.array([0, len(work)])
    cuts = np.searchsorted(cumulative, cumulative[-1] * np.arange(1, parts) / parts)
    return np.unique(np.concatenate([[0], cuts + 1, [len(work)]]).clip(0, len(work)))


class InTurn:
    """Sections entered in the order of their numbers 0, 1, 2, ..., whichever
    thread runs them (:func:`map_drawn` uses it): the random draws of jobs run
    by :func:`map_in_order`, taken from one generator in the jobs' order, so
    that every job gets the numbers it gets on one thread. (The map starts the
    jobs in order, so the job a section waits for has always started.)"""

    def __init__(self) -> None:
        self._next = 0
        self._changed = threading.Condition()

    @contextlib.contextmanager
    def turn(self, number: int) -> Iterator[None]:
        with self._changed:
            self._changed.wait_for(lambda: self._next == number)
        try:
            yield
        finally:
            with self._changed:
                self._next += 1
                self._changed.notify_all()
