"""One way to stop: Ctrl-C (to the process group, once or twice), SIGINT or
SIGTERM to the main process all end a command the same way, within a bound.

:class:`Shutdown` is installed by the command line for the life of one
command. Python runs signal handlers only between bytecodes of the main
thread, so a main thread blocked in C (a lock, a socket, compiled code)
would never see one; this class also has the signals written to a socket
(``signal.set_wakeup_fd``) that a watcher thread reads, which is what makes
the bound hold whatever the main thread is doing:

- the first signal completes :attr:`Shutdown.requested` (the run loop waits on
  it beside its runs, so it stops dispatching at once) and, outside a
  :meth:`Shutdown.deferred` section, raises :class:`KeyboardInterrupt` in the
  main thread;
- a second signal sets :attr:`Shutdown.hurry`: running workers get no more grace;
- ``deadline_s`` after the first signal, whatever still runs is the watchdog's:
  it terminates every descendant process, prints the command's line unless it
  was printed, and leaves with exit code 130 without finalising the interpreter;
- once the command is over (:meth:`Shutdown.settle`), a signal ends the
  process at once, with 130 and the line (its work is all done and kept);
  after an interrupt, whose line is said, further signals are ignored.

Sections that must not be cut halfway (creating a store, logging a result,
closing claims) run deferred: a signal there only sets the flags, and the
code looks at them at its own safe points.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import os
import signal
import socket
import sys
import threading

EXIT_CODE = 130
GRACE_S = 3.0  # what a running worker may still finish, and be logged, after the first signal
DEADLINE_S = 8.0  # after the first signal the process is gone within this, whatever it does
FINALISE_S = 30.0  # a command that is over leaves within this, whatever its libraries' exit hooks do
SIGNALS = (signal.SIGINT, signal.SIGTERM)
LINE = "mpe3d: interrupted"


class Shutdown:
    """Signal handling for one command; a context manager that restores the
    previous handlers on exit (the watchdog stays armed once a signal came)."""

    def __init__(self, deadline_s: float = DEADLINE_S):
        self.deadline_s = deadline_s
        self.requested: cf.Future = cf.Future()  # done (with the signal number) at the first signal
        self.hurry = threading.Event()  # a second signal: no more grace
        self.line = LINE  # what a user reads last; a command sets its own
        self.signals = 0
        self.finishing = False  # the command is over: a signal now only ends the process
        self._deferred = 0
        self._told = threading.Lock()
        self._said = False
        self._raised = False
        self._installed = False
        self._timer: threading.Timer | None = None
        self._finalise: threading.Timer | None = None

    # -- installation --------------------------------------------------------

    def __enter__(self) -> "Shutdown":
        if threading.current_thread() is not threading.main_thread():
            return self  # signals are the main thread's; a library caller keeps its own
        reader, writer = socket.socketpair()
        writer.setblocking(False)
        self._sockets = (reader, writer)
        self._previous = {sig: signal.signal(sig, self._on_signal) for sig in SIGNALS}
        self._previous_fd = signal.set_wakeup_fd(writer.fileno(), warn_on_full_buffer=False)
        threading.Thread(target=self._watch, args=(reader,), name="mpe3d-shutdown",
                         daemon=True).start()
        self._installed = True
        return self

    def __exit__(self, *exc) -> None:
        if not self._installed:
            return
        signal.set_wakeup_fd(self._previous_fd)
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._sockets[1].close()  # the watcher reads end-of-file and leaves
        for timer in (self._timer, self._finalise):  # an in-process caller outlives its command
            if timer is not None:
                timer.cancel()
        self._installed = False

    # -- what a signal does ----------------------------------------------------

    def _on_signal(self, signum, frame) -> None:
        """The main thread's handler: the watcher did the bookkeeping."""
        if self._deferred == 0 and not self._raised and not self.finishing:
            self._raised = True  # once: a second Ctrl-C must not cut the first one's cleanup
            raise KeyboardInterrupt

    def _watch(self, reader: socket.socket) -> None:
        with reader:
            while True:
                try:
                    data = reader.recv(64)
                except OSError:
                    return
                if not data:
                    return
                for signum in data:
                    if signum in SIGNALS:
                        self._count(signum)

    def _count(self, signum: int) -> None:
        if self.finishing:
            self.tell()
            os._exit(EXIT_CODE)
        self.signals += 1
        if self.signals == 1:
            self.requested.set_result(signum)
            self._timer = threading.Timer(self.deadline_s, self._expire)
            self._timer.daemon = True
            self._timer.start()
        else:
            self.hurry.set()

    @property
    def stopping(self) -> bool:
        return self.requested.done()

    @contextlib.contextmanager
    def deferred(self):
        """Signals only set the flags here; the code inside checks :attr:`stopping`."""
        self._deferred += 1
        try:
            yield self
        finally:
            self._deferred -= 1

    def check(self) -> None:
        """At a safe point: raise :class:`KeyboardInterrupt` when a stop was requested."""
        if self.stopping:
            raise KeyboardInterrupt

    # -- the end -------------------------------------------------------------------

    def tell(self) -> None:
        """Print the command's line, once, as the last line on stderr."""
        with self._told:
            if self._said:
                return
            self._said = True
        with contextlib.suppress(Exception):
            sys.stderr.flush()
        with contextlib.suppress(OSError):
            os.write(2, (self.line + "\n").encode())

    def settle(self, code: int) -> None:
        """The command is over with exit ``code``: from now on a signal only ends
        the process. After an interrupt (130, its line said) a further one is
        ignored: while the interpreter finalises, Python gives signals back to
        their default action, and a second Ctrl-C then killed the process
        (exit -2) after it had said it stopped; an ignored signal stays ignored."""
        self.finishing = True
        if not self._installed:
            return
        if code == EXIT_CODE:
            for sig in SIGNALS:
                signal.signal(sig, signal.SIG_IGN)
        # Exit hooks (loky's, SQLite's) once hung a stopped sweep for minutes after its
        # line was said; what it computed is kept by then, so the bound costs nothing.
        self._finalise = threading.Timer(FINALISE_S, self._leave, args=(code,))
        self._finalise.daemon = True
        self._finalise.start()

    @staticmethod
    def _leave(code: int) -> None:
        kill_descendants(grace_s=1.0)
        with contextlib.suppress(Exception):
            sys.stdout.flush()
            sys.stderr.flush()
        os._exit(code)

    def _expire(self) -> None:
        """The watchdog: the bound is up and the process still lives."""
        kill_descendants(grace_s=1.0)
        self.tell()
        os._exit(EXIT_CODE)


