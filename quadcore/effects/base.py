"""The shape every physical effect follows.

An effect adds a force ``f_b`` (N) and a torque ``tau_b`` (N m), both in the body frame,
to the nominal model, as a function of the flight state and a few physically meaningful
parameters in SI units::

    f_extra_b, tau_extra_b = effect.wrench(state, vehicle, params)

Effects compose by adding their wrenches. An effect that is *linear in its parameters*
(``wrench = Σ_k (p_k - default_k) B_k(state)``) declares ``linear = True`` and gives the
basis ``B_k`` through :meth:`Effect.basis`; it is fitted by linear least squares. An
effect linear in some other coordinates ``c`` (e.g. ``m_p / (m + m_p)``) gives its basis
per unit of ``c`` and maps back with ``from_linear`` / ``to_linear``. Any other effect is
fitted by a bounded nonlinear least-squares (:func:`quadcore.effects.fit`).

To add an effect, write one module with a subclass of :class:`Effect` and an instance
named ``EFFECT`` (see ``docs/adding-an-effect.md``); drop it into ``quadcore/effects/`` or
name its file in the model file's ``plugins`` list.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from quadcore.dynamics import FlightState
from quadcore.vehicle import Vehicle

Wrench = tuple[np.ndarray, np.ndarray]  # (f_b (n, 3) N, tau_b (n, 3) N m)


@dataclass(frozen=True)
class Parameter:
    """One parameter: name (with its unit as suffix), unit, default (the value that means
    'no effect'), bounds for fitting, and a one-line meaning."""

    name: str
    unit: str
    default: float
    lower: float
    upper: float
    doc: str = ""


class Effect:
    """Base class. Subclasses set the class attributes and implement :meth:`wrench`."""

    name: str = ""
    target: str = "force"  # "force", "torque" or "both": where the effect shows up
    linear: bool = False
    parameters: tuple[Parameter, ...] = ()
    doc: str = ""

    def defaults(self) -> dict[str, float]:
        return {p.name: p.default for p in self.parameters}

    def wrench(self, state: FlightState, vehicle: Vehicle, params: dict[str, float]) -> Wrench:
        """Body-frame force and torque added to the model, over the whole flight."""
        raise NotImplementedError

    def basis(self, state: FlightState, vehicle: Vehicle) -> list[Wrench]:
        """For linear effects: the wrench per unit of each linear coordinate, in order.

        The default derives it from :meth:`wrench` as ``wrench(default + e_k)`` (the
        wrench at the defaults is zero: they mean 'no effect'); override when a closed
        form is clearer or cheaper.
        """
        out = []
        for p in self.parameters:
            params = self.defaults()
            params[p.name] += 1.0
            out.append(self.wrench(state, vehicle, params))
        return out

    def from_linear(self, coefficients, vehicle: Vehicle) -> dict[str, float]:
        """Parameters from fitted linear coordinates (default: ``p_k = default_k + c_k``)."""
        return {p.name: p.default + float(c) for p, c in zip(self.parameters, coefficients)}

    def to_linear(self, params: dict[str, float], vehicle: Vehicle) -> list[float]:
        return [params[p.name] - p.default for p in self.parameters]

    def __repr__(self) -> str:
        return f"<effect {self.name}: {', '.join(p.name for p in self.parameters)}>"


def body_z(values: np.ndarray) -> np.ndarray:
    """(n, 3) vectors along body z with the given magnitudes."""
    out = np.zeros((len(values), 3))
    out[:, 2] = values
    return out


def collective_thrust_N(state: FlightState) -> np.ndarray:
    return state.f_rotor_N.sum(axis=1)
