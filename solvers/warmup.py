"""Compiling the kernels before any solver's clock starts.

Each compiled kernel says, where it is defined, how to compile it: the
:func:`warm_up` decorator registers one call that compiles it all (one
signature a kernel), with what that compile costs on a fresh cache. A module
that defines kernels registers them when it is imported, so :func:`warm`
compiles, or loads from numba's disk cache, the kernels of every solver this
process has imported, and nothing of a stack it never uses (a stress solve
never compiles bundle adjustment's kernels). A test fails if a compiled
kernel is neither registered nor compiled by a registered one.
"""

from __future__ import annotations

import functools
import threading
from dataclasses import dataclass
from typing import Callable

__all__ = ["WarmUp", "registered", "warm", "warm_in_background", "warm_up", "warmed"]


@dataclass(frozen=True)
class WarmUp:
    """One kernel's warm-up: ``call()`` compiles it; ``loss`` names the stress
    loss whose solves need it (None: every solve that imported it)."""

    name: str
    cost_s: float  # its compile on a fresh cache (2026-12-05, one process after another; ratios matter)
    call: Callable[[], object]
    loss: str | None = None


_REGISTRY: dict[str, WarmUp] = {}
_DONE: set[str] = set()
_LOCK = threading.Lock()  # a warm() in the main thread waits for one in the background


def warm_up(cost_s: float, call: Callable, *, loss: str | None = None, name: str | None = None):
    """Decorate a kernel: ``call(kernel)`` compiles it. ``name`` tells apart
    two warm-ups of one kernel (one per loss)."""
    def register(kernel):
        function = getattr(kernel, "py_func", kernel)
        key = name or f"{function.__module__}.{function.__name__}"
        _REGISTRY[key] = WarmUp(key, cost_s, functools.partial(call, kernel), loss)
        return kernel
    return register


def registered() -> dict[str, WarmUp]:
    """Every warm-up registered so far, by name."""
    return dict(_REGISTRY)


def warmed(loss: str = "l2") -> bool:
    """Whether :func:`warm` (``loss``) has nothing left to do in this process."""
    return all(w.name in _DONE for w in _REGISTRY.values() if w.loss in (None, loss))


def warm(loss: str = "l2", *, part: int = 0, parts: int = 1, only: tuple[str, ...] | None = None) -> None:
    """Compile (or load from the on-disk cache) every registered kernel that a
    solve with the stress loss ``loss`` can call, once per process; with
    ``only``, those whose names (``module.function``) start with one of its
    prefixes (a bundle adjustment calls none of the stress's kernels).

    A robust loss's dense kernel (about 6 s of a first compile each) is
    compiled only when a solve asks for that loss: most installs never do.

    With ``parts`` > 1, only the share ``part`` (0 <= part < parts) of every
    registered kernel, each loss's included. Numba compiles one kernel at a
    time in a process, so ``parts`` processes compile a fresh install's
    kernels side by side (the test suite does, before its workers start;
    they then load them from the cache)."""
    if parts > 1:
        if not 0 <= part < parts:
            raise ValueError(f"part must be in [0, {parts}), got {part}")
        for step in _share(part, parts):
            step.call()
        return
    with _LOCK:
        for step in list(_REGISTRY.values()):
            if step.name not in _DONE and step.loss in (None, loss) and (only is None or step.name.startswith(only)):
                step.call()
                _DONE.add(step.name)


def warm_in_background(loss: str = "l2", *, only: tuple[str, ...] | None = None) -> threading.Thread:
    """:func:`warm` in a thread of its own, started now: numba's first load
    from its cache (0.2-0.3 s a process) overlaps a long step that releases
    the GIL, such as COLMAP's feature extraction. A later :func:`warm` waits
    for it; a warm-up that failed here is tried again there, so its error is
    raised in the caller's thread. Not a daemon: a process ending early waits
    for it rather than stopping numba mid-load."""
    thread = threading.Thread(target=_quietly, args=(loss, only), name="mpe3d-warm")
    thread.start()
    return thread


def _quietly(loss: str, only: tuple[str, ...] | None) -> None:
    try:
        warm(loss, only=only)
    except Exception:  # noqa: BLE001  (warm() in the solve's thread raises it again, with its traceback)
        pass


def _share(part: int, parts: int) -> list[WarmUp]:
    """The warm-ups of ``part`` when all of them, longest first, go one by
    one to the part with the least cost so far."""
    loads, mine = [0.0] * parts, []
    for step in sorted(_REGISTRY.values(), key=lambda w: -w.cost_s):
        least = loads.index(min(loads))
        loads[least] += step.cost_s
        if least == part:
            mine.append(step)
    return mine
