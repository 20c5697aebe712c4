"""The planner's objective for a timing question (a lag against a delay, or a timing parameter),
in the statistic the diagnosis decides it by: the angular-rate level
(:mod:`quadcore.identify.rates`), not the torque channels.

**Separation.** Suppose timing candidate A is true at the value the diagnosis fitted. A flight's
rate-level residual is then ``R = C_A + n``: A's running sums plus the noise the logs show at that
level. The diagnosis's comparison (:func:`quadcore.identify.rates.difference_test`) scores each
block by ``g_b = Σ_a w_a Σ_k [(R − C_B)² − (R − C_A)²]`` (block means removed, ``w`` the rate
level's weights, :func:`quadcore.identify.rates.weights`), with mean
``D_b = Σ_a w_a D_ba``, ``D_ba = Σ_k (C̃_A − C̃_B)²`` (what B at its best fit cannot reproduce of
A, :meth:`quadcore.identify.rates.RateSums.costs` of B on a flight whose residual is A's running
sums, made with :func:`hypothetical`) and, for noise of variance ``s_a²`` per interval and axis,
variance ``4 Σ_a w_a² s_a² D_ba``; the test regresses ``g`` on ``D``, so the blocks' spread in
``D`` is no noise, and its expected t is

    t = Σ_b D_b / (2 sqrt(Σ_b Σ_a w_a² s_a² D_ba))

In the held-out view of the diagnosis's folds (as :mod:`quadcore.plan.objective`): the planned
flight is scored with B fitted (:func:`quadcore.identify.rates.fit`) on the old flights, the old
flights with B fitted on old and planned together. The same with B true; the design's
separation is the smaller. ``s_a²``: the rate-level residual per interval the logged flights
leave after the better of the two fitted candidates (or of neither): the sensor noise as it
appears there, plus whatever the model lacks. Every running sum goes through the whitening
filter the diagnosis uses (:func:`quadcore.identify.rates.gyro_noise_model`, the gyro's own noise):
a logged flight's own, a planned flight the first logged flight's (the same vehicle and
firmware), so that the noise is white where the formula takes it so; what the filter misses (the
closed loop's response to its own noise, docs/timing.md) makes the achieved t differ. The score
gap does not enter: between two timing candidates the diagnosis decides by this test alone
(:func:`quadcore.identify.rates.judge`).

**Information on a timing parameter.** The same machinery with the explanation against itself:
``Σ_a Σ_k (C̃(θ) − C̃(θ + h))² / s_a² / h²`` is the information a flight adds (white noise at the
rate level: one sample per independent one), ``std_after = (1/std_before² + I)^(-1/2)``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace

import numpy as np

from quadcore.identify import evidence, flightdata, rates
from quadcore.identify.model import PhysicsModel
from quadcore.physics.vehicle import Vehicle
from quadcore.plan.objective import SIGMA_GOAL, Information, Separation
from quadcore.plan.signatures import Explanation


def rate_flight(fd: flightdata.FlightData, vehicle: Vehicle, skip_blocks: int) -> rates.RateFlight:
    """``fd`` at the rate level (its increments are replaced, :func:`hypothetical`); a planned
    flight (flat state, no thrust hold of its own) gets the vehicle's command period as its hold,
    as it will be logged."""
    if fd.state.thrust_hold_s == 0 and vehicle.thrust_hold_s > 0:
        fd = replace(fd, state=replace(fd.state, thrust_hold_s=vehicle.thrust_hold_s))
    return rates.rate_flight(fd, vehicle, None, skip_blocks)


def hypothetical(rf: rates.RateFlight, truth: Explanation) -> rates.RateFlight:
    """``rf`` with the residual ``truth`` alone would leave (its increments at its fitted values,
    noise-free)."""
    return replace(rf, increments=rates.effect_increments(truth.effect, dict(truth.params), rf))


def expected_t(D: np.ndarray, w: np.ndarray, var: np.ndarray) -> float:
    """The comparison's expected t from ``D`` (blocks, 3) (see the module)."""
    den = float((D @ (w**2 * var)).sum())
    return float((D @ w).sum() / (2.0 * np.sqrt(den))) if den > 0 else 0.0


class _Logged:
    """The logged flights at the rate level, as the diagnosis takes them
    (:func:`quadcore.identify.rates.flight_sums`, the model's torque removed): their weights, and
    the residual per interval and axis after the best of ``candidates`` fitted on them or of none
    (each candidate at its default predicts nothing)."""

    def __init__(self, old: Mapping[str, flightdata.FlightData], model: PhysicsModel,
                 candidates: list[Explanation]):
        effects = [c.effect for c in candidates]
        self.skip_blocks = evidence.memory_blocks(effects)
        # the sums whitened as the diagnosis takes them (its default noise model, the gyro's own noise)
        self.filters = {f: rates.gyro_noise_model(fd) for f, fd in old.items()}
        real = [rates.flight_sums(fd, model, f, effects, self.skip_blocks, self.filters[f]) for f, fd in old.items()]
        # a planned flight is not flown yet: the vehicle's gyro, as the first logged flight has it
        self.planned_filter = self.filters[min(old)]
        self.w = rates.weights(real)
        n = max(sum(s.n for s in real), 1)
        left = [sum(s.costs(e, rates.fit(e, real, self.w).value).sum(axis=0) for s in real) / n for e in effects]
        left += [sum(s.costs(e, e.parameters[0].default).sum(axis=0) for s in real) / n for e in effects[:1]]
        self.var = min(left, key=lambda v: float(v @ self.w))
        self.flights = {f: rate_flight(fd, model.for_flight(f).vehicle, self.skip_blocks) for f, fd in old.items()}


