"""A flight at the rate level: its increments over the sample intervals, in blocks and segments.

Summing the torque equation over the sample intervals undoes the derivative (the gyro's noise
then enters white, not through the derivative filter: :mod:`quadcore.identify.rates`): per
interval ``[t_(k-1), t_k]``

    d_k = J (ω_k − ω_(k−1)) + ∫ ω × J ω dt − ∫ A f dt − ∫ τ_model dt      (N m s, body frame)

(the integrals with the thrust source's hold, :func:`quadcore.physics.signals.interval_integrals`),
and its running sum ``R_k = Σ_(i<=k) d_i`` holds the gyro noise as ``J (ε_k − ε_0)``: white,
plus a constant. A candidate's running sum ``C_k(θ) = Σ ∫ τ_e(θ) dt`` (:func:`effect_increments`)
depends on the commands up to ``t_(k−1)`` only (a command acts from the instant it is logged, so
the interval ending at ``t_k`` holds commands set before it), which are predetermined with
respect to ``ε_k``. The intervals fall in the diagnosis's blocks
(:data:`~quadcore.identify.evidence.BLOCK_S`), each with a free offset per segment (which takes
the ``ε_0`` of its start and any drift before it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from quadcore.effects import Effect
from quadcore.identify.flightdata import FlightData
from quadcore.physics import dynamics, signals
from quadcore.physics.vehicle import Vehicle


@dataclass(frozen=True)
class RateFlight:
    """One flight at the rate level: the increments ``d_k`` (m, 3) over its sample intervals
    (N m s, body frame, the model's torque removed), each interval's block (-1: not used) and
    its segment (-1: not used). The block is the diagnosis's, :func:`quadcore.identify.flightdata.block_index`
    of the interval's end sample (the held-out tests' clusters, the same at both levels); a
    segment is a run of consecutive used intervals within one block, each with its own offset
    (the running sum starts again after a gap, whose commands are unknown), so a block with a gap
    in it holds two segments."""

    fd: FlightData
    vehicle: Vehicle
    increments: np.ndarray
    block: np.ndarray
    segment: np.ndarray

    @property
    def n(self) -> int:
        return int((self.block >= 0).sum())


def rate_flight(fd: FlightData, vehicle: Vehicle, model_tau_b_Nm: np.ndarray | None = None,
                skip_blocks: int = 0) -> RateFlight:
    """The increments ``J Δω + ∫ ω × J ω − ∫ (A f + τ_model)`` of a flight; intervals across a
    gap (the commands in it unknown), ending near the filters' edges (not a usable sample,
    :func:`quadcore.identify.flightdata.usable_samples`) and in the first ``skip_blocks`` blocks
    (where an effect with memory predicts nothing; the diagnosis leaves the same blocks out of
    the torque level's scores) belong to no block."""
    st = fd.state
    t, om = st.t_s, st.omega_b_radps
    J = np.asarray(vehicle.inertia_kgm2, float)
    tau = dynamics.wrench_from_thrusts(vehicle, st.f_rotor_N)[1]
    if model_tau_b_Nm is not None:
        tau = tau + model_tau_b_Nm
    inc = (np.diff(om, axis=0) @ J.T + signals.interval_integrals(np.cross(om, om @ J.T), t, 0.0)
           - signals.interval_integrals(tau, t, st.thrust_hold_s))
    of_sample = np.full(len(t), -1)
    of_sample[fd.mask] = fd.blocks()
    end = of_sample[1:]
    dt = np.diff(t)
    ok = (dt < 1.5 * np.median(dt)) & (end >= skip_blocks)
    block, segment = np.where(ok, end, -1), np.full(len(inc), -1)
    segment[ok] = _runs(ok, end)[ok]
    return RateFlight(fd, vehicle, inc, block, segment)


def _runs(ok: np.ndarray, period: np.ndarray) -> np.ndarray:
    """Numbered runs of ``ok`` intervals, cut where ``period`` changes (0, 1, ... in time order)."""
    start = ok & np.concatenate([[True], ~ok[:-1] | (np.diff(period) != 0)])
    return np.cumsum(start) - 1


def effect_increments(effect: Effect, params: dict[str, float], rf: RateFlight) -> np.ndarray:
    """(m, 3) ``∫ τ_e dt`` over each sample interval of ``rf``'s flight: the torque of ``effect`` at
    ``params`` with the flight's thrust hold (N m s, body frame): a candidate's increments, whose
    running sum is its ``C``."""
    st = rf.fd.state
    return signals.interval_integrals(effect.wrench(st, rf.vehicle, params)[1], st.t_s, st.thrust_hold_s)
