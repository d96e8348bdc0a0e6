"""Run sweeps: skip what is tracked, claim each run before computing it, log as results arrive.

A run of a config is reused only when the code that computed it is the
running code (:mod:`mpe3d.harness.tracking.identity`). Every config this sweep computes is
first *claimed*: a RUNNING child run in the store, owned by this process and
kept alive by a heartbeat on the sweep's parent run. Another sweep that meets
the claim waits for it instead of computing the config again, and a claim
whose owner died is closed as KILLED and computed anew.

Workers (joblib's loky processes, dask workers, or one thread for
``--jobs 1``) compute whole runs and return :class:`~mpe3d.harness.experiment.execute.RunRecord`
objects. The parent writes each one to the local journal, then logs it to
MLflow, then drops it from the journal: an interrupt, a crash or a store
outage never loses a computed result, and the next invocation replays what
the journal still holds before it plans anything.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import logging
import os
import queue
import random
import signal
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Iterable, Iterator

from mpe3d import plugins
from mpe3d.errors import DiskFull, MpeError, StoreError
from mpe3d.harness.experiment.config import BACKENDS, RunConfig
from mpe3d.harness.experiment.execute import code_of, expected_work, failed_record, run_record
from mpe3d.harness.experiment.sweep import Sweep
from mpe3d.harness.files import Reserve, SpaceMeter, human_bytes, same_device
from mpe3d.harness.shutdown import EXIT_CODE, GRACE_S, Shutdown, kill_descendants
from mpe3d.harness.tracking.journal import Journal
from mpe3d.harness.tracking.ownership import Heartbeat, Owner
from mpe3d.harness.tracking.records import RunRecord

POLL_S = 2.0  # how often a sweep looks again at a claim of another sweep it waits for
DRAIN_S = 10.0  # after the store fails: how long runs in flight may still finish
log = logging.getLogger(__name__)


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


# -- where runs compute -------------------------------------------------------------

class _ThreadPool:
    """``--jobs 1``: runs compute in this process, on one daemon thread, so the
    loop keeps its heartbeat, its claims and its outage deadline meanwhile."""

    capacity = workers = 1

    def __init__(self):
        self._tasks: queue.SimpleQueue = queue.SimpleQueue()
        threading.Thread(target=self._work, name="mpe3d-run", daemon=True).start()

    def _work(self) -> None:
        while (task := self._tasks.get()) is not None:
            future, fn, args = task
            if future.set_running_or_notify_cancel():
                try:
                    future.set_result(fn(*args))
                except BaseException as exc:  # noqa: BLE001 - handed to the loop
                    future.set_exception(exc)

    def submit(self, fn, *args) -> cf.Future:
        future: cf.Future = cf.Future()
        self._tasks.put((future, fn, args))
        return future

    def close(self) -> None:
        """Its thread ends after the run it is in; a run inside compiled code
        cannot be stopped from another thread, so a stopped command leaves
        without waiting for it (``cli.console``)."""
        self._tasks.put(None)

    terminate = close


def _ignore_sigint() -> None:
    """In each worker: Ctrl-C reaches the whole process group, but only the
    parent decides what stops (a worker cut mid-run would log a false FAILED)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@contextlib.contextmanager
def _sigint_held() -> Iterator[None]:
    """SIGINT held back from this thread, and delivered when released. A
    process or thread started meanwhile inherits the block, so a worker cannot
    meet a Ctrl-C before :func:`_ignore_sigint` runs in it."""
    held = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, held)


def _is_loky_worker(process) -> bool:
    return any("LokyProcess" in part for part in process.cmdline())


