"""The main job's runs, submitted to a cluster instead of executed in this process.

With ``QUADCORE_CLUSTER_URL`` set (``make cluster-up`` writes it to ``.cluster/env``), every
materialisation of the main job (:mod:`pipeline.run.main`) is a run submitted through the
webserver's GraphQL API to the instance's run queue: the daemon launches it when a slot is
free, its steps run on the Celery workers, and this process waits for it and reads its events
from the shared instance (PostgreSQL). The stages, their order and what counts as stale are the
same as on one machine: only where the work runs changes.
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from urllib.parse import urlparse

import dagster as dg
from dagster_graphql import DagsterGraphQLClient

from pipeline.cluster.services import DAEMON_SILENT_S, daemon_beat
from pipeline.resources import SettingError

# Polling the instance for the runs' ends: a run of the main job takes seconds to minutes.
POLL_S = 1.0
# Our location's name in deploy/local/workspace.yaml.
LOCATION = "quadcore"
# The implicit job of all assets: a submission names the assets it materialises.
ASSET_JOB = "__ASSET_JOB"
ENDED = {dg.DagsterRunStatus.SUCCESS, dg.DagsterRunStatus.FAILURE, dg.DagsterRunStatus.CANCELED}
# The longest the main job waits for its runs (QUADCORE_CLUSTER_TIMEOUT_S): a run that hangs
# (a step whose worker never answers) would otherwise hold the data root's lock for ever. The
# 100 simulated flights' slowest stage took minutes here (docs/benchmarks.md#local-cluster).
WAIT_TIMEOUT_S = 6 * 3600.0
# The daemon's retry of a failed run appears within a few of its loops.
RETRY_APPEARS_S = 60.0


class ClusterUnavailable(RuntimeError):
    """The cluster cannot run what was submitted (its daemon is not running): one line for the user."""


def cluster_url() -> str | None:
    """The cluster's webserver (``QUADCORE_CLUSTER_URL``), or None: runs in this process."""
    return os.environ.get("QUADCORE_CLUSTER_URL", "").strip() or None


@dataclass
class SubmittedRun:
    """A run submitted to the cluster, read back as :func:`dagster.materialize`'s result is read:
    ``success``, the step failure events and all events (for the failure reasons)."""

    run_id: str
    instance: dg.DagsterInstance

    @property
    def success(self) -> bool:
        run = self.instance.get_run_by_id(self.run_id)
        return run is not None and run.status == dg.DagsterRunStatus.SUCCESS

    @property
    def all_events(self) -> list[dg.DagsterEvent]:
        return [e.dagster_event for e in self.instance.all_logs(self.run_id) if e.dagster_event is not None]

    def get_step_failure_events(self) -> list[dg.DagsterEvent]:
        return [e for e in self.all_events if e.is_step_failure]

    def asset_materializations_for_node(self, node: str) -> list[dg.AssetMaterialization]:
        return [e.step_materialization_data.materialization for e in self.all_events
                if e.is_step_materialization and e.step_key == node]


def _client():
    url = urlparse(cluster_url() or "")
    return DagsterGraphQLClient(url.hostname or "127.0.0.1", port_number=url.port, timeout=120)


def submit(assets, tags: dict[str, str] | None = None) -> str:
    """One run of ``assets`` (keys, partitions in ``tags``) in the cluster's queue; its id."""
    keys = [key for a in assets for key in a.keys]
    return _client().submit_job_execution(ASSET_JOB, repository_location_name=LOCATION,
                                          tags={"quadcore/main": "yes", **(tags or {})}, asset_selection=keys)


def wait_timeout_s() -> float:
    """``QUADCORE_CLUSTER_TIMEOUT_S`` (default :data:`WAIT_TIMEOUT_S`); :class:`SettingError` when
    it is not a positive number of seconds."""
    text = os.environ.get("QUADCORE_CLUSTER_TIMEOUT_S", "").strip()
    try:
        value = float(text) if text else WAIT_TIMEOUT_S
    except ValueError:
        value = -1.0
    if not value > 0 or value == float("inf"):
        raise SettingError(f"QUADCORE_CLUSTER_TIMEOUT_S={text!r}: give a positive number of seconds "
                           f"(default {WAIT_TIMEOUT_S:.0f})")
    return value


