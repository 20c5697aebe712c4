"""What each explanation predicts along a planned flight.

An explanation is an effect of the library with the parameters the diagnosis fitted on the
flights already logged (:class:`Explanation`). Along a planned trajectory its wrench is
``effect.wrench`` evaluated on the flat state (:mod:`quadcore.plan.flatness`) and passed
through the residual's filters (:func:`quadcore.identify.flightdata.prediction`: force through
the smoother, torque through the gyro derivative's filter), exactly as it would appear in the
residual of the flight once flown and logged.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from quadcore import effects as effectlib
from quadcore.identify import flightdata
from quadcore.physics import signals
from quadcore.physics.vehicle import Vehicle
from quadcore.plan import flatness
from quadcore.sim.trajectories import PolyTrajectory

PLANNED = "planned"  # the planned flight's name among the flights
ACTIVITY_S = 30.0  # seconds of the logged flights' closed-loop rotor activity kept


@dataclass(frozen=True)
class Explanation:
    """An effect with the parameters (and standard errors) fitted on the logged flights."""

    effect: effectlib.Effect
    params: Mapping[str, float]
    std: Mapping[str, float]

    @property
    def name(self) -> str:
        return self.effect.name


def activity(old: Sequence[flightdata.FlightData], seconds: float = ACTIVITY_S) -> np.ndarray:
    """(n, rotors) the closed loop's own rotor-thrust activity on the logged flights: each rotor's
    thrust minus its smoothed course (what the attitude controller does against sensor noise
    and small disturbances, broadband up to the log rate), ``seconds`` of the first flights'
    usable samples. Whatever is flown, the controller adds this; it is what tells a lag from a
    delay in hover."""
    parts, n = [], 0
    for fd in old:
        f = fd.state.f_rotor_N[fd.mask]
        parts.append(f - signals.smooth(f))
        n += len(f)
        if n >= seconds * flatness.LOG_RATE_HZ:
            break
    return np.concatenate(parts) if parts else np.zeros((0, 4))


def planned_flight(traj: PolyTrajectory, vehicle: Vehicle, closed_loop: np.ndarray | None = None,
                   rate_hz: float = flatness.LOG_RATE_HZ) -> flightdata.FlightData:
    """The planned flight as the fits take a flight: its noise-free flat state (plus, given, the
    closed loop's rotor-thrust ``activity`` repeated along it), a zero residual, every sample usable."""
    state = flatness.flight_state(flatness.flat_path(traj, vehicle, rate_hz), vehicle)
    if closed_loop is not None and len(closed_loop) and closed_loop.shape[1] == state.f_rotor_N.shape[1]:
        reps = int(np.ceil(state.n / len(closed_loop)))
        state.f_rotor_N = state.f_rotor_N + np.tile(closed_loop, (reps, 1))[: state.n]
    zeros = np.zeros((state.n, 3))
    return flightdata.FlightData(PLANNED, state, zeros, zeros.copy(), np.ones(state.n, dtype=bool))


def predict(expl: Explanation, fd: flightdata.FlightData, vehicle: Vehicle) -> np.ndarray:
    """(n, 6) the explanation's wrench as it appears in the residual (N, N m; body frame)."""
    return flightdata.prediction(expl.effect, dict(expl.params), fd, vehicle)


def unit_wrench(expl: Explanation, parameter: str, fd: flightdata.FlightData, vehicle: Vehicle) -> np.ndarray:
    """(n, 6) the change of the prediction per unit of ``parameter`` at the fitted values (a
    secant over 1 % of the parameter's range, inward from a bound)."""
    p = next(q for q in expl.effect.parameters if q.name == parameter)
    step = 0.01 * (p.upper - p.lower)
    params = dict(expl.params)
    base = flightdata.prediction(expl.effect, params, fd, vehicle)
    step = step if params[parameter] + step <= p.upper else -step
    params[parameter] += step
    return (flightdata.prediction(expl.effect, params, fd, vehicle) - base) / step