class _LokyPool:
    """Worker processes on this machine (joblib's loky executor)."""

    def __init__(self, jobs: int):
        from multiprocessing import resource_tracker

        from joblib.externals.loky import get_reusable_executor

        workers = jobs if jobs > 0 else (os.cpu_count() or 1)
        self.workers = workers
        self.capacity = 2 * workers  # one queued behind each running: no worker waits for a claim
        # loky starts Python's resource tracker with each worker; starting it
        # unblocks SIGINT (Python 3.11), so it is started first, unheld
        resource_tracker.ensure_running()
        with _sigint_held():  # loky starts workers (and its manager thread) in these calls
            self.executor = get_reusable_executor(max_workers=workers, initializer=_ignore_sigint)

    def submit(self, fn, *args) -> cf.Future:
        with _sigint_held():
            return self.executor.submit(fn, *args)

    def close(self) -> None:
        """Nothing: the reusable executor serves the next sweep of this process."""

    def terminate(self) -> None:
        """Stop the workers now. Terminating their processes is loky's own
        broken-pool path (every future fails, its threads and semaphores are
        released); ``shutdown(kill_workers=True)`` with calls still queued
        races in loky 1.6's manager thread (KeyError, leaked semaphores)."""
        kill_descendants(grace_s=1.0, only=_is_loky_worker)
        closing = threading.Thread(target=self.executor.shutdown, kwargs={"wait": True},
                                   name="mpe3d-loky-shutdown", daemon=True)
        closing.start()
        closing.join(3.0)


class _DaskPool:
    """A dask cluster's workers; their futures are bridged to concurrent.futures."""

    def __init__(self, client):
        self.client = client
        self.workers = max(1, sum(client.nthreads().values()))
        self.capacity = 2 * self.workers
        self._held: dict[int, object] = {}  # dask forgets a task whose future is dropped

    def submit(self, fn, *args) -> cf.Future:
        future: cf.Future = cf.Future()
        task = self.client.submit(fn, *args, pure=False)
        self._held[id(future)] = task

        def done(task) -> None:
            self._held.pop(id(future), None)
            try:
                future.set_result(task.result())
            except BaseException as exc:  # noqa: BLE001 - a cancelled or killed task
                future.set_exception(exc)
        task.add_done_callback(done)
        return future

    def close(self) -> None:
        """Nothing: the client's context closes the cluster."""

    def terminate(self) -> None:
        if self._held:
            with contextlib.suppress(Exception):
                self.client.cancel(list(self._held.values()), force=True)


@contextlib.contextmanager
def _dask_client(jobs: int, scheduler: str | None):
    """A client on ``scheduler``, or on a local cluster of ``jobs`` worker processes."""
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise MpeError("--backend dask needs dask.distributed: pip install 'dask[distributed]'") from None
    if scheduler:
        try:
            client = Client(scheduler, timeout="15s")
        except (OSError, TimeoutError) as exc:
            raise MpeError(f"cannot connect to the dask scheduler at {scheduler}: {exc}") from None
        with client:
            yield client
        return
    workers = jobs if jobs > 0 else (os.cpu_count() or 1)
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                      dashboard_address=":0",  # its HTTP server always starts: any free port
                      silence_logs=logging.ERROR) as cluster, \
            Client(cluster) as client:
        yield client


@contextlib.contextmanager
def _pool(jobs: int, backend: str, scheduler: str | None) -> Iterator:
    if backend == "dask":
        with _dask_client(jobs, scheduler) as client:
            yield _DaskPool(client)
        return
    pool = _ThreadPool() if jobs == 1 else _LokyPool(jobs)
    try:
        yield pool
    finally:
        pool.close()


# -- the run loop -----------------------------------------------------------------

@dataclass
class _Task:
    plan: Plan
    config: RunConfig
    run_id: str | None = None  # our claim
    next_look: float = 0.0  # when to look again at another sweep's claim

    @property
    def code(self) -> str:
        return code_of(self.config)


