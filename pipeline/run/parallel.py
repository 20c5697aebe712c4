"""Both cores in the main job's per-flight stages: a long range of flight partitions split in two
halves, one materialised in this process and the other, at the same time, in a second process
(spawned: it imports the definitions afresh, and Polars must not be forked). Each half is one
Dagster run on the same instance, so each flight keeps its own partition. Dagster's SQLite
storage takes two concurrent runs: each run's events go to a file of its own; the shared files
(the runs, the asset index) are in WAL mode and a writer waits for the other's short transaction
(busy timeout 5 s for the runs, ``SQLITE_BUSY_TIMEOUT_SECONDS`` = 30 s for the index) instead of
failing; the instance's ``max_concurrent_runs: 2`` allows as many. A range too short to repay
the second process's start-up (:data:`SPLIT_AT_FLIGHTS`) and ``QUADCORE_EXECUTOR=in_process``
stay in one process. ``QUADCORE_EXECUTOR=multiprocess`` runs each range as one run through
Dagster's multiprocess executor instead (each step a process of its own, two at once: the
alternative issue 26 measured against this split, ``benchmarks/bench_executors.py``).
"""

from __future__ import annotations

import multiprocessing
import os
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, replace
from pathlib import Path

import dagster as dg
import numpy as np
from dagster._core.instance.ref import InstanceRef
from dagster._core.storage.tags import ASSET_PARTITION_RANGE_END_TAG, ASSET_PARTITION_RANGE_START_TAG
from dagster._serdes import deserialize_value, serialize_value
from threadpoolctl import threadpool_limits

from pipeline.assets import EXPORT, FLEET, LEARNING, PER_FLIGHT
from pipeline.cluster import launch
from pipeline.partitions import failed_flights
from pipeline.resources import DataRoot, ModelConfig
from pipeline.run.instance import unsynced_event_log, unsynced_homes

# Keep the console to our progress lines (one per skipped flight, with its reason); Dagster's own
# events, a failed step's error and stack trace included, stay in the instance's event log (the UI).
QUIET = {"loggers": {"console": {"config": {"log_level": "CRITICAL"}}}}

# Split a range in two from this many flights. The second process's start-up (the definitions,
# then each asset's libraries on its first flight: 4-5 s under load here) takes what half a short
# range saves: on the 19 real flights at load average ~3 the split took as long as one process
# (statistics 8.2 / 7.9 s against 8.2 / 7.8 s; residuals, rollouts and MCAP 10.1 / 8.8 s against
# 10.1 / 8.4 s). benchmarks/bench_scale.py --per-flight 20 100 measures both sides of it.
SPLIT_AT_FLIGHTS = 40
# Decoding costs 0.05-0.25 s a flight: the split pays only on many more flights.
DECODE_SPLIT_AT = 100
# Dagster's multiprocess executor (QUADCORE_EXECUTOR=multiprocess): steps at once, one per core.
MAX_CONCURRENT_STEPS = 2


@dataclass(frozen=True)
class RangeOutcome:
    """What the main job needs of one run over a range of flights: whether it succeeded, the
    failed flights with their reasons (``failed_flights`` of its steps) and the failures' own
    messages, and its wall time."""

    success: bool
    failed: dict[str, str]
    reason: str
    seconds: float


def range_tags(keys: Sequence[str]) -> dict[str, str]:
    return {ASSET_PARTITION_RANGE_START_TAG: keys[0], ASSET_PARTITION_RANGE_END_TAG: keys[-1]}


def failure_reason(result) -> str:
    """The failures' own messages, once each (without Dagster's exception class prefix)."""
    reasons = [
        e.step_failure_data.error.message.strip().splitlines()[0].split("Failure: ", 1)[-1]
        for e in result.all_events
        if e.is_step_failure and e.step_failure_data and e.step_failure_data.error
    ]
    return "; ".join(dict.fromkeys(reasons)) or "failed"


