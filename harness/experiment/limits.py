"""Sane limits, checked before any allocation: each refusal names the limit
and the flag that lifts it.

A sweep file and a run config are written by hand, so a file of megabytes is
a mistake (a 100 MB YAML takes minutes to parse); a grid of more than
``MAX_RUNS`` runs is more likely a stray ``repeats`` than a plan; and a run
whose arrays cannot fit in this machine's memory must be refused before
NumPy's allocator dies on it.
"""

from __future__ import annotations

from pathlib import Path

from mpe3d.errors import MpeError

MAX_RUNS = 100_000
MAX_YAML_MB = 1.0


def check_yaml_size(path: Path, what: str, max_mb: float | None) -> None:
    """Refuse a YAML file that is not a regular file or is over ``max_mb`` MiB."""
    max_mb = MAX_YAML_MB if max_mb is None else max_mb
    if path.exists() and not path.is_file():
        raise MpeError(f"{what} {path} is not a regular file")
    size = path.stat().st_size if path.is_file() else 0
    if size > max_mb * 2**20:
        raise MpeError(f"{what} {path} is {size / 2**20:.1f} MiB, over the limit of {max_mb:g} MiB "
                       "for a hand-written YAML file (--max-yaml-mb lifts it)")


def check_run_count(count: int, where: str, max_runs: int | None) -> None:
    """Refuse a grid of more than ``max_runs`` runs before expanding it."""
    max_runs = MAX_RUNS if max_runs is None else max_runs
    if count > max_runs:
        raise MpeError(f"{where}: the grid has {count:,} runs, over the limit of {max_runs:,} "
                       "(--max-runs N lifts it)")


def run_bytes(points: int) -> float:
    """A floor on what one run of N points holds at once: every run scores its
    reconstruction with the exact EMD, whose N x N cost matrix is dense, with
    the assignment's working copy of it, beside the scene's own arrays."""
    return 16.0 * points * points + 256.0 * points


def check_run_memory(config) -> None:
    """Refuse a config whose run cannot fit in this machine's memory."""
    from mpe3d.solvers.base import require_memory

    n = config["points"]
    try:
        require_memory(run_bytes(n), f"points={n}: the exact EMD's {n}x{n} matrices")
    except MpeError as exc:
        raise MpeError(str(exc), key="points") from None
