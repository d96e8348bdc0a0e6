"""The run loop: claim a config, compute it on a pool, write its record to the
journal, log it to MLflow, drop it from the journal."""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import logging
import random
import time
from collections import deque
from dataclasses import dataclass

from mpe3d import plugins
from mpe3d.errors import DiskFull, MpeError, StoreError
from mpe3d.harness.experiment.config import BACKENDS, RunConfig
from mpe3d.harness.experiment.execute import code_of, expected_work, failed_record, run_record
from mpe3d.harness.files import Reserve, SpaceMeter, human_bytes, same_device
from mpe3d.harness.runner.plan import Plan, Reporter
from mpe3d.harness.runner.pools import pool
from mpe3d.harness.shutdown import GRACE_S, Shutdown
from mpe3d.harness.tracking.journal import Journal
from mpe3d.harness.tracking.ownership import Heartbeat, Owner
from mpe3d.harness.tracking.records import RunRecord

POLL_S = 2.0  # how often a sweep looks again at a claim of another sweep it waits for
DRAIN_S = 10.0  # after the store fails: how long runs in flight may still finish
log = logging.getLogger(__name__)


@dataclass
class Task:
    plan: Plan
    config: RunConfig
    run_id: str | None = None  # our claim
    next_look: float = 0.0  # when to look again at another sweep's claim

    @property
    def code(self) -> str:
        return code_of(self.config)


