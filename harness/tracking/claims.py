"""The claim protocol: a config is a RUNNING run of its sweep, owned by a live
process, before anyone computes it; and the sweep's parent run, whose
heartbeat tells other sweeps that its owner lives. A mix-in of
:class:`~mpe3d.harness.tracking.store.Tracker`."""

from __future__ import annotations

import socket
import time
from dataclasses import dataclass, field
from typing import Any, Mapping

from mpe3d.harness.tracking.connection import store_errors
from mpe3d.harness.tracking.identity import git_commit
from mpe3d.harness.tracking.ownership import STALE_S, Owner

HASH_TAG = "mpe3d.config_hash"
CODE_TAG = "mpe3d.code"  # the identity of the code that computed a run
CLAIM_TAG = "mpe3d.claim"  # "<code>#<config hash>": one computation, claimed before it starts
OWNER_TAG = "mpe3d.owner"
HEARTBEAT_TAG = "mpe3d.heartbeat"
ERROR_TAG = "mpe3d.error"
UNRECORDED = "unrecorded"  # the code of runs tracked before runs carried their code identity
PARENT_TAG = "mlflow.parentRunId"
# Statuses in the order a resume trusts them: a FINISHED run of a config wins.
STATUS_RANK = {"FINISHED": 3, "FAILED": 2, "KILLED": 1, "RUNNING": 0, "SCHEDULED": 0}


def claim_key(code: str, config_hash: str) -> str:
    return f"{code}#{config_hash}"


@dataclass
class Tracked:
    """What a store holds for one config, as a resume sees it."""

    status: str | None = None  # the best status of a run by the running code
    stale: int = 0  # FINISHED runs by other code
    known: set[str] = field(default_factory=set)  # their run ids: a later one is another sweep's


