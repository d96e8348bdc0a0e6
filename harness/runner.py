"""Run sweeps: skip what is tracked, compute the rest in parallel, log as results arrive.

Workers (joblib's loky processes, or dask workers) compute whole runs and
return :class:`~harness.execute.RunRecord` objects; the parent logs each one
to MLflow the moment it arrives, so an interrupted sweep loses at most the
runs in flight, and the next invocation resumes from the store.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from dataclasses import dataclass, field
from typing import Iterable, Iterator

from .config import RunConfig
from .errors import MpeError
from .execute import RunRecord, run_record
from .sweep import Sweep

BACKENDS = ("loky", "dask")
log = logging.getLogger(__name__)


@dataclass
class Plan:
    """One sweep against its experiment: what to run and what is already done."""

    sweep: Sweep
    experiment_id: str
    todo: list[RunConfig]
    skipped_finished: int = 0
    skipped_failed: int = 0
    parent_id: str | None = None
    counts: dict[str, int] = field(default_factory=lambda: {"FINISHED": 0, "FAILED": 0})
    failures: list[tuple[str, str]] = field(default_factory=list)  # (run label, error)

    @property
    def skipped(self) -> int:
        return self.skipped_finished + self.skipped_failed

    @property
    def pending(self) -> int:
        return len(self.todo) - sum(self.counts.values())


class Reporter:
    """Progress callbacks; the default is silent (the CLI shows a progress bar)."""

    def start(self, total: int, skipped: int) -> None: ...

    def advance(self, status: str) -> None: ...

    def stop(self) -> None: ...


def plan_sweeps(sweeps: Iterable[Sweep], tracker, rerun_failed: bool = False,
                force: bool = False) -> list[Plan]:
    """Decide, per sweep, which runs still need computing.

    A config whose hash already has a FINISHED run in the experiment is
    skipped; one whose best run FAILED is skipped unless ``rerun_failed``.
    ``force`` reruns everything. Sweeps sharing an experiment never run the
    same config twice in one invocation.
    """
    plans, planned = [], {}
    for sweep in sweeps:
        experiment_id = tracker.experiment_id(sweep.name)
        tracked = {} if force else tracker.tracked(experiment_id)
        seen = planned.setdefault(experiment_id, set())
        plan = Plan(sweep=sweep, experiment_id=experiment_id, todo=[])
        for config in sweep.runs:
            key = config.hash()
            status = tracked.get(key)
            if status == "FINISHED" or key in seen:
                plan.skipped_finished += 1
            elif status == "FAILED" and not rerun_failed:
                plan.skipped_failed += 1
            else:
                plan.todo.append(config)
                seen.add(key)
        plans.append(plan)
    return plans


def _task(index: int, config: RunConfig, keep_clouds: bool) -> tuple[int, RunRecord]:
    return index, run_record(config, keep_clouds)


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


def _records(tasks: list[tuple[int, RunConfig]], jobs: int, backend: str, scheduler: str | None,
             keep_clouds: bool) -> Iterator[tuple[int, RunRecord]]:
    from joblib import Parallel, delayed, parallel_config

    calls = (delayed(_task)(i, config, keep_clouds) for i, config in tasks)
    if backend == "dask":
        with _dask_client(jobs, scheduler) as client, parallel_config(backend="dask"):
            if sum(client.nthreads().values()) == 1:
                log.warning("the dask cluster has one thread: joblib then runs every run in "
                            "this process, not on the cluster")
            yield from Parallel(n_jobs=-1, return_as="generator_unordered")(calls)
    else:
        yield from Parallel(n_jobs=jobs, backend="loky",
                            return_as="generator_unordered")(calls)


def run_plans(plans: list[Plan], tracker, *, jobs: int = -1, backend: str = "loky",
              scheduler: str | None = None, artifacts: bool = True,
              reporter: Reporter | None = None) -> list[Plan]:
    """Compute every planned run and log each result as it arrives; returns
    ``plans`` with their counts and failures filled in.

    Each sweep with work to do gets a parent run; its children are nested
    under it. On an interrupt or a store failure the open parents are closed
    as KILLED and the error propagates; everything logged so far stays.
    """
    if backend not in BACKENDS:
        raise MpeError(f"--backend: unknown backend '{backend}' (use {' or '.join(BACKENDS)})")
    reporter = reporter or Reporter()
    tasks = [(i, config) for i, plan in enumerate(plans) for config in plan.todo]
    for plan in plans:
        if plan.todo:
            plan.parent_id = tracker.start_parent(plan.experiment_id, plan.sweep, {
                "mpe3d.backend": backend, "mpe3d.runs_planned": str(len(plan.todo))})
    started = time.time()
    reporter.start(len(tasks), sum(p.skipped for p in plans))
    try:
        for index, record in _records(tasks, jobs, backend, scheduler, artifacts):
            plan = plans[index]
            tracker.log_record(plan.experiment_id, plan.parent_id, record,
                               run_name=plan.sweep.label(record.config), artifacts=artifacts)
            plan.counts[record.status] += 1
            if record.error:
                plan.failures.append((plan.sweep.label(record.config), record.error))
            reporter.advance(record.status)
            if plan.pending == 0:
                _close(tracker, plan, "FINISHED", started)
    except BaseException:
        for plan in plans:
            if plan.parent_id and plan.pending:
                with contextlib.suppress(Exception):
                    _close(tracker, plan, "KILLED", started)
        raise
    finally:
        reporter.stop()
    return plans


def _close(tracker, plan: Plan, status: str, started: float) -> None:
    tracker.finish_parent(plan.parent_id, status, {
        "runs_finished": plan.counts["FINISHED"], "runs_failed": plan.counts["FAILED"],
        "runs_skipped": plan.skipped, "wall_s": time.time() - started})
