"""Plan sweeps against the store: what is done, what is claimed, what is left;
and the journal's replay that comes before any plan."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable

from mpe3d.harness.experiment.config import RunConfig
from mpe3d.harness.experiment.execute import code_of
from mpe3d.harness.experiment.sweep import Sweep
from mpe3d.harness.shutdown import Shutdown
from mpe3d.harness.tracking.journal import Journal


@dataclass
class Plan:
    """One sweep against its experiment: what to run and what is already done."""

    sweep: Sweep
    experiment_id: str
    todo: list[RunConfig]
    skipped_finished: int = 0
    skipped_failed: int = 0
    reused_stale: int = 0  # FINISHED by other code, kept on purpose (--reuse-stale)
    stale: int = 0  # of todo: FINISHED by other code, computed again
    elsewhere: int = 0  # of todo: computed by another sweep while this one ran
    zombies: int = 0  # runs of dead sweeps closed as KILLED when this plan was made
    parent_id: str | None = None
    counts: dict[str, int] = field(default_factory=lambda: {"FINISHED": 0, "FAILED": 0})
    failures: list[tuple[str, str]] = field(default_factory=list)  # (run label, error)
    known: dict[str, set[str]] = field(default_factory=dict)  # hash -> run ids seen when planned
    started: float = 0.0

    @property
    def skipped(self) -> int:
        return self.skipped_finished + self.skipped_failed + self.reused_stale

    @property
    def pending(self) -> int:
        return len(self.todo) - sum(self.counts.values()) - self.elsewhere


class Reporter:
    """Progress callbacks; the default is silent (the CLI shows a progress bar)."""

    def start(self, total: int, skipped: int) -> None: ...

    def advance(self, status: str) -> None: ...

    def stop(self) -> None: ...


def replay_journal(tracker, journal: Journal, stop: Shutdown | None = None) -> int:
    """Log into ``tracker`` the results dead sweeps left in ``journal``; a stop
    request ends it between two entries (the rest wait for the next sweep)."""
    stop = stop or Shutdown()  # not installed: never requested
    replayed = 0
    for entry in journal.orphans(tracker.uri):
        replayed += tracker.replay(entry)
        journal.remove(entry)
        stop.check()
    journal.tidy()
    return replayed


def plan_sweeps(sweeps: Iterable[Sweep], tracker, rerun_failed: bool = False,
                force: bool = False, reuse_stale: bool = False,
                stop: Shutdown | None = None) -> list[Plan]:
    """Decide, per sweep, which runs still need computing.

    First, RUNNING runs whose sweep died are closed as KILLED (counted in the
    first plan of their experiment).

    A config with a FINISHED run by the running code is skipped; one whose
    best such run FAILED is skipped unless ``rerun_failed``; one FINISHED only
    by other code is computed again unless ``reuse_stale``. ``force`` reruns
    everything. Sweeps sharing an experiment never plan one config twice.
    A stop request raises :class:`KeyboardInterrupt` between two sweeps.
    """
    stop = stop or Shutdown()  # not installed: never requested
    plans, planned = [], {}
    for sweep in sweeps:
        stop.check()
        experiment_id = tracker.experiment_id(sweep.name)
        tracker.describe(experiment_id, sweep.description)
        plan = Plan(sweep=sweep, experiment_id=experiment_id, todo=[])
        if experiment_id not in planned:
            plan.zombies = tracker.close_zombies(experiment_id)
        tracked = tracker.tracked(experiment_id, {c.hash(): code_of(c) for c in sweep.runs})
        seen = planned.setdefault(experiment_id, set())
        for config in sweep.runs:
            key = config.hash()
            entry = tracked.get(key)
            status, stale = (entry.status, entry.stale) if entry and not force else (None, 0)
            if key in seen or status == "FINISHED":
                plan.skipped_finished += 1
            elif status == "FAILED" and not rerun_failed:
                plan.skipped_failed += 1
            elif stale and reuse_stale and status is None:
                plan.reused_stale += 1
            else:
                plan.todo.append(config)
                plan.known[key] = entry.known if entry else set()
                plan.stale += bool(stale) and status is None
                seen.add(key)
        plans.append(plan)
    return plans


