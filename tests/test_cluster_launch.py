"""The main job's wait for cluster runs (pipeline.cluster.launch), without a cluster: a queued run
whose daemon is not running is a one-line error, not a wait for ever."""

from __future__ import annotations

import time
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