def wait(instance: dg.DagsterInstance, run_ids: Sequence[str], retries: bool = True,
         timeout_s: float | None = None) -> list[SubmittedRun]:
    """Wait until each run has ended: a run retried by the daemon (``run_retries``) is followed
    to its last retry. The runs, read back. Past ``timeout_s`` (default :func:`wait_timeout_s`)
    the runs still going are terminated and :class:`ClusterUnavailable` says so."""
    limit = wait_timeout_s() if timeout_s is None else timeout_s
    deadline = time.monotonic() + limit
    final = list(run_ids)
    while True:
        runs = [instance.get_run_by_id(r) for r in final]
        if any(r is not None and r.status == dg.DagsterRunStatus.QUEUED for r in runs):
            check_daemon(instance)
        if all(r is not None and r.status in ENDED for r in runs):
            retried = [_retry_of(instance, r) if retries and r is not None and r.status != dg.DagsterRunStatus.SUCCESS
                       else None for r in runs]
            if not any(retried):
                return [SubmittedRun(r, instance) for r in final]
            final = [new or old for new, old in zip(retried, final)]
        elif time.monotonic() > deadline:
            give_up([r.run_id for r in runs if r is not None and r.status not in ENDED], limit)
        time.sleep(POLL_S)


def check_daemon(instance: dg.DagsterInstance) -> None:
    """:class:`ClusterUnavailable` when the daemon's run coordinator has not beaten for
    :data:`DAEMON_SILENT_S` (or never): queued runs would never start."""
    beat = daemon_beat(instance)
    if beat is None or time.time() - beat > DAEMON_SILENT_S:
        raise ClusterUnavailable("the cluster's daemon is not running, so the queued runs cannot start: "
                                 "`make cluster-up` starts it again (its log: .cluster/logs/daemon.log)")


def give_up(run_ids: list[str], limit_s: float) -> None:
    """Terminate the runs still going (through the webserver) and raise :class:`ClusterUnavailable`."""
    try:
        if run_ids:
            _client().terminate_runs(run_ids)
        what = "terminated"
    except Exception as exc:  # the webserver gone too: say so, the runs' ids are in the line
        what = f"could not be terminated ({type(exc).__name__}): stop them in the UI"
    raise ClusterUnavailable(f"the cluster's runs did not end within the wait's limit (QUADCORE_CLUSTER_TIMEOUT_S, "
                             f"{limit_s:.0f} s); the runs still going, {', '.join(run_ids) or 'none'}, "
                             f"{what}; their logs: .cluster/logs and the UI")


def _retry_of(instance: dg.DagsterInstance, run) -> str | None:
    """The daemon's retry of a failed run, if it made or will make one. Dagster decides when the
    run fails and records it on the run (``dagster/will_retry``: false for a step's own failure, a
    bad flight, with ``retry_on_asset_or_op_failure: false`` in deploy/local/dagster.yaml); a
    run without that tag is expected to be retried while ``dagster/retry_number`` is below the
    retries allowed."""
    will = run.tags.get("dagster/will_retry")
    if will is not None:
        expected = will == "true"
    else:
        max_retries = int(run.tags.get("dagster/max_retries", instance.run_retries_max_retries))
        number = int(run.tags.get("dagster/retry_number", "0"))
        expected = instance.run_retries_enabled and number < max_retries
    expected = expected and run.status == dg.DagsterRunStatus.FAILURE
    deadline = time.monotonic() + (RETRY_APPEARS_S if expected else 0.0)  # the daemon's loop runs every few seconds
    while True:
        found = instance.get_runs(filters=dg.RunsFilter(tags={"dagster/parent_run_id": run.run_id}))
        if found:
            return found[0].run_id
        if time.monotonic() >= deadline:
            return None
        time.sleep(POLL_S)
