"""Who is computing a run, and whether that process still lives.

Every sweep invocation is an :class:`Owner` (host, pid, and the pid's start
time, so a recycled pid is not mistaken for the old process). Its parent runs
carry a heartbeat tag that a thread refreshes every ``HEARTBEAT_S`` seconds.
A claim whose owner is dead (gone from this host, or silent for ``STALE_S``
seconds on another host) is a zombie: the next invocation closes it as KILLED
and computes the config again.
"""

from __future__ import annotations

import os
import socket
import threading
import time
from dataclasses import dataclass

HEARTBEAT_S = 10.0
STALE_S = 60.0  # six missed heartbeats: far beyond a busy store's hiccup


def _start_time(pid: int) -> float | None:
    import psutil

    try:
        return psutil.Process(pid).create_time()
    except psutil.NoSuchProcess:
        return None
    except psutil.AccessDenied:  # another user's process: alive, start unknown
        return -1.0


@dataclass(frozen=True)
class Owner:
    host: str
    pid: int
    started: float  # the process's start time, seconds since the epoch

    @classmethod
    def current(cls) -> "Owner":
        pid = os.getpid()
        return cls(socket.gethostname(), pid, round(_start_time(pid) or 0.0, 2))

    def tag(self) -> str:
        return f"{self.host}|{self.pid}|{self.started:.2f}"

    @classmethod
    def parse(cls, text: str | None) -> "Owner | None":
        try:
            host, pid, started = (text or "").rsplit("|", 2)
            return cls(host, int(pid), float(started))
        except ValueError:
            return None

    def __str__(self) -> str:
        return f"{self.host}:{self.pid}"

    def alive(self, heartbeat: float | None, now: float | None = None) -> bool:
        """On this host, by its pid; elsewhere, by the freshness of its heartbeat."""
        if self.host == socket.gethostname():
            started = _start_time(self.pid)
            return started is not None and (started < 0 or abs(started - self.started) < 0.05)
        now = time.time() if now is None else now
        return heartbeat is not None and now - heartbeat < STALE_S


class Heartbeat:
    """A daemon thread that calls ``beat()`` every ``interval`` seconds.

    A failing beat is kept in ``error`` (the store is gone: the run loop stops)
    rather than raised in a thread nobody reads.
    """

    def __init__(self, beat, interval: float = HEARTBEAT_S):
        self._beat, self._interval = beat, interval
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="mpe3d-heartbeat", daemon=True)
        self.error: Exception | None = None

    def _loop(self) -> None:
        while not self._stop.wait(self._interval):
            try:
                self._beat()
            except Exception as exc:  # noqa: BLE001 - reported through .error
                self.error = exc
                return

    def __enter__(self) -> "Heartbeat":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)  # a beat stuck on a slow store must not hold a stop up
