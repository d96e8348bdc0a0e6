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
from dataclasses import dataclass
from typing import Callable

__all__ = ["WarmUp", "registered", "warm", "warm_up", "warmed"]


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
    for step in list(_REGISTRY.values()):
        if step.name not in _DONE and step.loss in (None, loss) and (only is None or step.name.startswith(only)):
            step.call()
            _DONE.add(step.name)


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
