"""The per-flight thumbnails: one figure per layout is reused from flight to flight, so a
flight's plot must not depend on the flights drawn before it."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from quadcore.identify import model
from quadcore.logs import flight
from quadcore.physics import dynamics, propagation, vehicle
from quadcore.report import plots


@pytest.fixture(scope="module")
def two_flights(drag_fleet):
    """(residual table, rollout error growth) of two simulated flights, nominal model."""
    veh = vehicle.load()
    nominal = model.PhysicsModel(veh, [])
    out = []
    for log in sorted(drag_fleet.glob("sim00[03]")):
        decoded = flight.decode_flight(log).tables["fixedFrequency"]
        state = dynamics.flight_state(decoded, veh)
        out.append((nominal.residual_table(decoded), propagation.error_growth(state, veh, horizons_s=(0.1, 0.5))))
    return out


def _pixels(png: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(png)))


@pytest.mark.parametrize("draw", [lambda f: plots.model_vs_measured(f[0], "a"),
                                  lambda f: plots.error_growth(f[1], "a")], ids=["model_vs_measured", "error_growth"])
def test_a_flights_thumbnail_does_not_depend_on_the_flight_drawn_before(two_flights, draw):
    first, second = two_flights
    a = _pixels(draw(first))
    b = _pixels(draw(second))
    again = _pixels(draw(first))
    assert a.shape == b.shape and not np.array_equal(a, b)  # another flight, another picture
    np.testing.assert_array_equal(again, a)  # same lines, limits, colours and legend as the first time
