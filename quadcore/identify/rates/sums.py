"""The rate level's sufficient sums of a flight, and a timing parameter's fit from them.

Over blocks ``b`` of :data:`~quadcore.identify.evidence.BLOCK_S` with a free offset each
(:mod:`quadcore.identify.rates.increments`), per axis ``a`` (body frame)

    J_rate(θ) = Σ_b Σ_(k∈b) Σ_axis w_a (R_ka − C_ka(θ) − c_ba)²,   w_a = 1 / σ_a²

is the prediction-error criterion with the right noise model (the torque noise is differenced
white gyro noise; its whitening filter is the running sum; coloured gyro noise goes through
:mod:`quadcore.identify.rates.noise`'s filter first). The offsets make the regressor and the
noise correlated only through the block mean, a bias of order one sample per block. Three 8 s
hover flights, 10 ms delay true, seeds 0-2: ``t_d`` = 9.97-10.18 ± 0.11 ms. The parameter's
standard error is the larger of the profile's (:func:`quadcore.identify.fit.solve.scalar_minimum`
with one sample per independent one: right for a white residual; for a delay, whose cost is a
quadratic between whole sample periods with a minimum in each,
:func:`piecewise_quadratic_minimum`: every piece searched, the interval taken whole) and the
blocks-as-clusters one (:func:`_clustered_variance`, right when the model's error within a block
is not white), and at least the distance to the fit without the whitening filters plus that fit's
own standard error (below about 8 ms the whitened and the unwhitened fits of a delay disagree by up
to 4 ms, the whitened one biased: docs/timing.md, "A small delay"; :attr:`RateFit.unwhitened`).

**From sums, one flight's rows at a time.** Every cost is a quadratic form of per-block Gram
sums (:class:`RateSums`, :func:`rate_sums`): ``R`` and each timing candidate's ``C`` at every
point of a grid of its parameter, block-demeaned, are taken in one pass over a flight's rows,
which then go. Between grid points the candidate's running sums are interpolated (linear
between whole sample periods for a delay, which is exact; the profiles' spline for a lag), so
the fit, its standard errors and the comparison come from the sums: on three hover flights
with 10 ms of either, within 0.001 standard errors of the row evaluation, the comparison's
``t`` within 1e-4 (tests/reference/rates.py holds the row evaluation as the reference). What the
rate level keeps of a flight (:data:`FlightRates`, :func:`flight_rates`) is made here and only
here: the rate cache's code digest (:mod:`quadcore.identify.diagnosis.rate_cache`) covers this
module and those below it.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from quadcore.effects import Effect, get as get_effect
from quadcore.identify.fit import solve
from quadcore.identify.flightdata import FlightData, one_blas_thread
from quadcore.identify.rates.increments import RateFlight, effect_increments, rate_flight
from quadcore.identify.rates.noise import Filter, NoiseModel, gyro_noise_model, noise_model, whitened
from quadcore.identify.stats import profiles
from quadcore.physics import signals
from quadcore.physics.vehicle import Vehicle


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
    (:func:`unwhitened_comparison`); :attr:`lagged_blocks` (B, 3, K, K) float32: per block and axis
    ``Σ_k x̃_(k−1) x̃_kᵀ`` of the whitened block-demeaned running sums, each interval's with the one
    before it (None: the flight has no whitening filter), the held-out comparison's with the
    direction one interval back as its instrument (:func:`instrumented_differences`).

    The model's linear effects (:attr:`model`, one label per linear coordinate) are not taken out
    of ``R`` before the sums: their torque per unit of each coordinate, ``T_j``, has a column of its
    own after ``R`` (``x_k = [R⁰_k, T_1k, …, C_k(v_1), …]``), and the direction takes them out at
    their values :attr:`at` (``u = [1, −c, −ω(v)]``: ``R = R⁰ − Σ_j c_j T_j`` is linear in them,
    and the filter and the demeaning are linear). The sums then hold no value of the model's
    linear effects: a refit that moves them is the same sums at other :attr:`at` (kept by the rate
    cache across refits, :func:`flight_inputs`)."""

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
    lagged_blocks: np.ndarray | None = None
    model: tuple[str, ...] = ()
    at: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def grid_key(self) -> tuple:
        """The same for flights whose directions are the same (the fleet's flights at one sample
        rate, under the same values of the model's linear effects)."""
        return (*((n, g.tobytes()) for n, g in self.grids.items()), self.model, self.at.tobytes())

    def at_model(self, model, flight: str) -> RateSums:
        """These sums with the values of ``model``'s linear effects on ``flight`` (:attr:`at`), the
        coordinates of :attr:`model`'s columns (:func:`model_columns`)."""
        return replace(self, at=np.array([c for _, c in model_columns(model, flight, self.model)], float))

    @property
    def filtered(self) -> bool:
        """Whether the totals went through a whitening filter (:attr:`unwhitened` differ from them)."""
        return self.unwhitened is not None and self.unwhitened is not self.total and not np.array_equal(
            self.unwhitened, self.total)

    def direction(self, effect: Effect | None, value: float = 0.0) -> np.ndarray:
        """(K,) ``u``: the residual (the model's linear effects at :attr:`at` taken out) minus
        ``effect``'s running sums at ``value`` (None: the residual alone)."""
        u = np.zeros(1 + len(self.model) + sum(len(g) for g in self.grids.values()))
        u[0] = 1.0
        u[1:1 + len(self.model)] = -self.at
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

    def instrumented(self, a: Effect, va: float, b: Effect, vb: float) -> tuple[np.ndarray, np.ndarray]:
        """(blocks, 3) each: :meth:`differences` with the direction one interval back as the
        instrument, ``2 Σ_k Δ̃_(k−1) ẽ_k`` and ``Σ_k Δ̃_(k−1) Δ̃_k`` (``Δ = C_a − C_b``,
        ``e = R − (C_a + C_b)/2``, whitened, :attr:`lagged_blocks`); a flight without a whitening
        filter (white noise: the direction is predetermined) its own :meth:`differences`."""
        if self.lagged_blocks is None:
            return self.differences(a, va, b, vb)
        ua, ub = self.direction(a, va), self.direction(b, vb)
        d, m = ub - ua, 0.5 * (ua + ub)
        G = self.lagged_blocks.astype(float)
        return 2.0 * np.einsum("i,baij,j->ba", d, G, m), np.einsum("i,baij,j->ba", d, G, d)

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