class _Loop:
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
        self.queue = deque(sorted((_Task(plan, config) for plan in plans for config in plan.todo),
                                  key=lambda task: -expected_work(task.config)))
        self.in_flight: dict[cf.Future, _Task] = {}
        self.waiting: list[_Task] = []  # claimed by another live sweep
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

    def _done_elsewhere(self, task: _Task) -> None:
        task.plan.elsewhere += 1
        self.reporter.advance("ELSEWHERE")
        self._close_if_done(task.plan)

    def _meta(self, task: _Task) -> dict:
        plan = task.plan
        return {"uri": self.tracker.uri, "experiment": plan.sweep.name,
                "experiment_id": plan.experiment_id, "parent_id": plan.parent_id,
                "run_id": task.run_id, "run_name": plan.sweep.label(task.config),
                "owner": self.owner.tag()}

    def _record(self, future: cf.Future, task: _Task) -> RunRecord:
        try:
            return future.result()
        except Exception as exc:  # noqa: BLE001 - a worker that died (OOM, segfault, killed)
            return failed_record(task.config, f"its worker died: {type(exc).__name__}: {exc}")

    def _finish(self, future: cf.Future, task: _Task) -> None:
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

    def _unjournaled(self, task: _Task, record: RunRecord) -> None:
        """No room for the journal: the store may still have some (another disk)."""
        try:
            self.tracker.log_record(task.run_id, record, artifacts=self.artifacts)
        except StoreError:
            self.lost += 1
            self.unlogged.append(task.run_id)
        else:
            self._count(task, record)

    def _count(self, task: _Task, record: RunRecord) -> None:
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
            _close(self.tracker, plan, "FINISHED")

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
                    _close(self.tracker, plan, "KILLED")


