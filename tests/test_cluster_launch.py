"""The main job's wait for cluster runs (pipeline.cluster.launch), without a cluster: a queued run
whose daemon is not running is a one-line error, not a wait for ever."""

from __future__ import annotations

import time
from pathlib import Path
from types import SimpleNamespace

import dagster as dg
import pytest

from pipeline.cluster import launch


class _Instance:
    """The two calls :func:`launch.wait` makes of an instance: a run that stays queued, and the
    daemon's heartbeats (``beats``: name -> seconds ago)."""

    def __init__(self, beats: dict[str, float]):
        self.beats = beats

    def get_run_by_id(self, run_id):
        return SimpleNamespace(run_id=run_id, status=dg.DagsterRunStatus.QUEUED, tags={})

    def get_daemon_heartbeats(self):
        return {name: SimpleNamespace(timestamp=time.time() - ago) for name, ago in self.beats.items()}


@pytest.mark.parametrize("beats", [{}, {"QUEUED_RUN_COORDINATOR": launch.DAEMON_SILENT_S + 5}])
def test_a_queued_run_without_a_running_daemon_is_an_error(beats):
    with pytest.raises(launch.ClusterUnavailable, match="daemon is not running"):
        launch.wait(_Instance(beats), ["run-1"])


def test_a_queued_run_with_a_beating_daemon_waits(monkeypatch):
    polls = []

    def stop_after_two(_s):
        polls.append(1)
        if len(polls) == 2:
            raise TimeoutError("still waiting, as it should")

    monkeypatch.setattr(launch.time, "sleep", stop_after_two)
    with pytest.raises(TimeoutError):
        launch.wait(_Instance({"QUEUED_RUN_COORDINATOR": 1.0}), ["run-1"])


class _Client:
    def __init__(self):
        self.terminated: list[str] = []

    def terminate_runs(self, run_ids):
        self.terminated += run_ids


def test_runs_that_outlive_the_wait_are_terminated_and_the_job_stops(monkeypatch):
    class Running(_Instance):
        def get_run_by_id(self, run_id):
            return SimpleNamespace(run_id=run_id, status=dg.DagsterRunStatus.STARTED, tags={})

    client = _Client()
    monkeypatch.setattr(launch, "_client", lambda: client)
    monkeypatch.setattr(launch.time, "sleep", lambda _s: None)
    with pytest.raises(launch.ClusterUnavailable, match="did not end within .* run-1, run-2, terminated"):
        launch.wait(Running({"QUEUED_RUN_COORDINATOR": 1.0}), ["run-1", "run-2"], timeout_s=0.05)
    assert client.terminated == ["run-1", "run-2"]


@pytest.mark.parametrize("text", ["abc", "0", "-5", "inf", "nan"])
def test_a_bad_wait_limit_is_a_one_line_user_error(monkeypatch, capsys, text):
    from pipeline.run import main

    monkeypatch.setenv("QUADCORE_CLUSTER_URL", "http://127.0.0.1:9")
    monkeypatch.setenv("QUADCORE_CLUSTER_TIMEOUT_S", text)
    assert main.main([]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"error: QUADCORE_CLUSTER_TIMEOUT_S={text!r}: give a positive number of seconds (default 21600)"]


def _local_retries() -> dict:
    import yaml  # type: ignore[import-untyped]

    return yaml.safe_load((Path(launch.__file__).parents[2] / "deploy" / "local" / "dagster.yaml").read_text())[
        "run_retries"]


@dg.asset
def _bad_flight():
    raise dg.Failure("jana99: the log is truncated")


@pytest.mark.parametrize(("retries", "retried"),
                         [(_local_retries(), False), ({"enabled": True, "max_retries": 2}, True)])
def test_a_run_failed_by_a_step_is_not_retried_on_the_cluster(retries, retried):
    """The local cluster's instance settings, in a real instance: a run whose step failed (a bad
    flight: the same input fails the same way) is marked not to be retried, and the main job's
    wait does not look for a retry; Dagster's default settings would retry it."""
    with dg.instance_for_test(overrides={"run_retries": retries}) as instance:
        result = dg.materialize([_bad_flight], instance=instance, raise_on_error=False)
        run = instance.get_run_by_id(result.run_id)
        assert run.status == dg.DagsterRunStatus.FAILURE
        assert run.tags.get("dagster/will_retry") == str(retried).lower()
        if not retried:
            t0 = time.monotonic()
            assert launch._retry_of(instance, run) is None
            assert time.monotonic() - t0 < launch.RETRY_APPEARS_S / 2