class Claims:
    """What a sweep needs to own its configs: the store's view of each config,
    claims, zombies, and the sweep's parent run. Mixed into the tracker, whose
    ``client``, ``uri``, ``code``, ``runs_of`` and ``artifact_uris`` it uses."""

    def tracked(self, experiment_id: str, codes: Mapping[str, str] | None = None) -> dict[str, Tracked]:
        """config hash -> what the store holds for it, judged by the running code
        (``codes``: each config's own, where a plug-in adds its part)."""
        codes = codes or {}
        out: dict[str, Tracked] = {}
        with store_errors(self.uri, "read its runs"):
            for run in self.runs_of(experiment_id):
                key, status = run.data.tags.get(HASH_TAG), run.info.status
                if not key:
                    continue
                entry = out.setdefault(key, Tracked())
                if run.data.tags.get(CODE_TAG) != codes.get(key, self.code):
                    entry.stale += status == "FINISHED"
                    continue
                if status in ("FINISHED", "FAILED"):
                    entry.known.add(run.info.run_id)
                if STATUS_RANK.get(status, 0) > STATUS_RANK.get(entry.status, -1):
                    entry.status = status
        return out

    # -- claims: a config is a RUNNING run of its sweep before it is computed ---------

    def child_tags(self, parent_id: str, config_hash: str, code: str, owner: Owner,
                    run_name: str) -> dict[str, str]:
        return {HASH_TAG: config_hash, CODE_TAG: code, CLAIM_TAG: claim_key(code, config_hash),
                PARENT_TAG: parent_id, OWNER_TAG: owner.tag(), "mlflow.runName": run_name}

    def claim(self, experiment_id: str, parent_id: str, config_hash: str, run_name: str,
              owner: Owner, known: set[str], code: str | None = None) -> tuple[str, Any]:
        """Try to own the computation of one config by the running code (``code``
        if a plug-in adds its part to it).

        Create our claim, then look for others: a run that FINISHED or FAILED
        since the plan (``known`` holds the ones before it) means another sweep
        did it; another live claim means another sweep is doing it. Either way
        ours is withdrawn. Two sweeps racing may both withdraw (and retry), but
        never both win: each looks only after its own claim is in the store.

        Returns ``("won", run_id)``, ``("busy", run)`` or ``("done", run)``.
        """
        code = code or self.code
        key = claim_key(code, config_hash)
        with store_errors(self.uri, "claim a run"):
            run = self.client.create_run(experiment_id, run_name=run_name, tags=self.child_tags(
                parent_id, config_hash, code, owner, run_name))
            mine = run.info.run_id
            state, other = self._claim_state(experiment_id, key, known, mine)
            if state == "free":
                self.artifact_uris[mine] = run.info.artifact_uri
                return "won", mine
            self.client.delete_run(mine)
        return ("busy" if state == "busy" else "done"), other

    def claim_state(self, experiment_id: str, config_hash: str, known: set[str],
                    code: str | None = None) -> tuple[str, Any]:
        """``("done" | "busy" | "free", run)``: has another sweep computed this
        config since the plan, is one computing it, or may we claim it? A claim
        whose owner died is closed as KILLED here, and the config is free."""
        with store_errors(self.uri, "read a claim"):
            return self._claim_state(experiment_id, claim_key(code or self.code, config_hash), known)

    def _claim_state(self, experiment_id, key, known, mine=None) -> tuple[str, Any]:
        runs = [r for r in self.runs_of(experiment_id, f"tags.`{CLAIM_TAG}` = '{key}'")
                if r.info.run_id != mine]
        done = [r for r in runs if r.info.status in ("FINISHED", "FAILED") and r.info.run_id not in known]
        if done:
            return "done", max(done, key=lambda r: STATUS_RANK[r.info.status])
        for run in runs:
            if run.info.status == "RUNNING" and not self._close_if_dead(run, {}):
                return "busy", run
        return "free", None

    def _heartbeat_of(self, run, running: dict[str, Any]) -> float | None:
        parent_id = run.data.tags.get(PARENT_TAG)
        parent = run if parent_id is None else running.get(parent_id)
        if parent is None:
            from mlflow.exceptions import MlflowException

            try:
                parent = self.client.get_run(parent_id)
            except MlflowException:
                return None
        beat = parent.data.tags.get(HEARTBEAT_TAG)
        return float(beat) if beat else None

    def _close_if_dead(self, run, running: dict[str, Any]) -> bool:
        """Close ``run`` as KILLED if its owner is dead; whether it was."""
        owner = Owner.parse(run.data.tags.get(OWNER_TAG))
        if owner is None:  # logged by a version of mpe3d without heartbeats
            dead = time.time() - run.info.start_time / 1000 > STALE_S
        else:
            dead = not owner.alive(self._heartbeat_of(run, running))
        if dead:
            self.kill([run.info.run_id], f"its sweep ({owner or 'unknown'}) died before the run ended")
        return dead

    def close_zombies(self, experiment_id: str) -> int:
        """Close every RUNNING run of ``experiment_id`` whose owner is dead
        (children and parents); returns how many children it closed."""
        with store_errors(self.uri, "close the runs of dead sweeps"):
            running = {r.info.run_id: r for r in self.runs_of(experiment_id, "attributes.status = 'RUNNING'")}
            closed = [run for run in running.values() if self._close_if_dead(run, running)]
        return sum(HASH_TAG in run.data.tags for run in closed)

    def kill(self, run_ids, reason: str) -> None:
        """Close runs as KILLED, saying why."""
        for run_id in run_ids:
            self.client.set_tag(run_id, ERROR_TAG, reason)
            self.client.set_terminated(run_id, status="KILLED")

    # -- the sweep's parent run ---------------------------------------------------------

    def start_parent(self, experiment_id: str, sweep, tags: dict[str, str], owner: Owner) -> str:
        """The parent run of one sweep invocation."""
        from mpe3d import __version__

        commit = git_commit()
        tags = {"mpe3d.sweep_file": str(sweep.path), "mpe3d.sweep_sha256": sweep.sha256,
                "mpe3d.scale": sweep.scale, CODE_TAG: self.code,
                "mpe3d.version": __version__, "mpe3d.host": socket.gethostname(),
                OWNER_TAG: owner.tag(), HEARTBEAT_TAG: f"{time.time():.1f}",
                "mlflow.note.content": sweep.description, **tags}
        if commit:
            tags.update({"mpe3d.git_commit": commit, "mlflow.source.git.commit": commit})
        with store_errors(self.uri, "start the sweep's parent run"):
            run = self.client.create_run(experiment_id, tags=tags,
                                         run_name=f"{sweep.name} {time.strftime('%Y-%m-%d %H:%M:%S')}")
        return run.info.run_id

    def heartbeat(self, parent_ids) -> None:
        """Tell other sweeps these parents' owner still lives."""
        now = f"{time.time():.1f}"
        with store_errors(self.uri, "send a heartbeat"):
            for run_id in parent_ids:
                self.client.set_tag(run_id, HEARTBEAT_TAG, now)

    def finish_parent(self, run_id: str, status: str, counts: dict[str, float]) -> None:
        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        with store_errors(self.uri, "close the sweep's parent run"):
            self.client.log_batch(run_id, metrics=[Metric(k, float(v), now, 0)
                                                   for k, v in counts.items()])
            self.client.set_terminated(run_id, status=status, end_time=now)
