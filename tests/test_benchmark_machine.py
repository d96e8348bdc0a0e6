"""benchmarks/machine.py: the description a timing is printed with."""
import os

import pytest

from tests.helpers import load_script


def _machine():
    return load_script("benchmarks/machine.py", "machine_benchmark")


def test_the_description_names_the_cpu_and_times_the_loop_both_ways():
    line = _machine().describe(repeats=1)
    assert line["cpu"] and line["logical_cpus"] == os.cpu_count()
    assert line["solo_s"] > 0 and line["all_at_once_s"] > 0
    assert line["parallel_share"] == round(line["solo_s"] / line["all_at_once_s"], 2)


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="needs CPU affinity (Linux)")
def test_two_processes_on_one_core_are_seen_sharing_it():
    """The loops really run at once: pinned to one CPU, two of them take about
    twice as long as one (were they run one after the other, as long)."""
    machine = _machine()
    cpus = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {min(cpus)})  # the forked processes inherit it
    try:
        solo = min(machine.at_once(1) for _ in range(3))
        together = min(machine.at_once(2) for _ in range(2))
    finally:
        os.sched_setaffinity(0, cpus)
    assert together > 1.5 * solo, (solo, together)
