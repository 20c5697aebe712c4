"""The rate level's gyro noise model: a whitening filter per flight and axis.

The rate level's argument (:mod:`quadcore.identify.rates`) needs the gyro noise white. The real
logs' is not (the firmware's 80 Hz low-pass: lag-one autocorrelation +0.7), and ``ε_k`` then
correlates with the ``ε_(k−1)`` the commands react to: on three hover flights with that noise
(simulated) a 10 ms delay came out 9.2-9.7 ms, a lag 11.0-11.9 ms, the delay preferred when the
lag was true. Each flight's running sums (``R`` and every ``C``) go through a whitening filter
per axis ``a`` (body frame)

    x̃_k = x_k − Σ_(i=1..p) φ_ai x_(k−i)

an AR model of the gyro's own noise (:func:`gyro_noise_model`: its spectrum read off the logged
rate less its trend above 30 Hz, held flat below; order ≤ 8 by BIC, 0 on white noise;
Yule-Walker with a 10 % white floor), so that the filtered residual's noise is the innovation,
unpredictable from the past; the fit stays a quadratic form of the filtered sums
(:func:`whitened`). Same flights: the lag 9.8-10.9 ms and preferred in 5 of 5 seeds; a 9 ms
delay 8.8-9.2 ms (docs/timing.md). The filter fitted to the residual instead
(:func:`noise_model`, ``rate_sums(..., noise="residual")``) is unbiased on the simulator too,
but on the 19 real flights it has ``Σφ`` 0.98-0.99, a near-difference that models the
unmodelled torque's drift within the running sums, not the sensor noise, and 'found' a delay of
1.0 ms at 6.3 σ; the gyro's has ``Σφ`` 0.5-0.65 and finds none. Which filter is right the gyro
cannot tell (it holds the loop's response to its own noise): the fit and the comparison are
also taken without it (:mod:`quadcore.identify.rates.sums`, :mod:`quadcore.identify.rates.compare`).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from scipy import linalg
from scipy.signal import savgol_coeffs

from quadcore.identify.flightdata import FlightData
from quadcore.physics import signals

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