def materialize(assets, resources, instance, partition_key=None, tags=None):
    """One run of ``assets``: in this process, or on the cluster when ``QUADCORE_CLUSTER_URL`` is
    set (:mod:`pipeline.cluster.launch`: the code location's resources, which the same
    environment configures)."""
    run_tags = {**(tags or {}), **({"dagster/partition": partition_key} if partition_key else {})}
    if launch.cluster_url():
        return launch.wait(instance, [launch.submit(assets, run_tags)])[0]
    if executor_kind() == "multiprocess":
        return _multiprocess(assets, resources, instance, run_tags)
    return dg.materialize(assets, partition_key=partition_key, instance=instance, resources=resources,
                          run_config=QUIET, raise_on_error=False, tags=tags)


def materialize_range(assets, resources: dict, instance, keys: Sequence[str]) -> RangeOutcome:
    """One run of ``assets`` over the flight partitions ``keys`` (consecutive), in this process."""
    t0 = time.perf_counter()
    result = materialize(assets, resources, instance, tags=range_tags(keys))
    return outcome(result, time.perf_counter() - t0)


def outcome(result, seconds: float) -> RangeOutcome:
    """A run's result (in this process or on the cluster) as the main job reads it."""
    if result.success:
        return RangeOutcome(True, {}, "", seconds)
    return RangeOutcome(False, failed_flights(result), failure_reason(result), seconds)


def executor_kind() -> str:
    """``QUADCORE_EXECUTOR`` as the main job reads it (validated by ``pipeline.resources.executor_from_env``)."""
    return os.environ.get("QUADCORE_EXECUTOR", "").strip().lower()


def one_process() -> bool:
    """``QUADCORE_EXECUTOR=in_process``: every run of the main job in this process;
    ``multiprocess``: no split of ours either (Dagster's executor spreads the steps)."""
    return executor_kind() in ("in_process", "multiprocess")


def _multiprocess(assets, resources: dict, instance, tags: dict[str, str]) -> launch.SubmittedRun:
    """One run of ``assets`` through Dagster's multiprocess executor: each step in a process of
    its own (:data:`MAX_CONCURRENT_STEPS` at once) that rebuilds the job from
    :func:`asset_job` with these resources' configs; read back from the instance."""
    names = [a.key.to_user_string() for a in assets]
    configs = {name: r.model_dump() for name, r in resources.items()}
    job = dg.build_reconstructable_job("pipeline.run.parallel", "asset_job",
                                       reconstructable_kwargs={"names": names, "configs": configs})
    run_config = {**QUIET, "execution": {"config": {"multiprocess": {"max_concurrent": MAX_CONCURRENT_STEPS}}}}
    with dg.execute_job(job, instance, run_config=run_config, tags=tags, raise_on_error=False) as result:
        return launch.SubmittedRun(result.run_id, instance)


def asset_job(names: list[str], configs: dict[str, dict]) -> dg.JobDefinition:
    """The job of the assets ``names`` with the main job's resources (``data_root``, ``model``
    from their configs): what each step process of :func:`_multiprocess` rebuilds."""
    every = [*PER_FLIGHT, *FLEET, *LEARNING, *EXPORT]
    job = dg.define_asset_job("quadcore_main", selection=[a.key for a in every if a.key.to_user_string() in names])
    resources = {"data_root": DataRoot(**configs["data_root"]), "model": ModelConfig(**configs["model"])}
    return dg.Definitions(assets=every, resources=resources, jobs=[job]).resolve_job_def("quadcore_main")


def halves(keys: list[str], sizes: Sequence[float] | None = None, split_at: int | None = None) -> list[list[str]]:
    """A range of at least ``split_at`` flights (default :data:`SPLIT_AT_FLIGHTS`) as two ranges
    of consecutive partitions of about the same work: the same total of ``sizes`` (the flights'
    log bytes: the time per flight grows with its samples) or, without them, of flights. Else
    the range itself."""
    if launch.cluster_url():  # a run per worker: the cluster runs them at once
        split_at = 2
    if len(keys) < (SPLIT_AT_FLIGHTS if split_at is None else split_at) or one_process():
        return [keys]
    cumulative = np.cumsum(sizes if sizes is not None else np.ones(len(keys)))
    middle = int(np.clip(np.argmin(np.abs(cumulative - cumulative[-1] / 2)) + 1, 1, len(keys) - 1))
    return [keys[:middle], keys[middle:]]


