"""Run sweeps: skip what is tracked, claim each run before computing it, log as results arrive.

A run of a config is reused only when the code that computed it is the
running code (:mod:`mpe3d.harness.tracking.identity`). Every config this sweep computes is
first *claimed*: a RUNNING child run in the store, owned by this process and
kept alive by a heartbeat on the sweep's parent run. Another sweep that meets
the claim waits for it instead of computing the config again, and a claim
whose owner died is closed as KILLED and computed anew.

Workers (joblib's loky processes, dask workers, or one thread for
``--jobs 1``) compute whole runs and return :class:`~mpe3d.harness.tracking.records.RunRecord`
objects. The parent writes each one to the local journal, then logs it to
MLflow, then drops it from the journal: an interrupt, a crash or a store
outage never loses a computed result, and the next invocation replays what
the journal still holds before it plans anything.

Four modules, one job each: :mod:`.plan` (what is done, what is left),
:mod:`.pools` (where runs compute), :mod:`.loop` (claim, compute, journal,
log) and :mod:`.sweeps` (a whole invocation).

May import: :mod:`mpe3d.harness.experiment`, :mod:`mpe3d.harness.tracking`,
:mod:`mpe3d.harness.files`, :mod:`mpe3d.harness.shutdown`, :mod:`mpe3d.plugins`
and :mod:`mpe3d.errors`; never the reports (a sweep's summary is a callback).
"""

from mpe3d.harness.runner.loop import run_plans
from mpe3d.harness.runner.plan import Plan, Reporter, plan_sweeps, replay_journal
from mpe3d.harness.runner.sweeps import run_sweeps

__all__ = ["Plan", "Reporter", "plan_sweeps", "replay_journal", "run_plans", "run_sweeps"]
