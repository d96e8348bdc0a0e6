"""benchmarks/machine.py: the description a timing is printed with."""
import os

from tests.helpers import load_script


def _machine():
    return load_script("benchmarks/machine.py", "machine_benchmark")


def test_the_description_names_the_cpu_and_times_the_loop_both_ways():
    line = _machine().describe(repeats=1)
    assert line["cpu"] and line["logical_cpus"] == os.cpu_count()
    assert line["solo_s"] > 0 and line["all_at_once_s"] > 0
    assert line["parallel_share"] == round(line["solo_s"] / line["all_at_once_s"], 2)


def test_the_loops_timed_at_once_run_side_by_side():
    """Every process's span (arrival at the start line to the end of its loop)
    holds the moment the line opened, so all spans overlap: the loops ran at
    once, whatever the load. How much they slow each other is a measurement,
    not a test (``python benchmarks/machine.py`` prints ``pinned_share``)."""
    spans = _machine().spans(3)
    assert len(spans) == 3 and all(seconds > 0 for seconds, _, _ in spans)
    assert max(arrived for _, arrived, _ in spans) < min(end for _, _, end in spans)
