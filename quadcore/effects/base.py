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
fitted by a bounded nonlinear search (:func:`quadcore.identify.fit.fit_effects`).

**In the simulator** an effect is by default evaluated through :meth:`Effect.wrench` on the
true state at every physics step. An effect that is a *mechanism* rather than a memoryless
force (a lag, a delay, a different mass or inertia, a wind that gusts) returns a
:class:`SimHook` from :meth:`Effect.simulator` instead; the simulator calls its methods at
fixed points of its loop and names no effect itself.

To add an effect, write one module with a subclass of :class:`Effect` and an instance
named ``EFFECT`` (see ``docs/adding-an-effect.md``); drop it into ``quadcore/effects/`` or
name its file in the model file's ``plugins`` list.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import numpy as np

from quadcore.effects.ccode import CCode
from quadcore.physics import dynamics
from quadcore.physics.dynamics import FlightState
from quadcore.physics.vehicle import Vehicle

Wrench = tuple[np.ndarray, np.ndarray]  # (f_b (n, 3) N, tau_b (n, 3) N m)
Target = Literal["force", "torque", "both"]
TARGETS: tuple[Target, ...] = ("force", "torque", "both")


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


@dataclass(frozen=True)
class SimContext:
    """What a simulator hook may know about the flight it is part of.

    ``t_s`` (n,) are the controller's instants (the log keeps every one, or every n-th at a
    lower log rate), ``dt_s`` their spacing, ``h_s`` the physics
    step (``dt_s / substeps``); ``vehicle`` is the NOMINAL vehicle (what the controller
    believes); ``config`` the :class:`quadcore.sim.simulation.SimConfig`; ``rng`` a random
    stream reserved for effects (deterministic given the flight's seed).
    """

    t_s: np.ndarray
    dt_s: float
    h_s: float
    vehicle: Vehicle
    config: Any
    rng: np.random.Generator


class SimHook:
    """One effect's part in one simulated flight (it may keep state between calls).

    Every method has a neutral default; override only the ones the mechanism needs. The
    simulator calls, per flight: :meth:`true_mass_kg`, :meth:`true_inertia_kgm2` and
    :meth:`air_velocity_w_mps` once; then at every physics step (``k`` the control sample,
    ``j`` the substep), in the order of the model's effects: :meth:`rotor_thrusts` on the
    rotor thrusts (starting from the thrust map's), and :meth:`wrench` for an extra body
    wrench on the true state. Raise ``ValueError`` for parameters the mechanism cannot fly.
    """

    def true_mass_kg(self, mass_kg: float) -> float:
        """The body's true mass, given the mass so far (nominal, or changed by another hook)."""
        return mass_kg

    def true_inertia_kgm2(self, inertia_kgm2: np.ndarray) -> np.ndarray:
        """The body's true (3, 3) inertia tensor about the centre of mass, body frame."""
        return inertia_kgm2

    def air_velocity_w_mps(self) -> np.ndarray | None:
        """(n, 3) air velocity in the world frame at the log instants, or None for still air.
        Effects with ``acts_on_airspeed`` are evaluated on ``v - air`` in the simulator."""
        return None

    def rotor_thrusts(self, f_N: list[float], k: int, j: int) -> list[float]:
        """The rotor thrusts (N, one per rotor) acting during physics step (k, j), given
        those of the previous stage of the chain (the thrust map's at the start): their mean
        over the step, which is what the rigid body integrates."""
        return f_N

    def thrusts_now(self, f_N: list[float]) -> list[float] | None:
        """The instantaneous rotor thrusts at the start of the coming step, given the previous
        stage's instantaneous ones, or None when they equal the step's mean (a thrust constant
        over the step). The sensors sample these: the accelerometer and the logged motor speed
        at a log instant. Called before :meth:`rotor_thrusts` of the same step."""
        return None

    def wrench(self, state: FlightState, k: int, j: int) -> tuple[list[float], list[float]] | None:
        """Extra body force (N) and torque (N m) during physics step (k, j), from the
        one-sample true ``state`` (its ``f_rotor_N`` is the map thrust, ``motor_radps`` the
        true rotor speed), or None."""
        return None


class ScaleRotorThrusts(SimHook):
    """Simulator hook: every rotor gives ``gains[i]`` times the thrust it is asked for."""

    def __init__(self, gains: list[float]):
        self.gains = [float(g) for g in gains]

    def rotor_thrusts(self, f_N, k, j):
        return [g * f for g, f in zip(self.gains, f_N)]

    def thrusts_now(self, f_N):
        return [g * f for g, f in zip(self.gains, f_N)]