class Loop:
    """Claim, compute, journal, log: one sweep invocation's runs."""

    def __init__(self, plans, tracker, pool, journal: Journal, artifacts: bool, reporter: Reporter,
                 reserve: Reserve | None = None):
        self.tracker, self.pool, self.journal = tracker, pool, journal
        self.reserve = reserve or Reserve(None)
        self.artifacts, self.reporter = artifacts, reporter
        self.owner = Owner.current()
        self.plans = plans
        # longest first (a stable sort: ties keep the sweep's order), so that the
        # last runs to finish are short ones and no worker idles at the end
        self.queue = deque(sorted((Task(plan, config) for plan in plans for config in plan.todo),
                                  key=lambda task: -expected_work(task.config)))
        self.in_flight: dict[cf.Future, Task] = {}
        self.waiting: list[Task] = []  # claimed by another live sweep
        self.open_parents = [p.parent_id for p in plans if p.parent_id]
        self.foreign_code: set[str] = set()
        self.plugin_files = tuple(str(p) for p in plugins.loaded_files())  # each worker loads them too
        self.space = SpaceMeter([journal.folder, *tracker.local_folders()])
        self.logged = 0  # results in the store or the journal
        self.lost = 0  # computed, but no room anywhere to keep them: computed again next time
        self.unlogged: list[str] = []  # claims whose result the store refused: still RUNNING there

    def run(self, heartbeat: Heartbeat, stop: Shutdown) -> bool:
        """Compute and log every task; False when ``stop`` was requested first
        (then :meth:`wind_down` is next)."""
        while self.queue or self.in_flight or self.waiting:
            self._fill(stop)
            if self.in_flight:
                done, _ = cf.wait([*self.in_flight, stop.requested], timeout=POLL_S,
                                  return_when=cf.FIRST_COMPLETED)
                if stop.stopping:  # a failure seen now may be the interrupt's doing
                    return False
                for future in done:
                    self._finish(future, self.in_flight.pop(future))
            elif self.waiting:
                cf.wait([stop.requested], timeout=min(
                    POLL_S, max(0.0, min(t.next_look for t in self.waiting) - time.time())))
            if stop.stopping:
                return False
            self._look_at_waiting()
            if heartbeat.error is not None:  # a StoreError naming the store already
                raise heartbeat.error
        return True

    def _fill(self, stop: Shutdown) -> None:
        while self.queue and len(self.in_flight) < self.pool.capacity and not stop.stopping:
            task = self.queue.popleft()
            plan, key = task.plan, task.config.hash()
            state, other = self.tracker.claim(plan.experiment_id, plan.parent_id, key,
                                              plan.sweep.label(task.config), self.owner,
                                              plan.known[key], task.code)
            if state == "won":
                task.run_id = other
                future = self.pool.submit(run_record, task.config, self.artifacts, self.plugin_files)
                self.in_flight[future] = task
            elif state == "busy":
                task.next_look = time.time() + POLL_S * random.uniform(0.5, 1.5)
                self.waiting.append(task)
            else:
                self._done_elsewhere(task)

    def _look_at_waiting(self) -> None:
        now = time.time()
        for task in [t for t in self.waiting if t.next_look <= now]:
            plan = task.plan
            state, _ = self.tracker.claim_state(plan.experiment_id, task.config.hash(),
                                                plan.known[task.config.hash()], task.code)
            if state == "busy":
                task.next_look = now + POLL_S * random.uniform(0.5, 1.5)
                continue
            self.waiting.remove(task)
            if state == "free":  # its owner died or withdrew: ours to claim
                self.queue.appendleft(task)
            else:
                self._done_elsewhere(task)

    def _done_elsewhere(self, task: Task) -> None:
        task.plan.elsewhere += 1
        self.reporter.advance("ELSEWHERE")
        self._close_if_done(task.plan)

    def _meta(self, task: Task) -> dict:
        plan = task.plan
        return {"uri": self.tracker.uri, "experiment": plan.sweep.name,
                "experiment_id": plan.experiment_id, "parent_id": plan.parent_id,
                "run_id": task.run_id, "run_name": plan.sweep.label(task.config),
                "owner": self.owner.tag()}

    def _record(self, future: cf.Future, task: Task) -> RunRecord:
        try:
            return future.result()
        except Exception as exc:  # noqa: BLE001 - a worker that died (OOM, segfault, killed)
            return failed_record(task.config, f"its worker died: {type(exc).__name__}: {exc}")

    def _finish(self, future: cf.Future, task: Task) -> None:
        record = self._record(future, task)
        try:
            entry = self.journal.write(record, self._meta(task))  # on disk before the store
        except DiskFull:
            self._unjournaled(task, record)
            raise
        try:
            self.tracker.log_record(task.run_id, record, artifacts=self.artifacts)
        except StoreError:
            self.unlogged.append(task.run_id)  # journaled: closed as KILLED, replayed next time
            raise
        self.journal.remove(entry)
        self._count(task, record)

    def _unjournaled(self, task: Task, record: RunRecord) -> None:
        """No room for the journal: the store may still have some (another disk)."""
        try:
            self.tracker.log_record(task.run_id, record, artifacts=self.artifacts)
        except StoreError:
            self.lost += 1
            self.unlogged.append(task.run_id)
        else:
            self._count(task, record)

    def _count(self, task: Task, record: RunRecord) -> None:
        self.logged += 1
        plan = task.plan
        plan.counts[record.status] += 1
        if record.error:
            plan.failures.append((plan.sweep.label(task.config), record.error))
        if record.code != task.code and record.code not in self.foreign_code:
            self.foreign_code.add(record.code)
            log.warning("a worker runs other code (%s, not %s): its runs are tracked as such "
                        "and will not count as done for this code", record.code, task.code)
        self.reporter.advance(record.status)
        self._close_if_done(plan)

    def _close_if_done(self, plan: Plan) -> None:
        if plan.pending == 0 and plan.parent_id in self.open_parents:
            self.open_parents.remove(plan.parent_id)
            close_parent(self.tracker, plan, "FINISHED")

    def wind_down(self, stop: Shutdown, grace_s: float = GRACE_S) -> None:
        """Stopped: dispatch nothing more, give running workers ``grace_s`` (none
        after a second signal) to finish and be logged, terminate the pool,
        then close our claims and parents as KILLED. Every run logged stays."""
        self.queue.clear()
        self.waiting.clear()  # claimed by other sweeps: nothing of ours to close
        # the pools run their calls in the order given: the oldest are the ones running,
        # those queued behind them are not started, so not waited for
        running = set(list(self.in_flight)[:self.pool.workers])
        deadline = time.monotonic() + grace_s
        while running & self.in_flight.keys() and not stop.hurry.is_set() \
                and time.monotonic() < deadline:
            done, _ = cf.wait(running & self.in_flight.keys(), return_when=cf.FIRST_COMPLETED,
                              timeout=min(0.2, deadline - time.monotonic()))
            self._keep(done)
        self.pool.terminate()
        self._keep([future for future in self.in_flight if future.done()])
        abandoned = [task.run_id for task in self.in_flight.values()]
        self.in_flight.clear()
        self.interrupted(abandoned + self.unlogged)

    def _keep(self, done) -> None:
        """Log what completed; a future that failed while stopping was cut short
        by the stop itself and stays in flight, to be closed as KILLED."""
        for future in done:
            if future.cancelled() or future.exception() is not None:
                continue
            task = self.in_flight.pop(future)
            try:
                self._finish(future, task)
            except StoreError:  # journaled first: the next sweep replays it
                pass

    def drain(self, error: StoreError) -> StoreError:
        """The store failed: keep in the journal what finishes within DRAIN_S
        (nothing is waited for when the journal's disk is the full one)."""
        full = isinstance(error, DiskFull)
        wait = 0.0 if full and same_device(error.path, self.journal.folder) else DRAIN_S
        deadline, journaled = time.monotonic() + wait, []
        while self.in_flight and time.monotonic() < deadline:
            done, _ = cf.wait(self.in_flight, timeout=deadline - time.monotonic(),
                              return_when=cf.FIRST_COMPLETED)
            for future in done:
                task = self.in_flight.pop(future)
                try:
                    self.journal.write(self._record(future, task), self._meta(task))
                except DiskFull:
                    self.lost, deadline = self.lost + 1, 0.0
                    continue
                journaled.append(task.run_id)
                self.logged += 1
        abandoned = [task.run_id for task in self.in_flight.values()]
        self.pool.terminate()
        kept = self.journal.pending(self.tracker.uri)
        self.reserve.release()  # the room to close the runs below
        if not full:  # an unreachable store would only make closing its runs wait
            return StoreError(f"{error.message}; stopped: {kept} computed result(s) wait in "
                              f"{self.journal.folder} and go into the store at the next run of "
                              f"this command; {len(abandoned)} run(s) in flight abandoned")
        self.interrupted(abandoned + journaled + self.unlogged, reason="no space left on the device")
        return DiskFull(self._no_space(error, kept), error.path)

    def _no_space(self, error: DiskFull, kept: int) -> str:
        left = sum(plan.pending for plan in self.plans)
        need = self.space.needed(error.path, self.logged, left)
        text = f"{error.message}; stopped, every finished run kept"
        if kept:
            text += f" ({kept} in {self.journal.folder}, logged at the next run of this command)"
        if self.lost:
            text += f"; {self.lost} result(s) with no room anywhere are computed again"
        more = f"about {human_bytes(need)} more" if need else "more space"
        return text + f"; the {left} run(s) left need {more} there: free it and run the same command"

    def interrupted(self, abandoned: list[str], reason: str = "the sweep was interrupted") -> None:
        """Close the ``abandoned`` claims and our open parents as KILLED."""
        with contextlib.suppress(Exception):
            self.tracker.kill(abandoned, reason)
        for plan in self.plans:
            if plan.parent_id in self.open_parents:
                with contextlib.suppress(Exception):
                    close_parent(self.tracker, plan, "KILLED")