def run_plans(plans: list[Plan], tracker, *, jobs: int = -1, backend: str = "loky",
              scheduler: str | None = None, artifacts: bool = True,
              reporter: Reporter | None = None, journal: Journal | None = None,
              stop: Shutdown | None = None) -> list[Plan]:
    """Compute every planned run and log each result as it arrives; returns
    ``plans`` with their counts and failures filled in.

    Each sweep with work to do gets a parent run; its children are nested
    under it. When ``stop`` is requested (or on a KeyboardInterrupt) the
    loop winds down (:meth:`_Loop.wind_down`) and raises KeyboardInterrupt.
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
        with _pool(jobs, backend, scheduler) as pool:
            loop = _Loop(plans, tracker, pool, journal, artifacts, reporter, reserve)
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


def _close(tracker, plan: Plan, status: str) -> None:
    tracker.finish_parent(plan.parent_id, status, {
        "runs_finished": plan.counts["FINISHED"], "runs_failed": plan.counts["FAILED"],
        "runs_skipped": plan.skipped, "runs_elsewhere": plan.elsewhere,
        "runs_stale_replaced": plan.stale, "wall_s": time.time() - plan.started})


# -- a whole invocation: recover, plan, run, summarise ------------------------------

def _nothing_to_do(plan: Plan, uri: str) -> str:
    parts = [f"{plan.skipped_finished} finished"]
    if plan.reused_stale:
        parts.append(f"{plan.reused_stale} by other code, reused on purpose (--reuse-stale)")
    if plan.skipped_failed:
        parts.append(f"{plan.skipped_failed} failed (--rerun-failed retries them)")
    return (f"{plan.sweep.name}: nothing to run: all {len(plan.sweep.runs)} runs are already "
            f"tracked in {uri} ({', '.join(parts)}; --force reruns everything)")


def _outcome(plan: Plan) -> str:
    text = (f"{plan.sweep.name}: {plan.counts['FINISHED']} finished, {plan.counts['FAILED']} failed, "
            f"{plan.skipped} skipped (already tracked) of {len(plan.sweep.runs)} runs")
    if plan.stale:
        text += (f"; {plan.stale} of them replaced runs computed by other code "
                 "(--reuse-stale keeps such runs)")
    if plan.reused_stale:
        text += f"; {plan.reused_stale} runs by other code reused (--reuse-stale)"
    if plan.elsewhere:
        text += f"; {plan.elsewhere} computed meanwhile by another sweep on this store"
    return text


def _quiet(text: str) -> None:
    pass


def run_sweeps(sweeps: list[Sweep], tracker, *, jobs: int = -1, backend: str = "loky",
               scheduler: str | None = None, artifacts: bool = True, rerun_failed: bool = False,
               force: bool = False, reuse_stale: bool = False, reporter: Reporter | None = None,
               say=_quiet, warn=_quiet, summarise=None,
               stop: Shutdown | None = None) -> tuple[list[Plan], int]:
    """Replay the journal, plan ``sweeps`` against ``tracker``, run what is
    missing and summarise; ``say`` and ``warn`` receive the lines to show.

    Returns the plans and the exit code: 0, 1 when a run failed, 130 when
    stopped (``stop`` requested, or a KeyboardInterrupt; every run logged so
    far is kept, and the caller says so). A store
    failure raises :class:`StoreError` (exit 3) after the computed results are
    journaled. With ``artifacts`` and ``summarise(tracker, sweep, parent_id)``
    (e.g. :func:`mpe3d.reports.summary.log_sweep_summary`), each parent run
    also gets its sweep's summary; the runner never draws reports itself.
    """
    stop = stop or Shutdown()  # not installed: never requested
    plans: list[Plan] = []
    try:
        plans = _plan(sweeps, tracker, stop, say, rerun_failed=rerun_failed, force=force,
                      reuse_stale=reuse_stale)
        if not any(plan.todo for plan in plans):
            return plans, 0
        start = time.time()
        run_plans(plans, tracker, jobs=jobs, backend=backend, scheduler=scheduler,
                  artifacts=artifacts, reporter=reporter, stop=stop)
        if artifacts and summarise is not None:
            for plan in plans:
                if plan.parent_id:
                    stop.check()
                    _log_summary(summarise, tracker, plan, warn)
    except KeyboardInterrupt:
        return plans, EXIT_CODE
    _say_outcomes(plans, say, warn)
    say(f"{time.time() - start:.1f} s; tracked in {tracker.uri} "
        f"(`mpe3d runs NAME` prints a table, `mpe3d ui` opens the MLflow UI)")
    return plans, 1 if any(plan.failures for plan in plans) else 0


def _plan(sweeps, tracker, stop: Shutdown, say, **how) -> list[Plan]:
    """Replay what dead sweeps left in the journal, then plan ``sweeps``."""
    journal = Journal()
    replayed = replay_journal(tracker, journal, stop)
    if replayed:
        say(f"replayed {replayed} result(s) from {journal.folder} into {tracker.uri}: an earlier "
            "sweep computed them but could not log them")
    plans = plan_sweeps(sweeps, tracker, stop=stop, **how)
    zombies = sum(plan.zombies for plan in plans)
    if zombies:
        say(f"closed {zombies} run(s) left RUNNING by sweeps that died, as KILLED; "
            "their configs are computed again")
    for plan in plans:
        if not plan.todo:
            say(_nothing_to_do(plan, tracker.uri))
    stop.check()
    return plans


def _say_outcomes(plans: list[Plan], say, warn) -> None:
    for plan in plans:
        if plan.todo:
            say(_outcome(plan))
        for label, error in plan.failures[:5]:
            warn(f"run failed: {label}: {error}")
        if len(plan.failures) > 5:
            warn(f"... and {len(plan.failures) - 5} more failed runs "
                 f"(`mpe3d runs '{plan.sweep.name}'` lists them)")


def _log_summary(summarise, tracker, plan: Plan, warn) -> None:
    """``summarise`` the sweep on its parent run, where MLflow's UI shows it; a
    failure to draw it costs no run."""
    try:
        summarise(tracker, plan.sweep, plan.parent_id)
    except StoreError:
        raise
    except Exception as exc:  # noqa: BLE001 - the runs are logged; the summary is a bonus
        warn(f"{plan.sweep.name}: could not log the summary report on the parent run: "
             f"{type(exc).__name__}: {exc}")