def _gram(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(3, K, K) per axis ``a`` the products ``Σ_k x[k, a, i] y[k, a, j]`` of two (n, 3, K) arrays of
    running sums, as one matrix product per axis (BLAS: about 14 times faster than the same sum by
    ``np.einsum`` at a real flight's segment of 450 rows and K = 84; equal to rounding, 1e-15 of the
    largest). Run it under :func:`~quadcore.identify.flightdata.one_blas_thread`: OpenBLAS's
    second thread splits the sum and moves its last bits."""
    return np.matmul(x.transpose(1, 2, 0), y.transpose(1, 0, 2))


def rate_sums(rf: RateFlight, timing: Sequence[Effect], noise: NoiseModel | Filter = "gyro",
              model: Sequence[tuple[str, np.ndarray]] = ()) -> RateSums:
    """A flight's :class:`RateSums` for the one-parameter ``timing`` effects, in one pass over
    its rows: each effect's interval integrals of its torque at every point of its grid, with
    the flight's thrust hold (as the model's torque in the increments); every running sum
    through the flight's whitening filter, ``noise`` saying which: ``"gyro"`` (the default, and
    the diagnosis's) fitted to the gyro's own noise (:func:`gyro_noise_model`), ``"residual"``
    fitted to the rate-level residual (:func:`noise_model`; on the real flights it models the
    unmodelled torque's drift, not the gyro noise: docs/timing.md, "The noise model"),
    ``"white"`` none; or a given filter (:data:`Filter`: a flight not flown yet takes the logged
    ones', quadcore.plan.ratelevel). ``model``: (label, increments (m, 3)) of each column of
    :attr:`RateSums.model` (the model's linear effects per unit of a coordinate, not in ``rf``'s
    increments; :func:`flight_sums`), at no value (:attr:`RateSums.at` zero)."""
    dt_s = float(np.median(np.diff(rf.fd.state.t_s)))
    grids = {e.name: rate_grid(e, dt_s) for e in timing}
    slots = _slots(grids, len(model))
    use = rf.block >= 0
    starts, cluster = _segments(rf, use)
    X = _running_sums(rf, use, starts, timing, grids, slots, model)
    ar, share = (noise if isinstance(noise, tuple) else gyro_noise_model(rf.fd) if noise == "gyro"
                 else noise_model(X, starts, rf.fd.noise[3:]) if noise == "residual"
                 else (np.zeros((3, 0)), np.ones(3)))
    blocks, raw, lagged = _block_grams(X, starts, cluster, ar)
    lags = ar.shape[1]
    used = int(np.maximum(np.diff(starts) - lags, 0).sum()) if len(X) else 0
    total = blocks.sum(axis=0)
    return RateSums(grids, slots, blocks.astype(np.float32), total, rf.fd.noise[3:] * np.sqrt(share),
                    samples=max(rf.fd.n, 1), dt_s=dt_s, n=used, unwhitened=raw.sum(axis=0) if lags else total,
                    unwhitened_blocks=raw.astype(np.float32) if lags else None,
                    lagged_blocks=lagged.astype(np.float32) if lags else None,
                    model=tuple(label for label, _ in model), at=np.zeros(len(model)))


def _slots(grids: Mapping[str, np.ndarray], linear: int) -> dict[str, slice]:
    """Each timing effect's columns of the running sums (:attr:`RateSums.slots`): one per point of
    its grid, in ``grids``' order, after the residual's column and the model's ``linear``
    coordinates'."""
    k, slots = 1 + linear, {}
    for name, grid in grids.items():
        slots[name] = slice(k, k + len(grid))
        k += len(grid)
    return slots


def _segments(rf: RateFlight, use: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The runs of ``rf``'s used rows (``use``) in one segment: their ``starts`` (S + 1,), each the
    first row of a run in the used rows and the last the end, and (S,) each run's block as an
    index of the flight's blocks that have one (the held-out tests' clusters)."""
    b = rf.segment[use]
    if not len(b):
        return np.zeros(1, int), np.zeros(0, int)
    starts = np.flatnonzero(np.concatenate([[True], np.diff(b) != 0, [True]]))
    return starts, np.unique(rf.block[use][starts[:-1]], return_inverse=True)[1].reshape(-1)


def _running_sums(rf: RateFlight, use: np.ndarray, starts: np.ndarray, timing: Sequence[Effect],
                  grids: Mapping[str, np.ndarray], slots: Mapping[str, slice],
                  model: Sequence[tuple[str, np.ndarray]]) -> np.ndarray:
    """(m, 3, K) the running sums of the used rows, each less its run's mean (which the block's
    offset takes): the residual's, the model's linear coordinates', each timing effect's at every
    point of its grid. float32, one flight's and the largest array here: the rounding perturbs
    each value by 6e-8 of itself, a residual by that of the values, not of their Gram."""
    k = 1 + len(model) + sum(len(g) for g in grids.values())
    size = np.diff(starts)

    def demeaned(increments: np.ndarray) -> np.ndarray:
        running = np.cumsum(increments, axis=0)[use]
        if not len(running):
            return running
        return running - np.repeat(np.add.reduceat(running, starts[:-1], axis=0) / size[:, None].astype(float),
                                   size, axis=0)

    X = np.empty((int(use.sum()), 3, k), np.float32)  # filled one column at a time
    X[:, :, 0] = demeaned(rf.increments)
    for j, (_, increments) in enumerate(model, 1):
        X[:, :, j] = demeaned(increments)
    for e in timing:
        (p,) = e.parameters
        for j, v in zip(range(slots[e.name].start, slots[e.name].stop), grids[e.name]):
            X[:, :, j] = demeaned(effect_increments(e, {p.name: float(v)}, rf))
    return X


def _block_grams(X: np.ndarray, starts: np.ndarray, cluster: np.ndarray, ar: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per block and axis the packed Gram of the running sums ``X`` through the whitening filter
    ``ar`` (3, lags), each run demeaned after it (:attr:`RateSums.blocks`, float64 here), and where
    there is a filter the same without it (:attr:`RateSums.unwhitened_blocks`) and each interval's
    whitened sums with the one before's (:attr:`RateSums.lagged_blocks`, full (K, K)); with no
    filter those two are zeros (of no block for the lagged)."""
    k, lags = X.shape[2], ar.shape[1]
    iu = np.triu_indices(k)
    blocks = np.zeros((int(cluster.max()) + 1 if len(cluster) else 0, 3, len(iu[0])))
    raw = np.zeros_like(blocks)
    lagged = np.zeros((len(blocks) if lags else 0, 3, k, k))
    with one_blas_thread():  # the Gram products: the same numbers whatever BLAS's thread count
        for i, (lo, hi) in enumerate(zip(starts[:-1], starts[1:])):  # each run's Gram into its block's
            x = whitened(X[lo:hi].astype(float), ar)
            if not len(x):
                continue
            x -= x.mean(axis=0)
            blocks[cluster[i]] += _gram(x, x)[:, iu[0], iu[1]]
            if lags:
                lagged[cluster[i]] += _gram(x[:-1], x[1:])
                r = X[lo:hi].astype(float)
                r -= r.mean(axis=0)
                raw[cluster[i]] += _gram(r, r)[:, iu[0], iu[1]]
    return blocks, raw, lagged


def weights(flights: Sequence[RateSums]) -> np.ndarray:
    """(3,) per axis ``1 / σ²`` from the torque channels' sensor-noise floor (the gyro noise
    through ``J``: the same per axis up to a common factor at every level)."""
    n = np.array([s.samples for s in flights], float)
    ms = sum(s.noise ** 2 * k for s, k in zip(flights, n)) / n.sum()
    return 1.0 / np.where(ms > 0, ms, 1.0)


def split_weights(flights: Mapping[str, RateSums], splits: Sequence[tuple[Sequence[str], Sequence[str]]]
                  ) -> list[np.ndarray]:
    """Per split (training, test flights) the :func:`weights` of its training flights: what a fold
    fits and scores its test flights with, none of them weighing it."""
    return [weights([flights[f] for f in tr]) for tr, _ in splits]


@dataclass(frozen=True)
class RateFit:
    """A timing effect's one parameter fitted at the rate level: value, standard error, and the
    weighted cost at it over ``n`` intervals; ``unwhitened``: the value fitted without the flights'
    whitening filters (None: they had none), and ``unwhitened_std`` its own standard error (the
    profile's); the standard error is at least the distance from ``value`` to it plus that (the
    answer's dependence on the noise model, which the gyro cannot check: it holds the loop's
    response to its own noise, docs/timing.md "A small delay" and "Calibration")."""

    effect: str
    parameter: str
    value: float
    std: float
    cost: float
    n: int
    unwhitened: float | None = None
    unwhitened_std: float = 0.0

    @property
    def depends_on_noise_model(self) -> bool:
        """Whether the two noise models' fits differ by more than the unwhitened one's own error and
        that difference sets :attr:`std` (its note in the diagnosis, :mod:`.judgement`)."""
        if self.unwhitened is None:
            return False
        d = abs(self.value - self.unwhitened)
        return d >= self.unwhitened_std and d + self.unwhitened_std >= self.std


def fit(effect: Effect, flights: Sequence[RateSums], w: np.ndarray) -> RateFit:
    """The value of ``effect``'s one parameter minimising ``J_rate`` over ``flights`` (module), its
    standard error (:func:`fit_cost`) at least the distance to the value fitted without the flights'
    whitening filters (:attr:`RateFit.unwhitened`) plus that value's own standard error (the
    profile's): the error bar reaches the far side of the other noise model's 1σ interval. With the
    distance alone the truth sat at the bar's edge wherever the unwhitened fit was right (white gyro
    noise, a 2 ms lag or delay: z = −1.02, 40-53 % of 30 seeds within 1σ;
    benchmarks/bench_timing_calibration.py, docs/timing.md "Calibration")."""
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
    if not any(s.filtered for s in flights):
        return out
    raw = _pooled([s if s.unwhitened is None else replace(s, total=s.unwhitened) for s in flights], w)

    def J_raw(v: float) -> float:  # the same cost without each flight's whitening filter
        v = float(min(max(v, p.lower), p.upper))
        return sum(float(t @ _packed_square(s.direction(effect, v))) for s, t in raw)

    other, var = (piecewise_quadratic_minimum(J_raw, knots, n)[:2] if effect.linear_between_samples
                  else solve.scalar_minimum(J_raw, n, p.lower, p.upper, samples_per_independent=1))
    own = float(np.sqrt(var)) if np.isfinite(var) else 0.0  # no rise within the bounds: the distance alone
    return replace(out, std=max(out.std, abs(out.value - other) + own), unwhitened=other, unwhitened_std=own)


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


def _model_torque(model, flight: str, fd: FlightData, keep_linear: bool) -> tuple[Vehicle, np.ndarray | None]:
    """The vehicle of ``flight`` and the torque (n, 3) of the model's effects there (unfiltered):
    with ``keep_linear``, of its effects that are not linear (the linear ones are columns of the
    sums, :func:`model_columns`)."""
    m = model.for_flight(flight)
    terms = [t for t in m.terms if not (keep_linear and get_effect(t.name).linear)]
    if not terms:
        return m.vehicle, None
    tau = np.zeros((fd.state.n, 3))
    for t in terms:
        tau += get_effect(t.name).wrench(fd.state, m.vehicle, t.params)[1]
    return m.vehicle, tau


def model_columns(model, flight: str, labels: Sequence[str]) -> list[tuple[str, float]]:
    """(label, value) of the linear coordinates ``labels`` (``effect:index``, a
    :attr:`RateSums.model`) of ``model``'s linear effects on ``flight``
    (:meth:`~quadcore.effects.Effect.to_linear`; a label the model lacks is at 0)."""
    m = model.for_flight(flight)
    values = {f"{t.name}:{i}": float(c) for t in m.terms if get_effect(t.name).linear
              for i, c in enumerate(get_effect(t.name).to_linear(t.params, m.vehicle))}
    return [(label, values.get(label, 0.0)) for label in labels]


def _model_increments(model, flight: str, rf: RateFlight) -> list[tuple[str, np.ndarray]]:
    """(label, ``∫ B_j dt`` (m, 3)) per linear coordinate of the model's linear effects on
    ``flight`` that has a torque: the torque per unit of it over each sample interval, with the
    thrust hold."""
    m, st = model.for_flight(flight), rf.fd.state
    out = []
    for t in m.terms:
        e = get_effect(t.name)
        if e.linear:
            for i, (_, torque) in enumerate(e.basis(st, m.vehicle)):
                if np.any(torque):  # a coordinate without torque (a drag's) is no column: the rate level is torque
                    out.append((f"{t.name}:{i}", signals.interval_integrals(torque, st.t_s, st.thrust_hold_s)))
    return out


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
    the start left out, and the model on the flight: its vehicle, its effects, and the values of
    those that are not linear (a linear one's values are not in the sums: :attr:`RateSums.at`)."""
    m = model.for_flight(flight)
    return {"timing": [e.name for e in timing], "skip_blocks": skip_blocks,
            "vehicle": {k: v for k, v in asdict(m.vehicle).items() if k != "source"},
            "terms": [[t.name, None if get_effect(t.name).linear else t.params] for t in m.terms]}


def flight_sums(fd: FlightData, model, flight: str, timing: Sequence[Effect], skip_blocks: int,
                noise: NoiseModel | Filter = "gyro") -> RateSums:
    """One flight's :class:`RateSums` as the diagnosis takes them: the increments with the torque
    of ``model``'s effects (on ``flight``) removed (its linear effects' as columns taken out at
    their values, :attr:`RateSums.at`; all in the increments for ``noise="residual"``, whose filter
    is fitted to the residual), its first ``skip_blocks`` blocks left out (the longest memory of
    the ``timing`` candidates), whitened as ``noise`` says (:func:`rate_sums`)."""
    keep = not (isinstance(noise, str) and noise == "residual")
    vehicle, tau = _model_torque(model, flight, fd, keep)
    rf = rate_flight(fd, vehicle, tau, skip_blocks)
    return rate_sums(rf, timing, noise, _model_increments(model, flight, rf) if keep else ()).at_model(model, flight)


def flight_rates(fd: FlightData, model, flight: str, timing: Sequence[Effect], skip_blocks: int) -> FlightRates:
    """What the rate level keeps of one flight (:func:`quadcore.identify.rates.judge`'s, and its
    cache's): :class:`BelowCommandRate` (its median log period and thrust hold) when it is
    :func:`below_command_rate`, else its :func:`flight_sums`."""
    if below_command_rate(fd):
        return BelowCommandRate(float(np.median(np.diff(fd.state.t_s))), fd.state.thrust_hold_s)
    return flight_sums(fd, model, flight, timing, skip_blocks)


def below_command_rate(fd: FlightData) -> bool:
    """True when ``fd`` logs a held command (PWM) less often than the firmware sets it: the
    commands between two samples are not in the log."""
    hold = fd.state.thrust_hold_s
    return hold > 0 and float(np.median(np.diff(fd.state.t_s))) > 1.5 * hold