class _Direction:
    """One truth and its rival at the rate level (see the module): the old flights' sums with the
    truth's residual, made once, and the rival's fit to them."""

    def __init__(self, truth: Explanation, rival: Explanation, logged: _Logged):
        self.truth, self.rival, self.w = truth, rival.effect, logged.w
        self.planned_filter = logged.planned_filter
        self.old = [self.sums(rf, logged.filters[f]) for f, rf in logged.flights.items()]
        self.on_old = rates.fit(self.rival, self.old, self.w).value

    def sums(self, rf: rates.RateFlight, noise: rates.Filter | None = None) -> rates.RateSums:
        """A flight's sums with the truth's residual, through ``noise`` (a logged flight's own
        whitening filter; a planned one's: the logged flights')."""
        return rates.rate_sums(hypothetical(rf, self.truth), [self.rival],
                               noise=self.planned_filter if noise is None else noise)

    def held_out(self, new: rates.RateSums | None = None) -> np.ndarray:
        """(blocks, 3) ``D`` per block and axis: the old flights alone (the rival fitted on them),
        or with a planned flight's sums (the old ones with the rival fitted on both, the planned
        one with the rival fitted on the old ones)."""
        if new is None:
            return np.concatenate([s.costs(self.rival, self.on_old) for s in self.old])
        joint = rates.fit(self.rival, [*self.old, new], self.w).value
        return np.concatenate([*(s.costs(self.rival, joint) for s in self.old), new.costs(self.rival, self.on_old)])


class RateSeparation:
    """The expected separation of two timing candidates ``a`` and ``b`` at the rate level (see
    the module), given the logged flights ``old`` and the diagnosis's ``model``; the interface of
    :class:`quadcore.plan.objective.SeparationObjective` (``score_gap`` None: it does not enter)."""

    def __init__(self, a: Explanation, b: Explanation, old: Mapping[str, flightdata.FlightData], model: PhysicsModel,
                 vehicle: Vehicle):
        self.vehicle = vehicle
        self.logged = _Logged(old, model, [a, b])
        self.directions = [_Direction(a, b, self.logged), _Direction(b, a, self.logged)]

    def evaluate(self, new: flightdata.FlightData | None = None) -> Separation:
        rf = rate_flight(new, self.vehicle, self.logged.skip_blocks) if new is not None else None
        by_truth = {d.truth.name: (expected_t(d.held_out(d.sums(rf) if rf is not None else None), self.logged.w,
                                              self.logged.var), None) for d in self.directions}
        sigma = min(s for s, _ in by_truth.values())
        return Separation(sigma, None, sigma / SIGMA_GOAL, by_truth)

    def value(self, new: flightdata.FlightData) -> float:
        return self.evaluate(new).value

    def own(self, new: flightdata.FlightData) -> dict[str, float]:
        """Per truth, the expected t of ``new``'s blocks alone (the rival fitted on the old
        flights): what that flight adds, whatever the old flights hold."""
        rf = rate_flight(new, self.vehicle, self.logged.skip_blocks)
        return {d.truth.name: expected_t(d.sums(rf).costs(d.rival, d.on_old), self.logged.w, self.logged.var)
                for d in self.directions}


class RateInformation(Information):
    """The standard error of a timing effect's one parameter after a planned flight, at the rate
    level (see the module)."""

    def __init__(self, expl: Explanation, std_before: float, old: Mapping[str, flightdata.FlightData],
                 model: PhysicsModel, vehicle: Vehicle):
        self.expl, self.vehicle = expl, vehicle
        self.std_before = float(std_before)
        self.logged = _Logged(old, model, [expl])

    def information(self, new: flightdata.FlightData) -> float:
        return self.flight_information(rate_flight(new, self.vehicle, self.logged.skip_blocks))

    def flight_information(self, rf: rates.RateFlight) -> float:
        """What a flight at the rate level adds to the parameter's information (see the module; a
        secant over a quarter sample period, inward from a bound)."""
        e = self.expl.effect
        (p,) = e.parameters
        s = rates.rate_sums(hypothetical(rf, self.expl), [e], noise=self.logged.filters.get(rf.fd.flight,
                                                                                           self.logged.planned_filter))
        theta = float(self.expl.params[p.name])
        h = 0.25 * s.dt_s if theta + 0.25 * s.dt_s <= p.upper else -0.25 * s.dt_s
        return float((s.costs(e, theta + h).sum(axis=0) / self.logged.var).sum()) / h**2
