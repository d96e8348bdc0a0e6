"""What a timing was measured on, for a benchmark's JSON line.

    python benchmarks/machine.py

The targets are wall times on 2 cores, and the development machine's speed
moved by 2x between two sessions on the same code (see
docs/results/2026-12-06-targets-on-a-faster-machine.md): 1.4x on one core,
2x on a two-worker reproduction. A CPU's name does not tell that apart on a
virtual machine ("AMD EPYC"), so :func:`describe` also times a fixed piece of
interpreter work alone and on every logical CPU at once. ``all_at_once_s``
near ``solo_s`` means the CPUs are really as many cores. Near twice it means
they share one, and a sweep's workers slow each other down.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import platform
import time

_WORK = 6_000_000  # about 0.3 s of the interpreter on the development machine


def _spin() -> float:
    """Seconds for a fixed loop of integer arithmetic (no BLAS, little memory traffic)."""
    start = time.perf_counter()
    total = 0
    for i in range(_WORK):
        total += i * i % 7
    return time.perf_counter() - start


def _spin_after(barrier, results) -> None:
    arrived = time.monotonic()  # system-wide: comparable between processes
    barrier.wait()  # every process starts its loop at once
    seconds = _spin()
    results.put((seconds, arrived, time.monotonic()))


def spans(count: int) -> list[tuple[float, float, float]]:
    """(loop seconds, arrival at the start line, end) of ``count`` processes
    that run the loop at the same time. Each span holds the moment the start
    line opened, so the spans overlap: the loops were timed side by side."""
    context = multiprocessing.get_context("fork")
    barrier, results = context.Barrier(count, timeout=120), context.Queue()
    workers = [context.Process(target=_spin_after, args=(barrier, results)) for _ in range(count)]
    for worker in workers:
        worker.start()
    out = [results.get(timeout=300) for _ in workers]
    for worker in workers:
        worker.join()
    return out


def at_once(count: int) -> float:
    """The slowest of ``count`` processes that run the loop at the same time."""
    return max(seconds for seconds, _, _ in spans(count))


def pinned_share(repeats: int = 3) -> float | None:
    """Two loops pinned to one CPU against one alone: about 2 (they share it).
    None where CPU affinity is not offered."""
    if not hasattr(os, "sched_setaffinity"):
        return None
    cpus = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {min(cpus)})  # the forked processes inherit it
    try:
        solo = min(at_once(1) for _ in range(repeats))
        together = min(at_once(2) for _ in range(repeats))
    finally:
        os.sched_setaffinity(0, cpus)
    return round(together / solo, 2)


def cpu_name() -> str:
    """The CPU's model name, from /proc/cpuinfo where there is one."""
    try:
        with open("/proc/cpuinfo") as info:
            for line in info:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def describe(repeats: int = 3) -> dict:
    """The CPU's name, its logical CPUs, and the best of ``repeats`` timings of
    the same loop alone and on every logical CPU at once."""
    cpus = os.cpu_count() or 1
    # rounded first, so that the share printed is the ratio of the times printed
    solo = round(min(at_once(1) for _ in range(repeats)), 3)
    together = round(min(at_once(cpus) for _ in range(repeats)), 3)
    return {"cpu": cpu_name(), "logical_cpus": cpus, "solo_s": solo,
            "all_at_once_s": together, "parallel_share": round(solo / together, 2)}


if __name__ == "__main__":
    # pinned_share checks the measurement itself: two loops on one CPU take about twice one
    print(json.dumps({"benchmark": "machine", **describe(), "pinned_share": pinned_share()}))
