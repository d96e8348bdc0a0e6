"""Where runs compute: one thread (``--jobs 1``), joblib's loky processes, or
a dask cluster, behind one small interface (``submit``, ``close``,
``terminate``, ``capacity``, ``workers``). Workers ignore SIGINT: only the
parent decides what stops."""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import logging
import os
import queue
import signal
import sys
import threading
from typing import Iterator

from mpe3d.errors import MpeError
from mpe3d.harness.shutdown import kill_descendants


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
        without waiting for it (``mpe3d.cli.main.console``)."""
        self._tasks.put(None)

    terminate = close


def _worker_start(parent: int) -> None:
    """In each worker: Ctrl-C reaches the whole process group, but only the
    parent decides what stops (a worker cut mid-run would log a false FAILED);
    and the worker dies with its parent. A parent that leaves without closing
    the pool (``os._exit``, as a pytest-xdist worker leaves) would otherwise
    leave its workers, and the resource trackers they hold open, running."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if sys.platform.startswith("linux"):
        import ctypes

        pr_set_pdeathsig = 1
        ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, signal.SIGKILL)
    if os.getppid() != parent:  # the parent died before the line above
        os._exit(0)


@contextlib.contextmanager
def _sigint_held() -> Iterator[None]:
    """SIGINT held back from this thread, and delivered when released. A
    process or thread started meanwhile inherits the block, so a worker cannot
    meet a Ctrl-C before :func:`_worker_start` runs in it."""
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
            self.executor = get_reusable_executor(max_workers=workers, initializer=_worker_start,
                                                 initargs=(os.getpid(),))

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
def pool(jobs: int, backend: str, scheduler: str | None) -> Iterator:
    if backend == "dask":
        with _dask_client(jobs, scheduler) as client:
            yield _DaskPool(client)
        return
    pool = _ThreadPool() if jobs == 1 else _LokyPool(jobs)
    try:
        yield pool
    finally:
        pool.close()


