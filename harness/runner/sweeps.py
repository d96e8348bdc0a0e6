"""A whole invocation: replay the journal, plan, run what is missing, summarise."""

from __future__ import annotations

import time

from mpe3d.errors import StoreError
from mpe3d.harness.experiment.sweep import Sweep
from mpe3d.harness.runner.loop import run_plans
from mpe3d.harness.runner.plan import Plan, Reporter, plan_sweeps, replay_journal
from mpe3d.harness.shutdown import EXIT_CODE, Shutdown
from mpe3d.harness.tracking.journal import Journal


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