def run_plans(plans: list[Plan], tracker, *, jobs: int = -1, backend: str = "loky",
              scheduler: str | None = None, artifacts: bool = True,
              reporter: Reporter | None = None, journal: Journal | None = None,
              stop: Shutdown | None = None) -> list[Plan]:
    """Compute every planned run and log each result as it arrives; returns
    ``plans`` with their counts and failures filled in.

    Each sweep with work to do gets a parent run; its children are nested
    under it. When ``stop`` is requested (or on a KeyboardInterrupt) the
    loop winds down (:meth:`Loop.wind_down`) and raises KeyboardInterrupt.
    On a store failure the loop stops
    within ``DRAIN_S`` seconds, keeps what it computed in the journal and
    raises :class:`StoreError`.
    """
    if backend not in BACKENDS:
        raise MpeError(f"--backend: unknown backend '{backend}' (use {' or '.join(BACKENDS)})")
    reporter = reporter or Reporter()
    journal = journal or Journal()
    stop = stop or Shutdown()  # not installed: never requested
    owner = Owner.current()
    for plan in plans:
        if plan.todo:
            plan.started = time.time()
            plan.parent_id = tracker.start_parent(plan.experiment_id, plan.sweep, {
                "mpe3d.backend": backend, "mpe3d.runs_planned": str(len(plan.todo))}, owner)
    reporter.start(sum(len(p.todo) for p in plans), sum(p.skipped for p in plans))
    folders = tracker.local_folders()
    reserve = Reserve(folders[0] if folders else None)
    try:
        with pool(jobs, backend, scheduler) as workers:
            loop = Loop(plans, tracker, workers, journal, artifacts, reporter, reserve)
            with Heartbeat(lambda: tracker.heartbeat(list(loop.open_parents))) as heartbeat:
                try:
                    completed = loop.run(heartbeat, stop)
                except StoreError as exc:
                    raise loop.drain(exc) from None
                except BaseException:  # a library caller's Ctrl-C: no grace
                    loop.wind_down(stop, grace_s=0.0)
                    raise
                if not completed:
                    loop.wind_down(stop)
                    raise KeyboardInterrupt
    finally:
        reserve.release()
        reporter.stop()
        journal.tidy()  # an empty journal folder is litter, stopped or not
    return plans


def close_parent(tracker, plan: Plan, status: str) -> None:
    tracker.finish_parent(plan.parent_id, status, {
        "runs_finished": plan.counts["FINISHED"], "runs_failed": plan.counts["FAILED"],
        "runs_skipped": plan.skipped, "runs_elsewhere": plan.elsewhere,
        "runs_stale_replaced": plan.stale, "wall_s": time.time() - plan.started})