def kill_descendants(grace_s: float = 1.0, only=None) -> None:
    """Terminate this process's descendants (those ``only(process)`` accepts),
    then kill the ones still alive after ``grace_s``."""
    import psutil

    try:
        family = psutil.Process().children(recursive=True)
    except psutil.Error:
        return
    if only is not None:
        family = [p for p in family if _accepts(only, p)]
    for process in family:
        with contextlib.suppress(psutil.Error):
            process.terminate()
    _, alive = psutil.wait_procs(family, timeout=grace_s)
    for process in alive:
        with contextlib.suppress(psutil.Error):
            process.kill()
    psutil.wait_procs(alive, timeout=grace_s)


def _accepts(only, process) -> bool:
    import psutil

    try:
        return bool(only(process))
    except psutil.Error:
        return False


def stop_group(process, grace_s: float = 2.0) -> None:
    """SIGTERM to the whole process group that ``process`` (a ``Popen`` started
    with ``start_new_session=True``) leads, then SIGKILL to whatever outlives
    ``grace_s``: a server's forked workers go with it."""
    import subprocess
    import time

    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(process.pid, sig)
        except ProcessLookupError:
            break
        try:
            process.wait(grace_s)
        except subprocess.TimeoutExpired:
            continue
        deadline = time.monotonic() + grace_s  # the leader is gone; its workers may linger a moment
        while time.monotonic() < deadline:
            try:
                os.killpg(process.pid, 0)
            except ProcessLookupError:
                return
            time.sleep(0.1)
    with contextlib.suppress(subprocess.TimeoutExpired):
        process.wait(grace_s)  # reap the leader
