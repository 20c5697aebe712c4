"""Rotor timing (a lag, a delay) fitted and compared at the angular-rate level, where the closed
loop does not bias it.

**Why not at the torque level.** The torque residual is ``J D[ω + ε] − M[A f]`` (docs/timing.md):
the gyro's noise ``ε`` enters through the derivative filter ``D``, which spans the samples on
both sides of ``t_k``. The commands ``f`` come from a controller that reads the same noisy gyro,
so ``f_j`` reacts to ``ε_i`` for every ``i <= j``. A timing effect's regressor is built from the
commands (``A (f(t - t_d) - f(t))``, through ``M``), and ``D[ε]_k`` holds ``ε_(k-15)``, which
every command in the window reacts to: regressor and noise are correlated (errors in variables
in closed loop) and the fit absorbs a few milliseconds of it. Measured on this project's
simulator (three 8 s hover flights, 10 ms delay true, seeds 0-2): ``t_d`` = 14.8-15.1 ± 0.2 ms
on the torque channels; the same flights with the gyro noise added to the log only (the
controller flying on the true rates) give 10.2-11.6 ± 0.5 ms.

**The rate level.** Summing the torque equation over the sample intervals undoes the
derivative: per interval ``[t_(k-1), t_k]``

    d_k = J (ω_k − ω_(k−1)) + ∫ ω × J ω dt − ∫ A f dt − ∫ τ_model dt      (N m s, body frame)

(the integrals with the thrust source's hold, :func:`quadcore.physics.signals.interval_integrals`),
and its running sum ``R_k = Σ_(i<=k) d_i`` holds the gyro noise as ``J (ε_k − ε_0)``: white,
plus a constant. A candidate's running sum ``C_k(θ) = Σ ∫ τ_e(θ) dt`` depends on the commands
up to ``t_(k−1)`` only (a command acts from the instant it is logged, so the interval ending at
``t_k`` holds commands set before it), which are predetermined with respect to ``ε_k``. Over blocks
``b`` of :data:`~quadcore.identify.evidence.BLOCK_S` with a free offset each (which takes the
``ε_0`` of the block's start and any drift before it)

    J_rate(θ) = Σ_b Σ_(k∈b) Σ_axis w_a (R_ka − C_ka(θ) − c_ba)²,   w_a = 1 / σ_a²

is the prediction-error criterion with the right noise model (the torque noise is differenced
white gyro noise; its whitening filter is the running sum). The offsets make the regressor and
the noise correlated only through the block mean, a bias of order one sample per block. Same
flights: ``t_d`` = 9.97-10.18 ± 0.11 ms. The parameter's standard error is the larger of the
profile's (:func:`quadcore.identify.fit.solve.scalar_minimum` with one sample per independent one:
right for a white residual; for a delay, whose cost is a quadratic between whole sample periods
with a minimum in each, :func:`piecewise_quadratic_minimum`: every piece searched, the interval
taken whole) and the blocks-as-clusters one (:func:`_clustered_variance`, right
when the model's error within a block is not white), the comparison of two candidates the held-out difference of their
``J_rate`` per block, t-tested over the blocks (:func:`difference_test`).

**The noise model.** The argument needs the gyro noise white. The real logs' is not (the
firmware's 80 Hz low-pass: lag-one autocorrelation +0.7), and ``ε_k`` then correlates with the
``ε_(k−1)`` the commands react to: on three hover flights with that noise (simulated) a 10 ms delay
came out 9.2-9.7 ms, a lag 11.0-11.9 ms, the delay preferred when the lag was true. Each flight's
running sums (``R`` and every ``C``) go through a whitening filter ``x_k − Σ_i φ_i x_(k−i)`` per
axis, an AR model of the gyro's own noise (:func:`gyro_noise_model`: its spectrum read off the
logged rate less its trend above 30 Hz, held flat below; order ≤ 8 by BIC, 0 on white noise;
Yule-Walker with a 10 % white floor), so that the filtered residual's noise is the innovation,
unpredictable from the past; the fit stays a quadratic form of the filtered sums. Same flights:
the lag 9.8-10.9 ms and preferred in 5 of 5 seeds; a 9 ms delay 8.8-9.2 ms (docs/timing.md). The
filter fitted to the residual instead (:func:`noise_model`, ``rate_sums(..., noise="residual")``)
is unbiased on the simulator too, but on the 19 real flights it has ``Σφ`` 0.98-0.99, a
near-difference that models the unmodelled torque's drift within the running sums, not the sensor
noise, and 'found' a delay of 1.0 ms at 6.3 σ; the gyro's has ``Σφ`` 0.5-0.65 and finds none.
Which filter is right the gyro cannot tell (it holds the loop's response to its own noise), and
below about 8 ms the whitened and the unwhitened fits of a delay disagree by up to 4 ms (the
whitened one biased: docs/timing.md, "A small delay"): :func:`fit` fits both and the standard
error is at least their distance (:attr:`RateFit.unwhitened`).

**From sums, one flight's rows at a time.** Every cost is a quadratic form of per-block Gram
sums (:class:`RateSums`, :func:`rate_sums`): ``R`` and each timing candidate's ``C`` at every
point of a grid of its parameter, block-demeaned, are taken in one pass over a flight's rows,
which then go. Between grid points the candidate's running sums are interpolated (linear
between whole sample periods for a delay, which is exact; the profiles' spline for a lag), so
the fit, its standard errors and the comparison come from the sums: on three hover flights
with 10 ms of either, within 0.001 standard errors of the row evaluation, the comparison's
``t`` within 1e-4 (tests/reference/rates.py holds the row evaluation as the reference).

Used by :func:`quadcore.identify.diagnosis.diagnose` for the candidates that re-time the rotors'
commanded thrust (:attr:`quadcore.effects.Effect.retimes_thrust`): their parameters and how they
rank against each other come from here (docs/diagnosis.md).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, replace
from typing import TYPE_CHECKING, Literal

import numpy as np
from scipy import linalg, stats
from scipy.signal import savgol_coeffs

from quadcore.effects import Effect, get as get_effect
from quadcore.identify import evidence
from quadcore.identify.fit import solve
from quadcore.identify.flightdata import FlightData
from quadcore.identify.stats import profiles
from quadcore.physics import dynamics, signals
from quadcore.physics.vehicle import Vehicle

if TYPE_CHECKING:  # the diagnosis imports this module: its types only for the annotations
    from quadcore.identify.diagnosis.rows import CandidateRow
    from quadcore.identify.settings import DiagnosisSettings

RATE_LEVEL = "angular rate"  # what separates two timing candidates (a row's ``separated_by``)
NOT_SIGNIFICANT = "not significant:"  # how a row's note on its significance begins (quadcore.identify.diagnosis)


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


@dataclass(frozen=True)
class RateSums:
    """One flight at the rate level as sufficient sums, its rows no longer needed: per block
    ``b`` and axis ``a`` the Gram ``G_ba = Σ_(k∈b) x̃_k x̃_kᵀ`` of the block-demeaned running sums
    ``x_k = [R_k, C_k(v_1), …]``: the residual's and, per timing effect (its columns
    :attr:`slots`), its candidate's at each point ``v_g`` of its grid (:func:`rate_grid`). With
    the grid's interpolation weights ``ω(v)`` (:func:`grid_weights`) and ``u = [1, −ω(v)]`` in
    the effect's columns, ``Σ_(k∈b) (R̃_ka − C̃_ka(v))² = uᵀ G_ba u = a − 2 ω·s + ωᵀ Q ω`` (the
    variable-projection form of the torque level's profiles): exact on a grid point, the
    candidate's running sums interpolated between. Stored as each Gram's upper triangle,
    :attr:`blocks` (B, 3, P) in float32 (the held-out tests' clusters, as the profiles' blocks)
    and :attr:`total` (3, P) over the flight in float64 (the fits). ``noise`` (3,) the torque
    channels' sensor-noise RMS over ``samples`` usable samples (:func:`weights`), ``dt_s`` the
    median sample period, ``n`` the used intervals. :attr:`unwhitened` (3, P): :attr:`total`
    without the whitening filter (the same where it is empty; None: not taken), whose fit
    :func:`fit` sets beside the whitened one (the noise model's share of the standard error);
    :attr:`unwhitened_blocks` (B, 3, P) float32: :attr:`blocks` without the filter (None: the
    same as :attr:`blocks`, or not taken), the held-out comparison's without the noise model
    (:func:`unwhitened_comparison`)."""

    grids: dict[str, np.ndarray]
    slots: dict[str, slice]
    blocks: np.ndarray
    total: np.ndarray
    noise: np.ndarray
    samples: int
    dt_s: float
    n: int
    unwhitened: np.ndarray | None = None
    unwhitened_blocks: np.ndarray | None = None

    @property
    def grid_key(self) -> tuple:
        """The same for flights whose grids are the same (the fleet's flights at one sample rate)."""
        return tuple((n, g.tobytes()) for n, g in self.grids.items())

    def direction(self, effect: Effect | None, value: float = 0.0) -> np.ndarray:
        """(K,) ``u``: the residual minus ``effect``'s running sums at ``value`` (None: the
        residual alone)."""
        u = np.zeros(1 + sum(len(g) for g in self.grids.values()))
        u[0] = 1.0
        if effect is not None:
            u[self.slots[effect.name]] = -grid_weights(effect, self.grids[effect.name], value)
        return u

    def cost(self, effect: Effect, value: float, w: np.ndarray) -> float:
        """``Σ_a w_a Σ_k (R̃_ka − C̃_ka(value))²`` over the flight."""
        return float(w @ (self.total @ _packed_square(self.direction(effect, value))))

    def costs(self, effect: Effect, value: float) -> np.ndarray:
        """(blocks, 3) ``Σ_(k∈b) (R̃_ka − C̃_ka(value))²`` per block and axis."""
        return self._forms(self.direction(effect, value))

    def differences(self, a: Effect, va: float, b: Effect, vb: float, unwhitened: bool = False
                    ) -> tuple[np.ndarray, np.ndarray]:
        """(blocks, 3) each: ``b``'s cost minus ``a``'s, and ``Σ (C̃_a(va) − C̃_b(vb))²``;
        ``unwhitened``: from the Grams without the whitening filter (:attr:`unwhitened_blocks`)."""
        ua, ub = self.direction(a, va), self.direction(b, vb)
        G = self.unwhitened_blocks if unwhitened and self.unwhitened_blocks is not None else self.blocks
        return self._forms(ub, G) - self._forms(ua, G), self._forms(ub - ua, G)

    def _forms(self, u: np.ndarray, G: np.ndarray | None = None) -> np.ndarray:
        """(blocks, 3) ``uᵀ G_ba u`` (``G``: :attr:`blocks` unless given)."""
        return (self.blocks if G is None else G).astype(float) @ _packed_square(u)


def _packed_square(u: np.ndarray) -> np.ndarray:
    """(P,) the coefficients of a packed upper triangle in ``uᵀ G u``: ``u_i u_j`` (twice off
    the diagonal)."""
    i, j, twice = _triangle(len(u))
    return u[i] * u[j] * twice


@functools.lru_cache(maxsize=8)
def _triangle(k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The upper triangle's indices of a k × k matrix and its factors (2 off the diagonal): made
    once per size (every cost of a fit asks for them; read only)."""
    i, j = np.triu_indices(k)
    return i, j, np.where(i == j, 1.0, 2.0)


def _pooled(flights: Sequence[RateSums], w: np.ndarray) -> list[tuple[RateSums, np.ndarray]]:
    """Per set of flights with the same grids (the fleet's flights at one sample rate share them):
    one of them, and their axis-weighted totals summed, ``Σ_f w·total_f`` (P,): the weighted
    cost of a direction ``u`` over all of them is then one dot with its packed square
    (:meth:`RateSums.cost`, summed over flights: a fit's cost no longer grows with the flights)."""
    pooled: dict[tuple, tuple[RateSums, np.ndarray]] = {}
    for s in flights:
        first, t = pooled.get(s.grid_key, (s, np.zeros(s.total.shape[1])))
        pooled[s.grid_key] = (first, t + w @ s.total)
    return list(pooled.values())


def _squares(effect: Effect, flights: Sequence[RateSums]) -> Callable[[float], list[np.ndarray]]:
    """``squares(v)``: per flight the packed square of its :meth:`RateSums.direction` at ``v``, made
    once for the flights whose grids are the same (the same vector: the fleet's flights at one
    sample rate share them)."""
    first: dict[tuple, int] = {}
    same = [first.setdefault(s.grid_key, k) for k, s in enumerate(flights)]

    def squares(v: float) -> list[np.ndarray]:
        made = {k: _packed_square(flights[k].direction(effect, v)) for k in first.values()}
        return [made[k] for k in same]

    return squares


def rate_grid(effect: Effect, dt_s: float) -> np.ndarray:
    """The values of ``effect``'s one parameter the rate level's sums are taken at, on a flight
    of median sample period ``dt_s``: the profile grid
    (:func:`quadcore.identify.stats.profiles.profile_grid`), or, for an effect linear in it between
    whole sample periods (:attr:`~quadcore.effects.Effect.linear_between_samples`, a delay),
    every multiple of ``dt_s`` within its bounds and the bounds: the interpolation between
    them is then exact, where a smooth one through the profile grid rounds off the kinks (a
    delay fitted 0.9 σ from the rows' minimum on three hover flights)."""
    (p,) = effect.parameters
    if not effect.linear_between_samples:
        return profiles.profile_grid(p.lower, p.upper)
    steps = np.arange(np.ceil(p.lower / dt_s), np.floor(p.upper / dt_s) + 1) * dt_s
    return np.unique(np.concatenate([[p.lower], steps[(steps > p.lower) & (steps < p.upper)], [p.upper]]))


def grid_weights(effect: Effect, grid: np.ndarray, v: float) -> np.ndarray:
    """(G,) the interpolation weights at ``v`` of :func:`rate_grid`'s ``grid``: linear between
    its points for an effect linear between samples, else the profiles' spline
    (:func:`quadcore.identify.stats.profiles.weights`)."""
    (p,) = effect.parameters
    if not effect.linear_between_samples:
        return profiles.weights(p.lower, p.upper, v)
    v = float(min(max(v, grid[0]), grid[-1]))
    i = int(np.clip(np.searchsorted(grid, v, side="right") - 1, 0, len(grid) - 2))
    t = (v - grid[i]) / (grid[i + 1] - grid[i])
    out = np.zeros(len(grid))
    out[i], out[i + 1] = 1.0 - t, t
    return out


def rate_sums(rf: RateFlight, timing: Sequence[Effect], noise: NoiseModel | Filter = "gyro") -> RateSums:
    """A flight's :class:`RateSums` for the one-parameter ``timing`` effects, in one pass over
    its rows: each effect's interval integrals of its torque at every point of its grid, with
    the flight's thrust hold (as the model's torque in the increments); every running sum
    through the flight's whitening filter, ``noise`` saying which: ``"gyro"`` (the default, and
    the diagnosis's) fitted to the gyro's own noise (:func:`gyro_noise_model`), ``"residual"``
    fitted to the rate-level residual (:func:`noise_model`; on the real flights it models the
    unmodelled torque's drift, not the gyro noise: docs/timing.md, "The noise model"),
    ``"white"`` none; or a given filter (:data:`Filter`: a flight not flown yet takes the logged
    ones', quadcore.plan.ratelevel)."""
    st = rf.fd.state
    use = rf.block >= 0
    dt_s = float(np.median(np.diff(st.t_s)))
    grids = {e.name: rate_grid(e, dt_s) for e in timing}
    k, slots = 1, {}
    for e in timing:
        slots[e.name] = slice(k, k + len(grids[e.name]))
        k += len(grids[e.name])
    b = rf.segment[use]
    starts = np.flatnonzero(np.concatenate([[True], np.diff(b) != 0, [True]])) if len(b) else np.zeros(1, int)
    cluster = np.unique(rf.block[use][starts[:-1]], return_inverse=True)[1].reshape(-1) if len(b) else starts[:0]
    size = np.diff(starts).astype(float)

    def demeaned(running: np.ndarray) -> np.ndarray:
        """(m, 3) running sums less their block's mean (which the block's offset takes)."""
        return running - np.repeat(np.add.reduceat(running, starts[:-1], axis=0) / size[:, None], np.diff(starts),
                                   axis=0) if len(b) else running

    # (m, 3, K) block-demeaned, filled one column at a time; float32 (one flight's, the largest array here):
    # the rounding perturbs each value by 6e-8 of itself, a residual by that of the values, not of their Gram
    X = np.empty((len(b), 3, k), np.float32)
    X[:, :, 0] = demeaned(np.cumsum(rf.increments, axis=0)[use])
    for e in timing:
        (p,) = e.parameters
        for j, v in zip(range(slots[e.name].start, slots[e.name].stop), grids[e.name]):
            X[:, :, j] = demeaned(np.cumsum(effect_increments(e, {p.name: float(v)}, rf), axis=0)[use])
    ar, share = (noise if isinstance(noise, tuple) else gyro_noise_model(rf.fd) if noise == "gyro"
                 else noise_model(X, starts, rf.fd.noise[3:]) if noise == "residual"
                 else (np.zeros((3, 0)), np.ones(3)))
    lags = ar.shape[1]
    iu = np.triu_indices(k)
    blocks = np.zeros((int(cluster.max()) + 1 if len(cluster) else 0, 3, len(iu[0])))
    raw = np.zeros_like(blocks)  # the same without the filter (RateSums.unwhitened_blocks)
    for i, (lo, hi) in enumerate(zip(starts[:-1], starts[1:])):  # each segment's Gram into its block's
        x = whitened(X[lo:hi].astype(float), ar)
        if not len(x):
            continue
        x -= x.mean(axis=0)
        blocks[cluster[i]] += np.einsum("kai,kaj->aij", x, x)[:, iu[0], iu[1]]
        if lags:
            r = X[lo:hi].astype(float)
            r -= r.mean(axis=0)
            raw[cluster[i]] += np.einsum("kai,kaj->aij", r, r)[:, iu[0], iu[1]]
    used = int(np.maximum(np.diff(starts) - lags, 0).sum()) if len(b) else 0
    total = blocks.sum(axis=0)
    return RateSums(grids, slots, blocks.astype(np.float32), total, rf.fd.noise[3:] * np.sqrt(share),
                    max(rf.fd.n, 1), dt_s, used, raw.sum(axis=0) if lags else total,
                    raw.astype(np.float32) if lags else None)


def effect_increments(effect: Effect, params: dict[str, float], rf: RateFlight) -> np.ndarray:
    """(m, 3) ``∫ τ_e dt`` over each sample interval of ``rf``'s flight: the torque of ``effect`` at
    ``params`` with the flight's thrust hold (N m s, body frame): a candidate's increments, whose
    running sum is its ``C``."""
    st = rf.fd.state
    return signals.interval_integrals(effect.wrench(st, rf.vehicle, params)[1], st.t_s, st.thrust_hold_s)


# The rate level's noise model (noise_model, docs/timing.md "The noise model")
MAX_AR_ORDER = 8  # its largest AR order (the simulator's coloured gyro noise takes all 8)
NOISE_MODEL_PASSES = 3  # fits of it, each on the residual of the column the last one's whitening prefers
WHITE_FLOOR = 0.1  # its white floor, a share of the residual's variance (Yule-Walker's lag-0 loading)


NOISE_BAND_HZ = 30.0  # the gyro noise's spectrum is read above it (below, the vehicle's motion is in the gyro)
NOISE_FLAT_HZ = 20.0  # the width of the band above NOISE_BAND_HZ whose level the spectrum keeps below it
NOISE_LAGS = 64  # the gyro noise's autocovariance's lags its spectrum comes from (8 Hz resolution at 500 Hz)
NoiseModel = Literal["gyro", "residual", "white"]  # what a flight's whitening filter is fitted to (rate_sums)
Filter = tuple[np.ndarray, np.ndarray]  # a whitening filter: AR coefficients (3, p) and the innovation's share (3,)


def gyro_noise_model(fd: FlightData) -> tuple[np.ndarray, np.ndarray]:
    """Per axis the AR(p) coefficients (3, p) of the gyro's own noise ``ε`` as the log has it and
    the share (3,) of its variance the whitening ``ε_k − Σ_i φ_i ε_(k−i)`` leaves (the
    innovation's), from the logged rate alone: no model, no residual.

    The logged rate is ``ω̃ = ω + ε``; less its trend (:func:`quadcore.physics.signals.smooth`,
    the local quadratic ``S`` over 31 samples) it is ``e = (1 − S)[ε] + (1 − S)[ω]``. Above
    :data:`NOISE_BAND_HZ` the vehicle's own motion is small against the noise (on the real logs
    the raw gyro's spectrum at 30-60 Hz is 0.87-0.90 of the detrended one's, ``1 / |1 − H_S|²``
    predicts 0.91; at 15-30 Hz it is 1.5-3.1 times its 30-60 Hz level: the motion), so there
    ``S_e(f) ≈ |1 − H_S(f)|² S_ε(f)``:

        S_ε(f) = S_e(f) / |1 − H_S(f)|²                              (f >= NOISE_BAND_HZ)
        S_ε(f) = mean of S_ε over [NOISE_BAND_HZ, NOISE_BAND_HZ + NOISE_FLAT_HZ]   (below)

    the second because the firmware's low-pass (80 Hz, two poles) is flat within its passband and
    the sensor's own noise is white: what the trend and the motion hide is the level above them.
    ``S_e`` is the Blackman-Tukey estimate from ``e``'s autocovariances at lags 0 to
    :data:`NOISE_LAGS` (over the pairs of usable samples that many periods apart) with a
    Tukey-Hanning lag window; ``γ_ε(ℓ) = ∫ S_ε(f) cos(2π f ℓ Δt) df`` over [0, Nyquist]. The order
    ``p`` <= :data:`MAX_AR_ORDER` by BIC of the Levinson prediction errors over the flight's ``n``
    usable samples, ``n log(σ²_p / γ_ε(0)) + p log n``, the largest over the axes (0 on white
    noise: nothing changes), the coefficients by Yule-Walker with ``γ_ε(0)`` raised by
    :data:`WHITE_FLOOR` (the low-pass leaves almost nothing near the log's Nyquist frequency,
    where the exact whitening's gain is unbounded: docs/timing.md, "Why a floor"), the share
    ``aᵀ Γ_ε a / γ_ε(0)`` with ``a = [1, −φ]`` (``Γ_ε`` the Toeplitz of ``γ_ε``).

    What it cannot see: the closed loop's response to its own noise. The controller turns the
    noise into torque, and the rate follows it (``ω̃ = (1 − T) ε`` in the loop's band); on the
    simulator's roll and pitch axes that raises the detrended gyro's spectrum at 30-60 Hz by
    6-16 % above the noise's (the rate-level residual's at the true timing), at 20-30 Hz 34-40 %. A
    filter from the exact noise spectrum fits a 10 ms delay at 9.86-10.18 ms; this one, on the
    same flights, on either side of it (docs/timing.md). On the real logs ``Σφ`` is 0.5-0.65
    (the residual's filter: 0.98-0.99)."""
    t = fd.state.t_s
    om = fd.state.omega_b_radps
    return _noise_ar(om - signals.smooth(om, t_s=t), fd.mask, t)


def _noise_ar(e: np.ndarray, ok: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The AR coefficients (3, p) and innovation shares (3,) of the noise whose detrended
    series is ``e`` (n, 3) at times ``t``, over the usable samples ``ok`` (:func:`gyro_noise_model`)."""
    none = (np.zeros((3, 0)), np.ones(3))
    n = int(ok.sum())
    if n <= 10 * NOISE_LAGS:
        return none
    dt = float(np.median(np.diff(t)))
    f_hz, spectrum = _noise_spectrum(e, ok, t, dt)
    lags = np.arange(MAX_AR_ORDER + 1)
    quad = np.full(len(f_hz), 1.0)
    quad[[0, -1]] = 0.5
    gamma = (np.cos(2 * np.pi * np.outer(lags, f_hz) * dt) * quad) @ spectrum  # (lags, 3)
    if not np.all(gamma[0] > 0):
        return none
    bic = np.array([[n * np.log(max(_prediction_error(g, p) / g[0], 1e-300)) + p * np.log(n) for g in gamma.T]
                    for p in range(MAX_AR_ORDER + 1)])
    p = int(np.argmin(bic, axis=0).max())
    if p == 0:
        return none
    ar = np.array([linalg.solve_toeplitz(np.concatenate([[g[0] * (1 + WHITE_FLOOR)], g[1:p]]), g[1:p + 1])
                   for g in gamma.T])
    a = np.concatenate([np.ones((3, 1)), -ar], axis=1)
    share = np.array([a[i] @ linalg.toeplitz(gamma[:p + 1, i]) @ a[i] / gamma[0, i] for i in range(3)])
    return ar, share


def _noise_spectrum(e: np.ndarray, ok: np.ndarray, t: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """(F,) frequencies and (F, 3) the gyro noise's spectrum ``S_ε`` (up to a constant) from the
    detrended rate ``e`` (:func:`gyro_noise_model`)."""
    m = len(e)
    gamma = np.zeros((NOISE_LAGS + 1, e.shape[1]))
    for lag in range(NOISE_LAGS + 1):
        pair = ok[:m - lag] & ok[lag:] & (np.abs(t[lag:] - t[:m - lag] - lag * dt) < 0.5 * dt)
        gamma[lag] = (e[:m - lag] * e[lag:])[pair].sum(axis=0) / max(int(pair.sum()), 1)
    lags = np.arange(NOISE_LAGS + 1)
    f_hz = np.linspace(0.0, 0.5 / dt, 4 * NOISE_LAGS + 1)
    window = np.where(lags == 0, 1.0, 2.0) * 0.5 * (1 + np.cos(np.pi * lags / (NOISE_LAGS + 1)))
    s_e = np.cos(2 * np.pi * np.outer(f_hz, lags) * dt) @ (window[:, None] * gamma)
    half = signals.WINDOW // 2
    h_s = np.cos(2 * np.pi * np.outer(f_hz, np.arange(-half, half + 1)) * dt) @ savgol_coeffs(signals.WINDOW,
                                                                                           signals.ORDER)
    band = f_hz >= NOISE_BAND_HZ
    s_eps = s_e / np.maximum((1.0 - h_s) ** 2, 1e-12)[:, None]
    s_eps[~band] = s_eps[band & (f_hz < NOISE_BAND_HZ + NOISE_FLAT_HZ)].mean(axis=0)
    return f_hz, s_eps


def _prediction_error(gamma: np.ndarray, p: int) -> float:
    """The one-step prediction error variance of the best AR(p) for autocovariances ``gamma``."""
    if p == 0:
        return float(gamma[0])
    phi = linalg.solve_toeplitz(gamma[:p], gamma[1:p + 1])
    return float(gamma[0] - phi @ gamma[1:p + 1])


def whitened(x: np.ndarray, ar: np.ndarray) -> np.ndarray:
    """(m - p, 3, ...) ``x_k − Σ_i φ_ai x_(k−i)`` per axis ``a`` of one block's consecutive
    intervals ``x`` (m, 3, ...), ``ar`` (3, p) the coefficients ``φ``; the first ``p`` intervals,
    whose past is outside the block, go."""
    p, m = ar.shape[1], len(x)
    out = x[p:].copy()
    if m <= p:
        return out
    for i in range(1, p + 1):
        out -= ar[:, i - 1].reshape((1, 3) + (1,) * (x.ndim - 2)) * x[p - i:m - i]
    return out


def _lagged(e: np.ndarray, starts: np.ndarray, p: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) targets ``e_k`` and (n, 3, p) their pasts ``e_(k−1..k−p)``, for every ``k`` of a
    block with ``MAX_AR_ORDER`` earlier intervals in it (the same samples whatever ``p``)."""
    ks = np.concatenate([np.zeros(0, int),
                         *(np.arange(lo + MAX_AR_ORDER, hi) for lo, hi in zip(starts[:-1], starts[1:]))])
    return e[ks], np.stack([e[ks - i] for i in range(1, p + 1)], axis=2) if p else np.zeros((len(ks), 3, 0))


def noise_model(X: np.ndarray, starts: np.ndarray, noise: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per axis the AR(p) coefficients (3, p) of a flight's running sums' noise and the share (3,)
    of its variance the whitening leaves (the innovation's), fitted (:func:`_ar_fit`) to the
    block-demeaned residual ``e = R − C`` of the column of ``X`` (a timing candidate at a point
    of its grid, or none) that fits the flight best, first unwhitened, then whitened with the
    model fitted so far, until that column stays (at most :data:`NOISE_MODEL_PASSES` passes).
    ``X`` (m, 3, K) the block-demeaned running sums, ``starts`` the blocks' first rows and the
    end, ``noise`` (3,) the torque floor (the axes' weights in choosing the column)."""
    none = (np.zeros((3, 0)), np.ones(3))
    y, _ = _lagged(X[:, :, 0], starts, MAX_AR_ORDER)
    if len(y) <= 10 * MAX_AR_ORDER:
        return none
    w = 1.0 / np.where(noise > 0, noise, 1.0) ** 2
    ar, share, column = none[0], none[1], -1
    for _ in range(NOISE_MODEL_PASSES):
        best = int(np.argmin(_column_costs(X, starts, ar) @ w))
        if best == column:
            break
        column = best
        e = X[:, :, 0].astype(float) - (X[:, :, column] if column else 0.0)
        ar, share = _ar_fit(*_lagged(e, starts, MAX_AR_ORDER))
    return ar, share


def _column_costs(X: np.ndarray, starts: np.ndarray, ar: np.ndarray) -> np.ndarray:
    """(K, 3) per column ``j`` of ``X`` and axis ``Σ (F[R] − F[X_j])²`` (block means removed, ``F``
    the whitening of ``ar``; column 0: ``R`` alone)."""
    out = np.zeros((X.shape[2], 3))
    for lo, hi in zip(starts[:-1], starts[1:]):
        x = whitened(X[lo:hi].astype(float), ar)
        if not len(x):
            continue
        d = x[:, :, :1] - x
        d[:, :, 0] = x[:, :, 0]
        d -= d.mean(axis=0)
        out += np.einsum("kaj,kaj->ja", d, d)
    return out


def _ar_fit(y: np.ndarray, past: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(3, p) AR coefficients per axis of targets ``y`` (n, 3) on their pasts (n, 3, MAX_AR_ORDER)
    and (3,) the share of ``y``'s variance the innovation keeps. The order ``p`` by BIC of the
    least-squares fits (the largest over the axes; 0 for white noise); the coefficients by
    Yule-Walker with the variance raised by :data:`WHITE_FLOOR` (a white floor under the noise's
    spectrum, which bounds the whitening's gain where the spectrum has almost nothing, near the
    log's Nyquist frequency: without it the fit follows what the filter amplifies there,
    docs/timing.md)."""
    n = len(y)
    bic = np.zeros((MAX_AR_ORDER + 1, 3))
    for p in range(MAX_AR_ORDER + 1):
        for a in range(3):
            A = past[:, a, :p]
            r = y[:, a] - A @ np.linalg.lstsq(A, y[:, a], rcond=None)[0] if p else y[:, a]
            bic[p, a] = n * np.log(max(float(r @ r) / n, 1e-300)) + p * np.log(n)
    p = int(np.argmin(bic, axis=0).max())
    if p == 0:
        return np.zeros((3, 0)), np.ones(3)
    gamma = np.concatenate([(y**2).mean(axis=0)[:, None], np.einsum("na,nak->ak", y, past[:, :, :p]) / n], axis=1)
    ar = np.array([linalg.solve_toeplitz(np.concatenate([[g[0] * (1 + WHITE_FLOOR)], g[1:p]]), g[1:p + 1])
                   for g in gamma])
    innovation = y - np.einsum("nap,ap->na", past[:, :, :p], ar)
    return ar, (innovation**2).sum(axis=0) / np.maximum((y**2).sum(axis=0), 1e-300)


def weights(flights: Sequence[RateSums]) -> np.ndarray:
    """(3,) per axis ``1 / σ²`` from the torque channels' sensor-noise floor (the gyro noise
    through ``J``: the same per axis up to a common factor at every level)."""
    n = np.array([s.samples for s in flights], float)
    ms = sum(s.noise ** 2 * k for s, k in zip(flights, n)) / n.sum()
    return 1.0 / np.where(ms > 0, ms, 1.0)


@dataclass(frozen=True)
class RateFit:
    """A timing effect's one parameter fitted at the rate level: value, standard error, and the
    weighted cost at it over ``n`` intervals; ``unwhitened``: the value fitted without the flights'
    whitening filters (None: they had none), whose distance from ``value`` the standard error is
    at least (the answer's dependence on the noise model, which the gyro cannot check: it holds
    the loop's response to its own noise, docs/timing.md "A small delay")."""

    effect: str
    parameter: str
    value: float
    std: float
    cost: float
    n: int
    unwhitened: float | None = None


def fit(effect: Effect, flights: Sequence[RateSums], w: np.ndarray) -> RateFit:
    """The value of ``effect``'s one parameter minimising ``J_rate`` over ``flights`` (module), its
    standard error (:func:`fit_cost`) at least the distance to the value fitted without the flights'
    whitening filters (:attr:`RateFit.unwhitened`)."""
    (p,) = effect.parameters
    memo: dict[float, float] = {}
    pooled = _pooled(flights, w)
    squares = _squares(effect, flights)

    def J(v: float) -> float:  # Σ_f RateSums.cost: per grid, the flights' weighted totals summed once
        v = float(min(max(v, p.lower), p.upper))
        if v not in memo:
            memo[v] = sum(float(t @ _packed_square(s.direction(effect, v))) for s, t in pooled)
        return memo[v]

    def per_block(v: float) -> np.ndarray:  # RateSums.costs per flight, its direction made once per grid
        return np.concatenate([(s.blocks.astype(float) @ q) @ w for s, q in zip(flights, squares(v))])

    knots = np.unique(np.concatenate([s.grids[effect.name] for s in flights]))
    n = sum(s.n for s in flights) * 3
    out = fit_cost(effect, J, per_block, n, min(s.dt_s for s in flights), knots)
    if not any(_filtered(s) for s in flights):
        return out
    raw = _pooled([s if s.unwhitened is None else replace(s, total=s.unwhitened) for s in flights], w)

    def J_raw(v: float) -> float:  # the same cost without each flight's whitening filter
        v = float(min(max(v, p.lower), p.upper))
        return sum(float(t @ _packed_square(s.direction(effect, v))) for s, t in raw)

    other = (piecewise_quadratic_minimum(J_raw, knots, n)[0] if effect.linear_between_samples
             else solve.scalar_minimum(J_raw, n, p.lower, p.upper, samples_per_independent=1)[0])
    return replace(out, std=max(out.std, abs(out.value - other)), unwhitened=other)


def _filtered(s: RateSums) -> bool:
    """Whether ``s``'s totals went through a whitening filter (its :attr:`RateSums.unwhitened` differ)."""
    return s.unwhitened is not None and s.unwhitened is not s.total and not np.array_equal(s.unwhitened, s.total)


def fit_cost(effect: Effect, J: Callable[[float], float], per_block: Callable[[float], np.ndarray], n: int,
             dt_s: float, knots: np.ndarray) -> RateFit:
    """:func:`fit` on a cost ``J`` over ``n`` values and its per-block parts ``per_block`` (weighted,
    (blocks,)): a delay (:attr:`~quadcore.effects.Effect.linear_between_samples`) by
    :func:`piecewise_quadratic_minimum` over the pieces between ``knots`` (its grids' whole sample
    periods), another effect by :func:`quadcore.identify.fit.solve.scalar_minimum`; the standard
    error the larger of the profile's and :func:`_clustered_variance`'s (``dt_s`` the shortest
    sample period)."""
    (p,) = effect.parameters
    if effect.linear_between_samples:
        best, var, curvature = piecewise_quadratic_minimum(J, knots, n)
    else:
        best, var = solve.scalar_minimum(J, n, p.lower, p.upper, samples_per_independent=1)
        curvature = 2.0 * (J(best) / max(n - 1, 1)) / var if np.isfinite(var) and var > 0 else 0.0
    var = max(var, _clustered_variance(effect, per_block, dt_s, best, curvature))
    return RateFit(effect.name, p.name, best, float(np.sqrt(var)), J(best), n)


def piecewise_quadratic_minimum(J: Callable[[float], float], knots: np.ndarray, n: int) -> tuple[float, float, float]:
    """The minimum of ``J``, a quadratic between consecutive ``knots`` (a delay's cost between whole
    sample periods: its running sums interpolated linearly, :func:`grid_weights`), over
    ``[knots[0], knots[-1]]``: each piece's quadratic from ``J`` at its ends and middle, the lowest
    of the pieces' minima. The variance of its position the likelihood-ratio interval's,
    ``{v: J(v) <= J_min + s²}`` (``s² = J_min / (n − 1)``, the residual white), taken whole over
    every piece: its larger distance from the minimum, to where it ends or to a bound it reaches
    (a piece's minimum elsewhere within ``s²`` of the lowest widens it: the data do not tell
    them apart; a minimum on a bound is measured to the other side). Also the curvature ``J''``
    of the minimum's piece (the sandwich's, :func:`_clustered_variance`; 0 where that piece is not
    convex, the minimum at a kink).

    Why not :func:`quadcore.identify.fit.solve.scalar_minimum`: its 17 geometric points are 2.5 ms
    apart at 5 ms and the cost has a minimum in every piece (the interpolation between whole
    samples dips below the chord by ``t (1 − t) |C_(m+1) − C_m|²``), so it stopped in the piece
    nearest its best point: three 8 s hovers with a 5 ms delay fitted 0.89-1.04 ± 0.12 ms
    (docs/timing.md)."""
    a, b = knots[:-1], knots[1:]
    ja, jb = np.array([J(float(v)) for v in a]), np.array([J(float(v)) for v in b])
    jm = np.array([J(float(v)) for v in 0.5 * (a + b)])
    # per piece J(a + x h) = ja + x (jb − ja − c) + c x², x in [0, 1]
    c = 2.0 * (ja + jb - 2.0 * jm)
    slope = jb - ja - c
    x = np.where(c > 0, np.clip(-slope / np.where(c > 0, 2.0 * c, 1.0), 0.0, 1.0), np.where(jb < ja, 1.0, 0.0))
    low = ja + slope * x + c * x**2
    i = int(np.argmin(low))
    best, j0 = float(a[i] + x[i] * (b[i] - a[i])), float(low[i])
    level = j0 + j0 / max(n - 1, 1)
    inside = [(best, best)]  # each piece's stretch with J <= level (roots of the quadratic); the minimum's own
    for k in range(len(a)):
        h = b[k] - a[k]
        xs = _below(float(ja[k] - level), float(slope[k]), float(c[k]))
        if xs is not None:
            inside.append((a[k] + xs[0] * h, a[k] + xs[1] * h))
    lo, hi = min(v for v, _ in inside), max(v for _, v in inside)
    widths = [d for d in (best - lo, hi - best) if d > 0]
    var = float(max(widths) ** 2) if widths else 0.0
    return best, var, float(max(c[i], 0.0) * 2.0 / (b[i] - a[i]) ** 2)


def _below(c0: float, c1: float, c2: float) -> tuple[float, float] | None:
    """The hull of ``{x in [0, 1]: c0 + c1 x + c2 x² <= 0}`` as its ends (None: empty): its ends are
    among 0, 1 (where the quadratic is <= 0 there) and its roots within [0, 1]."""
    if c2 != 0.0:
        disc = c1 * c1 - 4.0 * c2 * c0
        roots = (-c1 + np.array([-1.0, 1.0]) * np.sqrt(disc)) / (2.0 * c2) if disc >= 0 else np.zeros(0)
    else:
        roots = np.array([-c0 / c1]) if c1 != 0.0 else np.zeros(0)
    ends = [e for e in (0.0, 1.0) if c0 + c1 * e + c2 * e * e <= 0.0]
    points = [*ends, *(float(r) for r in roots if 0.0 <= r <= 1.0)]
    return (min(points), max(points)) if points else None


def _clustered_variance(effect: Effect, per_block: Callable[[float], np.ndarray], dt_s: float, best: float,
                        curvature: float) -> float:
    """The variance of the fitted value with the blocks as independent clusters (the sandwich
    ``Σ_b (∂J_b/∂θ)² / H²``, ``H`` the cost's ``curvature`` at ``best``: the profile's ``2 s² / var``,
    or a delay's piece's exact one, :func:`piecewise_quadratic_minimum`), which the profile's
    variance, right for a white residual, understates where the residual within a block is not
    white (the effect's form only close to the physics, a torque the model lacks); each block's
    slope (``per_block``) by central differences over half a sample period (``dt_s``), one-sided at a bound, where the
    slopes' sum is not 0 (the bound holds the fit: on a simulated fleet with no delay the slope
    from 0 rose the cost by s² within 3 µs) and their spread about their mean is the score's
    variance. 0 without a positive curvature (the profile's interval stands)."""
    (p,) = effect.parameters
    if not np.isfinite(curvature) or curvature <= 0:
        return 0.0
    h = 0.25 * dt_s
    lo, hi = max(best - h, p.lower), min(best + h, p.upper)
    if hi <= lo:
        return 0.0
    slopes = (per_block(hi) - per_block(lo)) / (hi - lo)
    if best <= p.lower or best >= p.upper:  # held by a bound, the blocks' slopes need not sum to 0: their spread
        slopes = slopes - slopes.mean()
    k = len(slopes)
    return float(k / max(k - 1, 1) * np.sum(slopes**2) / curvature**2)


def block_differences(flights: Sequence[RateSums], a: Effect, pa: dict[str, float], b: Effect,
                      pb: dict[str, float], w: np.ndarray, unwhitened: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Per block of ``flights``: ``g``, ``b``'s weighted ``J_rate`` minus ``a``'s (> 0: ``a`` fits
    better), and ``D``, the weighted ``Σ (C_a − C_b)²`` (block means removed) that ``g`` is made of:
    with ``e = R − (C_a + C_b)/2``, ``g = 2 Σ (C_a − C_b) e`` and, if ``a`` is the truth,
    ``E g = D``; if ``b`` is, ``−D``. ``unwhitened``: without the flights' whitening filters
    (:attr:`RateSums.unwhitened_blocks`)."""
    g, D = [], []
    for s in flights:
        gs, Ds = s.differences(a, pa[a.parameters[0].name], b, pb[b.parameters[0].name], unwhitened)
        g.append(gs @ w)
        D.append(Ds @ w)
    return np.concatenate(g), np.concatenate(D)


def difference_test(g: np.ndarray, D: np.ndarray) -> evidence.HeldOutTest:
    """Which of two candidates the blocks prefer: the slope ``β = Σ g / Σ D`` of the residual on
    the direction from ``b``'s prediction to ``a``'s (+1: ``a`` is right, −1: ``b`` is, 0: neither
    fits better), its standard error from the blocks' scores ``g − β D`` (blocks as independent
    clusters, as :func:`quadcore.identify.evidence.held_out_test_of` takes them), two-sided
    (``t > 0``: ``a`` fits better). A t-test of the mean of ``g`` instead would count the spread
    of ``D`` between blocks (a manoeuvre's blocks against a hover's) as noise."""
    n, den = len(g), float(D.sum())
    if n < 3 or den <= 0:
        return evidence.NO_TEST
    beta = float(g.sum() / den)
    se = float(np.sqrt(n / (n - 1) * np.sum((g - beta * D) ** 2)) / den)
    t = beta / se if se > 0 else (np.inf if beta > 0 else -np.inf if beta < 0 else 0.0)
    t = float(np.clip(t, -1e6, 1e6))
    return evidence.HeldOutTest(beta, t, float(2 * stats.t.sf(abs(t), n - 1)), n)


# ---------------------------------------------------------------------------------------
# In the diagnosis
# ---------------------------------------------------------------------------------------

def _model_torque(model, flight: str, fd: FlightData) -> tuple[Vehicle, np.ndarray | None]:
    """The vehicle of ``flight`` and the torque (n, 3) of the model's effects there (unfiltered)."""
    m = model.for_flight(flight)
    if not m.terms:
        return m.vehicle, None
    tau = np.zeros((fd.state.n, 3))
    for t in m.terms:
        tau += get_effect(t.name).wrench(fd.state, m.vehicle, t.params)[1]
    return m.vehicle, tau


TIE = " = "  # joins the timing candidates a fold's answer names when the rate level prefers none of them


@dataclass(frozen=True)
class Judged:
    """What :func:`judge` measured: per pair ``(a, b)`` of timing candidates, each held-out flight's
    per-block :func:`block_differences` (> 0: ``a`` fits better); ``undecided``: the pairs whose
    answer the gyro noise model decides (:func:`noise_model_decides`), which prefer neither."""

    differences: dict[tuple[str, str], dict[str, np.ndarray]]
    undecided: frozenset[tuple[str, str]] = frozenset()

    def answer(self, effect: str, flights: Sequence[str]) -> str:
        """A fold's answer ``effect`` (the torque level's), as the rate level has it on ``flights``
        when ``effect`` is one of the timing candidates it compared: from every pair's difference
        summed over ``flights``, the candidate no other fits better; several (an exact tie: fits
        that predict alike) or, in a cycle, none: every candidate none fits better, or all of them,
        joined by :data:`TIE` (a tie stated as one); a pair in :attr:`undecided` beats neither.
        Symmetric: the same whatever the order of the pairs and of each pair's sides. ``effect``
        itself when it is no timing candidate or no pair was measured on ``flights``."""
        names = {n for pair in self.differences for n in pair}
        measured = [(a, b, per_flight) for (a, b), per_flight in self.differences.items()
                    if any(f in per_flight for f in flights)]
        if effect not in names or not measured:
            return effect
        beaten: set[str] = set()
        for a, b, per_flight in measured:
            if (a, b) in self.undecided:
                continue
            total = sum(float(per_flight[f].sum()) for f in flights if f in per_flight)
            beaten |= {b} if total > 0 else {a} if total < 0 else set()
        return TIE.join(sorted(names - beaten) or sorted(names))


@dataclass(frozen=True)
class BelowCommandRate:
    """A flight logged below the command rate (:func:`below_command_rate`): its median log
    period and its thrust hold, s. Its rows give no rate-level sums."""

    period_s: float
    hold_s: float


FlightRates = RateSums | BelowCommandRate  # what the rate level keeps of one flight
# ``cache(flight, inputs, compute)``: the flight's FlightRates for ``inputs`` (what they depend on
# besides the flight's log: the timing candidates, the skipped start, the model there), kept
# from an earlier diagnosis or ``compute()``d (quadcore.identify.diagnosis.rate_cache)
RatesCache = Callable[[str, dict, Callable[[], FlightRates]], FlightRates]


def flight_inputs(model, flight: str, timing: Sequence[Effect], skip_blocks: int) -> dict:
    """What a flight's :class:`FlightRates` depend on besides its log (JSON): the timing effects,
    the start left out, and the model on the flight (its vehicle, its effects' values)."""
    m = model.for_flight(flight)
    return {"timing": [e.name for e in timing], "skip_blocks": skip_blocks,
            "vehicle": {k: v for k, v in asdict(m.vehicle).items() if k != "source"},
            "terms": [[t.name, t.params] for t in m.terms]}


def judge(rows: list[CandidateRow], cands: Sequence[Effect], rows_of: Callable[[str], FlightData],
          release: Callable[[str], None], model, splits: Sequence[tuple[list[str], list[str]]], train_all: list[str],
          settings: DiagnosisSettings, decide: Callable[[CandidateRow], None],
          cache: RatesCache | None = None) -> tuple[list[CandidateRow], Judged]:
    """The ranked candidate rows of a diagnosis with its timing candidates (one parameter each,
    :attr:`~quadcore.effects.Effect.retimes_thrust`) fitted and compared at the rate level: each
    one's parameter, standard error (the larger of the profile's and the spread between the
    folds' fits) and significance from :func:`fit` on the training flights, and, per pair, the
    held-out :func:`difference_test` over the folds' test flights (each candidate fitted on the
    fold's training flights): significant at ``settings.alpha``, the better one ranks above the
    other (within its tier) and the two are no longer tied; not, they are tied when either is
    found (undecided, whatever the torque level says). Every candidate on the same intervals
    (after the longest memory of them). The model's effects at their values fitted on all
    training flights. Each flight's rows (``rows_of``) are read once, reduced to its
    :class:`RateSums` and let go (``release``); ``cache``: those kept from an earlier diagnosis,
    each flight's rows read only when its are missing or stale. ``decide``: the diagnosis's
    decision (found, grade), taken again on a row whose significance changed."""
    timing = [c for c in cands if c.retimes_thrust and len(c.parameters) == 1]
    if not timing:
        return rows, Judged({})
    skip = evidence.memory_blocks(timing)
    ids = sorted({f for tr, te in splits for f in (*tr, *te)})

    slow: dict[str, tuple[float, float]] = {}  # flights below the command rate: their log period and hold

    def compute(f: str) -> FlightRates:  # one flight's rows at a time, let go once its sums are taken
        fd = rows_of(f)
        if below_command_rate(fd):
            out: FlightRates = BelowCommandRate(float(np.median(np.diff(fd.state.t_s))), fd.state.thrust_hold_s)
        else:
            out = flight_sums(fd, model, f, timing, skip)
        release(f)
        return out

    def reduced(f: str) -> RateSums | None:
        out = compute(f) if cache is None else cache(f, flight_inputs(model, f, timing, skip), lambda: compute(f))
        if isinstance(out, BelowCommandRate):
            slow[f] = (out.period_s, out.hold_s)
            return None
        return out

    reduced_flights = {f: reduced(f) for f in ids}
    by_name = {r.effect: r for r in rows}
    if slow:
        first = sorted(slow)[0]
        return _undecided(rows, [by_name[c.name] for c in timing], sorted(slow), *slow[first]), Judged({})
    flights = {f: s for f, s in reduced_flights.items() if s is not None}
    w = weights([flights[f] for f in train_all])  # the training flights' noise: none of the held-out ones'
    folds = {c.name: [fit(c, [flights[f] for f in tr], w) for tr, _ in splits] for c in timing}
    # the spread between flights: the folds' fits, or with one split, fits leaving out groups of its flights
    groups = ([[f for f in train_all if f not in g] for g in solve.folds(train_all, settings.n_folds)]
              if len(train_all) >= 3 else [])
    for c in timing:
        spread = folds[c.name] if len(splits) > 1 else [fit(c, [flights[f] for f in g], w) for g in groups]
        _update_row(by_name[c.name], c, fit(c, [flights[f] for f in train_all], w), spread, settings.min_sigma)
        decide(by_name[c.name])
    rows = sorted(rows, key=lambda r: r.tier())  # found ones first, as ranked (stable)
    differences: dict[tuple[str, str], dict[str, np.ndarray]] = {}
    wins: list[tuple[CandidateRow, CandidateRow]] = []
    undecided: set[tuple[str, str]] = set()
    for i, a in enumerate(timing):
        for b in timing[i + 1:]:
            ra, rb = by_name[a.name], by_name[b.name]
            if not (ra.physical and rb.physical):
                continue
            per_flight, test = compare_pair(flights, splits, a, b, folds[a.name], folds[b.name], w)
            differences[(a.name, b.name)] = {f: g for f, (g, _) in per_flight.items()}
            raw = unwhitened_comparison(flights, splits, a, b, folds[a.name], folds[b.name], w)
            if raw is not None and noise_model_decides(test, raw, settings.alpha):
                undecided.add((a.name, b.name))
                _noise_model_tie(ra, rb, test, raw)
            elif test.p_value < settings.alpha:
                wins.append((ra, rb) if test.t > 0 else (rb, ra))
                _prefer(*wins[-1])
            elif ra.found or rb.found:
                _tie(ra, rb)
    return _ranked(rows, wins), Judged(differences, frozenset(undecided))


def flight_sums(fd: FlightData, model, flight: str, timing: Sequence[Effect], skip_blocks: int,
                noise: NoiseModel | Filter = "gyro") -> RateSums:
    """One flight's :class:`RateSums` as the diagnosis takes them: the increments with the torque
    of ``model``'s effects (on ``flight``) removed, its first ``skip_blocks`` blocks left out (the
    longest memory of the ``timing`` candidates), whitened as ``noise`` says (:func:`rate_sums`)."""
    vehicle, tau = _model_torque(model, flight, fd)
    return rate_sums(rate_flight(fd, vehicle, tau, skip_blocks), timing, noise)


def compare_pair(flights: Mapping[str, RateSums], splits: Sequence[tuple[Sequence[str], Sequence[str]]], a: Effect,
                 b: Effect, fits_a: Sequence[RateFit], fits_b: Sequence[RateFit], w: np.ndarray
                 ) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], evidence.HeldOutTest]:
    """The held-out comparison of two timing candidates: per test flight of each split its
    :func:`block_differences` with both candidates fitted on the split's training flights
    (``fits_a``, ``fits_b``, one per split), and the :func:`difference_test` over all of them
    (``t > 0``: ``a`` fits better)."""
    per_flight = {f: block_differences([flights[f]], a, {fa.parameter: fa.value}, b, {fb.parameter: fb.value}, w)
                  for (_, te), fa, fb in zip(splits, fits_a, fits_b) for f in te}
    return per_flight, difference_test(*(np.concatenate(x) for x in zip(*per_flight.values())))


def unwhitened_comparison(flights: Mapping[str, RateSums], splits: Sequence[tuple[Sequence[str], Sequence[str]]],
                          a: Effect, b: Effect, fits_a: Sequence[RateFit], fits_b: Sequence[RateFit], w: np.ndarray
                          ) -> evidence.HeldOutTest | None:
    """:func:`compare_pair`'s test without the whitening filters: each candidate at its value fitted
    without them (:attr:`RateFit.unwhitened`), the blocks' differences from the unfiltered Grams
    (:attr:`RateSums.unwhitened_blocks`). None when no test flight went through a filter (the two
    are then the same test)."""
    if not any(_filtered(flights[f]) for _, te in splits for f in te):
        return None

    def at(fit: RateFit) -> dict[str, float]:
        return {fit.parameter: fit.value if fit.unwhitened is None else fit.unwhitened}

    per_flight = [block_differences([flights[f]], a, at(fa), b, at(fb), w, unwhitened=True)
                  for (_, te), fa, fb in zip(splits, fits_a, fits_b) for f in te]
    return difference_test(*(np.concatenate(x) for x in zip(*per_flight)))


def noise_model_decides(test: evidence.HeldOutTest, unwhitened: evidence.HeldOutTest, alpha: float) -> bool:
    """True when the comparison's answer depends on the gyro noise model: ``test`` (whitened) prefers
    one candidate at ``alpha`` and the same comparison without the filters (``unwhitened``) prefers
    the other at ``alpha``. The gyro cannot tell which filter is right (it holds the closed loop's
    response to its own noise, docs/timing.md "A small delay"), so two defensible noise models
    that significantly contradict each other leave the pair undecided; an unwhitened test that
    merely fails to confirm (not significant, or significant the same way) leaves the whitened
    answer standing (its error bar already spans the noise model: :attr:`RateFit.unwhitened`)."""
    return test.p_value < alpha and unwhitened.p_value < alpha and bool(np.sign(test.t) != np.sign(unwhitened.t))


def below_command_rate(fd: FlightData) -> bool:
    """True when ``fd`` logs a held command (PWM) less often than the firmware sets it: the
    commands between two samples are not in the log."""
    hold = fd.state.thrust_hold_s
    return hold > 0 and float(np.median(np.diff(fd.state.t_s))) > 1.5 * hold


def _undecided(rows: list[CandidateRow], timing: list[CandidateRow], slow: list[str], dt: float, hold_s: float
               ) -> list[CandidateRow]:
    """The timing candidates of a fleet with flights :func:`below_command_rate`: not fitted or
    compared at the rate level (their parameters stay the torque level's), and tied where either
    is found. Between two log samples the firmware sets commands the log does not hold, each
    reacting to a fresh gyro sample; the interval integral gives the logged command's jitter
    the whole interval where it acted for one command period, and a lag (which smooths it
    away) fits that better than the truth (docs/timing.md: on simulated 100 Hz hover flights a
    lag came out at its 0.2 s bound whether a 10 ms lag or a 10 ms delay was true)."""
    note = (f"not compared with the other timing candidates at the angular-rate level: {', '.join(slow)} "
            f"log{'s' if len(slow) == 1 else ''} the commands every {dt * 1e3:.3g} ms, the firmware sets them "
            f"every {hold_s * 1e3:.3g} ms, and the commands between samples read as a lag "
            "(docs/timing.md); the parameter is the torque level's, which the closed loop biases")
    for i, a in enumerate(timing):
        a.notes = (*a.notes, note)
        for b in timing[i + 1:]:
            if a.physical and b.physical and (a.found or b.found):
                _tie(a, b)
    return rows


def _update_row(r: CandidateRow, c: Effect, rf: RateFit, folds: list[RateFit], min_sigma: float) -> None:
    """A candidate row with its parameter from the rate level (the torque level's in a note),
    its standard error the larger of the profile's and the grouped jackknife's over ``folds``
    (fits that each leave out a group of flights)."""
    (p,) = c.parameters
    spread = solve.jackknife_std([{p.name: f.value} for f in folds]).get(p.name, 0.0)
    std = max(rf.std, spread)
    torque_v, torque_s = r.parameters[p.name], r.parameter_std[p.name]
    r.parameters = {p.name: rf.value}
    r.parameter_std = {p.name: std}
    r.parameter_spread_between_flights = {p.name: spread}
    sigma = abs(rf.value - p.default) / std if std > 0 else (np.inf if rf.value != p.default else 0.0)
    r.significance_sigma = float(min(sigma, 1e6))
    r.significant = r.significance_sigma >= min_sigma
    r.notes = (*(n for n in r.notes if not n.startswith(NOT_SIGNIFICANT)),
               f"{p.name} fitted at the angular-rate level, {rf.value:.4g} ± {std:.2g} (on the torque channels, which "
               f"the closed loop biases, {torque_v:.4g} ± {torque_s:.2g}: docs/timing.md)")
    if rf.unwhitened is not None and abs(rf.value - rf.unwhitened) >= std:
        r.notes = (*r.notes, f"{p.name} depends on the gyro noise model: {rf.value:.4g} with it, {rf.unwhitened:.4g} "
                             "without; the standard error spans both (docs/timing.md, 'A small delay')")
    if not r.significant:
        r.notes = (*r.notes, f"{NOT_SIGNIFICANT} the fit is only {r.significance_sigma:.1f} standard errors from "
                             "'no effect'")


def _prefer(better: CandidateRow, worse: CandidateRow) -> None:
    """``better`` separated from ``worse`` by the rate level (:func:`_ranked` ranks it above)."""
    for r, o in ((better, worse), (worse, better)):
        r.tied_with = tuple(x for x in r.tied_with if x != o.effect)
        r.separated_by = {**r.separated_by, o.effect: RATE_LEVEL}


def _ranked(rows: list[CandidateRow], wins: Sequence[tuple[CandidateRow, CandidateRow]]) -> list[CandidateRow]:
    """``rows`` (in their tiers) with the better of each pair in ``wins`` (better, worse) ranked
    above the worse where both are in one tier, every other row in its order: row by row, the
    first row left, or, when a row left in its tier fits better than it, that one (the first
    such, followed up the chain; in a cycle, the first row left). A function of the set of wins,
    so the same whatever order the pairs were compared in. (Before, each significant pair moved
    its better one above the worse in turn, and with three timing candidates a later move could
    put a worse one back above its better: [c, a, b] with a > b > c became [b, a, c] when the
    pairs came as (a, b), (b, c), (a, c), and [a, b, c] in another order.)"""
    better = {(id(b), id(w)) for b, w in wins if b.tier() == w.tier()}
    left, out = list(rows), []
    while left:
        r, chain = left[0], []
        while r not in chain:
            chain.append(r)
            above = [o for o in left if (id(o), id(r)) in better]
            if not above:
                break
            r = above[0]
        else:  # a cycle: no row of it is above the others
            r = left[0]
        out.append(r)
        left.remove(r)
    return out


def _tie(a: CandidateRow, b: CandidateRow) -> None:
    """``a`` and ``b`` tied: the rate level prefers neither."""
    for r, o in ((a, b), (b, a)):
        if o.effect not in r.tied_with:
            r.tied_with = (*r.tied_with, o.effect)
        if o.effect not in r.indistinguishable_from:
            r.indistinguishable_from = (*r.indistinguishable_from, o.effect)
        r.separated_by = {k: v for k, v in r.separated_by.items() if k != o.effect}


def _noise_model_tie(a: CandidateRow, b: CandidateRow, test: evidence.HeldOutTest, raw: evidence.HeldOutTest) -> None:
    """``a`` and ``b`` tied because the noise model decides between them (:func:`noise_model_decides`):
    the held-out comparison prefers one with the gyro's whitening filter (``test``, ``t > 0``: ``a``)
    and the other without it (``raw``); each row says so (they are tied, as an undecided pair is,
    when either is found)."""
    first, second = (a, b) if test.t > 0 else (b, a)
    note = (f"the angular-rate level prefers {first.effect} to {second.effect} with the gyro noise model "
            f"(t = {abs(test.t):.1f}) and {second.effect} without it (t = {abs(raw.t):.1f}): the noise model "
            "decides it, so neither is preferred (docs/timing.md, 'A small delay')")
    for r in (a, b):
        r.notes = (*r.notes, note)
    if a.found or b.found:
        _tie(a, b)