def log_sizes(data_root, keys: Sequence[str]) -> list[float] | None:
    """The flights' raw log sizes in bytes (None when one is unreadable: split by count)."""
    try:
        return [float(data_root.raw_log(k).stat().st_size) for k in keys]
    except (OSError, ValueError):
        return None


def materialize_ranges(assets, resources: dict, instance, ranges: list[list[str]]) -> list[RangeOutcome]:
    """One run per range: one range in this process; two at once, the second in the second
    process (:func:`second_process`) on the same instance (``instance.get_ref()``). A second
    process that dies (killed, out of memory) leaves its range to this process, so its flights
    still run."""
    if launch.cluster_url():
        return _on_cluster(assets, instance, ranges)
    if len(ranges) == 1:
        return [materialize_range(assets, resources, instance, ranges[0])]
    first, second = ranges
    names = [a.key.to_user_string() for a in assets]
    ref = serialize_value(instance.get_ref())  # Dagster's records do not pickle; its serdes does
    # a resource used in a run holds Dagster state that does not pickle either: its class and config
    configs = {name: (type(r), r.model_dump()) for name, r in resources.items()}
    t0 = time.perf_counter()
    other = second_process().submit(_materialize_in_child, ref, sorted(unsynced_homes()), configs, names, second)
    with one_blas_thread():
        here = materialize_range(assets, resources, instance, first)
    try:  # the second half's time with the second process's start-up, if it started now
        return [here, replace(other.result(), seconds=time.perf_counter() - t0)]
    except BrokenProcessPool:
        shutdown()
        return [here, materialize_range(assets, resources, instance, second)]


def _on_cluster(assets, instance, ranges: list[list[str]]) -> list[RangeOutcome]:
    """Every range a run in the cluster's queue at once; the daemon runs as many as it allows."""
    t0 = time.perf_counter()
    runs = launch.wait(instance, [launch.submit(assets, range_tags(keys)) for keys in ranges])
    return [outcome(run, time.perf_counter() - t0) for run in runs]


_POOL: list[ProcessPoolExecutor] = []


def second_process() -> ProcessPoolExecutor:
    """The second process, started on first use and kept until :func:`shutdown`: the main job's
    stages share it, so its start-up (the definitions, then each asset's libraries on its first
    flight) is paid once per job, not once per stage."""
    if not _POOL:
        _POOL.append(ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn")))
    return _POOL[0]


def shutdown() -> None:
    """End the second process (if started)."""
    while _POOL:
        _POOL.pop().shutdown(wait=True, cancel_futures=True)


def _materialize_in_child(ref: str, homes: list[str], configs: dict, names: list[str],
                          keys: list[str]) -> RangeOutcome:
    """:func:`materialize_range` in the second process: the per-flight assets named ``names``,
    the resources from their classes and configs, the instance from its serialised ref (its
    SQLite files written as the parent writes them)."""
    resources = {name: cls(**config) for name, (cls, config) in configs.items()}
    for home in homes:
        unsynced_event_log(Path(home))
    assets = [a for a in PER_FLIGHT if a.key.to_user_string() in names]
    with dg.DagsterInstance.from_ref(deserialize_value(ref, InstanceRef)) as instance, one_blas_thread():
        return materialize_range(assets, resources, instance, keys)


def one_blas_thread():
    """One BLAS thread in each of the two processes while both work: two of OpenBLAS's threads
    per process on two cores wait for each other (see :func:`quadcore.identify.flightdata.one_blas_thread`)."""
    return threadpool_limits(limits=1, user_api="blas")
