"""Interrupt a real sweep many times and count what went wrong, as one JSON line.

    python scripts/interrupt_trials.py [--trials 50] [--seed 0] [--jobs 2]

Each trial (``tests/harness/interrupts.py``) starts ``mpe3d sweep`` in its own
session, interrupts it at a random moment (planning, mid-run, while logging,
while replaying a dead sweep's journal) in a random way (Ctrl-C to the
group, twice, SIGINT or SIGTERM to the main process), then checks: exit 130
within 10 s, the one line last on stderr, no process of its tree alive 10 s
later, and a rerun that completes every config exactly once, losing nothing.
"""
from __future__ import annotations

import argparse
import json
import random
import sys
import tempfile
import time
from collections import Counter
from dataclasses import asdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.harness.interrupts import LAST_LINE, MOMENTS, trial  # noqa: E402

HOWS = ("group-sigint", "group-sigint", "double-sigint", "sigint", "sigterm")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=50)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--verbose", action="store_true", help="one JSON line per trial too")
    args = parser.parse_args(argv)
    rng = random.Random(args.seed)
    outcomes = []
    start = time.time()
    for i in range(args.trials):
        moment, how = MOMENTS[i % len(MOMENTS)], rng.choice(HOWS)
        with tempfile.TemporaryDirectory(prefix="mpe3d-intr-") as folder:
            outcome = trial(Path(folder), moment, rng, how=how, jobs=args.jobs)
        outcomes.append(outcome)
        if args.verbose:
            print(json.dumps({"trial": i, **asdict(outcome), "clean": outcome.clean}), flush=True)
    exits = [o.exit_s for o in outcomes if o.exit_s is not None]
    print(json.dumps({
        "benchmark": "interrupts", "trials": len(outcomes),
        "by_moment": dict(Counter(o.moment for o in outcomes)),
        "by_signal": dict(Counter(o.how for o in outcomes)),
        "too_late": sum(o.too_late for o in outcomes),  # the sweep was over: not an interrupt
        "hangs": sum(o.hung for o in outcomes),
        "bad_exit_code": sum(o.exit_code != 130 for o in outcomes if not o.hung),
        "left_processes": sum(bool(o.left_alive) for o in outcomes),
        "not_one_line": sum(not o.hung and o.exit_code == 130 and o.last_line != LAST_LINE
                            for o in outcomes),
        "lost": sum(o.lost for o in outcomes), "missing_after_rerun": sum(o.missing for o in outcomes),
        "computed_twice": sum(o.computed_twice for o in outcomes),
        "rerun_failed": sum(o.rerun_code != 0 for o in outcomes),
        "clean": sum(o.clean for o in outcomes),
        "exit_s_max": round(max(exits), 2) if exits else None,
        "exit_s_median": round(sorted(exits)[len(exits) // 2], 2) if exits else None,
        "wall_s": round(time.time() - start, 1)}), flush=True)
    return 0 if all(o.clean for o in outcomes) else 1


if __name__ == "__main__":
    sys.exit(main())
