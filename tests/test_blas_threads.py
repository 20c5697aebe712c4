"""No result may depend on the BLAS thread count (the developers' guide): the suite runs with one
BLAS thread (tests/conftest.py), a user's machine with as many as it has cores. The diagnosis of
the shared fleet, its whole JSON document, with one BLAS thread and with four."""

from __future__ import annotations

import json

from snapshot import json_differences
from threadpoolctl import threadpool_info, threadpool_limits

from quadcore.physics import vehicle
from quadcore.spec import model
from quadcore.workflows import fleet as fleetlib, identify


def _diagnosis_json(folder, threads: int) -> dict:
    with threadpool_limits(limits=threads, user_api="blas"):
        assert {p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"} == {threads}
        veh = vehicle.load()
        flights = fleetlib.fleet_from_logs([str(folder)], veh)
        return json.loads(identify.diagnosis_json(identify.diagnose(flights, model.spec_from(veh, []), [])))


def test_the_diagnosis_is_the_same_with_one_and_four_blas_threads(drag_fleet):
    one, four = _diagnosis_json(drag_fleet, 1), _diagnosis_json(drag_fleet, 4)
    assert one["candidates"][0]["effect"] == "rotor_drag"  # the fleet's hidden effect: a real diagnosis
    assert json_differences(four, one) == []
