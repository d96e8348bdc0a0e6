"""The solver passes' threads: a limit, a map in order, draws in turn."""

import threading
import time

import numpy as np
import pytest

from mpe3d.solvers import threads


def test_limit_nests_and_restores():
    outside = threads.count()
    assert outside == threads.available() >= 1
    with threads.limit(1):
        assert threads.count() == 1
        with threads.limit(3):
            assert threads.count() == 3
        assert threads.count() == 1
    assert threads.count() == outside
    with pytest.raises(ValueError, match="at least 1"):
        with threads.limit(0):
            pass


def test_map_in_order_keeps_the_items_order_and_uses_the_threads():
    seen = set()

    def job(i):
        seen.add(threading.get_ident())
        time.sleep(0.01 * (5 - i % 5))  # later items finish first
        return i * i

    assert threads.map_in_order(job, range(10), 4) == [i * i for i in range(10)]
    assert len(seen) > 1
    seen.clear()
    with threads.limit(1):
        assert threads.map_in_order(job, range(4)) == [0, 1, 4, 9]
    assert seen == {threading.get_ident()}  # one thread: this one


def test_turns_draw_in_the_jobs_order_whatever_the_threads():
    """Jobs that draw from one generator inside their turn get the numbers they
    get on one thread, however long each one's work before or after takes."""
    def draws(n_threads):
        rng, turns = np.random.default_rng(7), threads.InTurn()

        def job(numbered):
            number, size = numbered
            time.sleep(0.002 * (size % 3))
            with turns.turn(number):
                drawn = rng.random(size)
            time.sleep(0.002 * (2 - size % 3))
            return drawn

        return threads.map_in_order(job, enumerate([5, 1, 7, 3, 2, 8, 4, 6] * 3), n_threads)

    one = draws(1)
    for n in (2, 5):
        assert all(np.array_equal(a, b) for a, b in zip(draws(n), one))


def test_an_even_split_covers_every_item_once():
    work = np.array([9.0, 1, 1, 1, 0, 5, 3, 0])
    for parts in range(1, 10):
        bounds = threads.even_split(work, parts)
        assert bounds[0] == 0 and bounds[-1] == len(work)
        assert np.all(np.diff(bounds) > 0) and len(bounds) - 1 <= parts
    assert list(threads.even_split(np.zeros(4), 2)) == [0, 4]