class Effect(ABC):
    """Base class. Subclasses set the class attributes and implement :meth:`wrench`.

    ``name``: unique, the name users write in model files. ``target``: where the effect
    shows up (the diagnosis scores it there). ``linear``: the wrench is linear in the
    parameters (fitted in closed form). ``acts_on_airspeed``: in a simulated wind, the
    simulator evaluates the effect on the velocity relative to the air. ``offered``: the
    diagnosis offers it as a candidate unless asked for others (False for an effect known to
    fit something other than itself on ordinary flights; it can still be put in a model).
    """

    # Not ClassVar: an effect built at run time (quadcore.identify.discovery) sets these per instance.
    name: str = ""
    target: Target = "force"
    linear: ClassVar[bool] = False
    parameters: tuple[Parameter, ...] = ()
    acts_on_airspeed: ClassVar[bool] = False
    offered: ClassVar[bool] = True
    # the effect re-times the rotors' commanded thrust (a lag, a delay): its regressor is built
    # from the closed loop's commands, which react to the gyro noise the measured torque carries,
    # so the diagnosis fits and compares it at the angular-rate level (quadcore.identify.rates)
    retimes_thrust: ClassVar[bool] = False
    # the wrench is linear in the one parameter between its multiples of the sample period (a
    # delay interpolated between samples): the rate level's sums take those multiples as their
    # grid (quadcore.identify.rates.rate_grid), exact between them where a smooth interpolant
    # of a coarser grid would round off the kinks
    linear_between_samples: ClassVar[bool] = False
    doc: str = ""
    # values of some parameters at which the others' sensitivity is stated, for parameters
    # that show only through another (a wind only through a drag); see quadcore.identify.evidence
    sensitivity_reference: ClassVar[dict[str, float]] = {}

    def defaults(self) -> dict[str, float]:
        return {p.name: p.default for p in self.parameters}

    @abstractmethod
    def wrench(self, state: FlightState, vehicle: Vehicle, params: dict[str, float]) -> Wrench:
        """Body-frame force and torque added to the model, over the whole flight."""

    def memory_s(self) -> float:
        """How long after a log's first sample the wrench still depends on the flight before it
        (a filter settling from an initial state it cannot know, a delay's history): within
        this time the fits, held-out tests and predictions of the identification take no part of
        it (:func:`quadcore.identify.flightdata.prediction`), so a flight whose log starts in a
        manoeuvre does not bias them. The same for every parameter value (a fit compares values
        on the same samples): take the longest the parameter's range allows. 0, the default,
        for memoryless effects."""
        return 0.0

    def simulator(self, params: dict[str, float], context: SimContext) -> SimHook | None:
        """The mechanism to fly in the simulator, or None (the default): then the simulator
        adds :meth:`wrench` evaluated on the true state at every physics step, which is
        right for effects without memory."""
        return None

    def check(self, params: dict[str, float]) -> None:  # noqa: B027 (optional hook: no check by default)
        """Raise ``ValueError`` for parameter values that make no sense at all (wider than
        the fitting bounds: a simulation may go beyond those)."""

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

    def c_code(self, vehicle: Vehicle, params: dict[str, float]) -> CCode | None:
        """The wrench as C99 statements for ``quadcore export-c`` (see :mod:`quadcore.effects.ccode`).
        ``None``, the default, means no C form: exporting a model with this effect fails with
        an error naming it."""
        return None

    def __repr__(self) -> str:
        return f"<effect {self.name}: {', '.join(p.name for p in self.parameters)}>"


def body_z(values: np.ndarray) -> np.ndarray:
    """(n, 3) vectors along body z with the given magnitudes."""
    out = np.zeros((len(values), 3))
    out[:, 2] = values
    return out


def rotor_wrench(vehicle: Vehicle, f_rotor_N: np.ndarray) -> Wrench:
    """The body wrench of extra rotor thrusts (n, rotors): ``(0, 0, T)`` and ``A[1:4] f``."""
    T, tau = dynamics.wrench_from_thrusts(vehicle, f_rotor_N)
    return body_z(T), tau


def collective_thrust_N(state: FlightState) -> np.ndarray:
    return state.f_rotor_N.sum(axis=1)
