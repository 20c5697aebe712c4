"""Smoothing and differentiation of logged signals, zero phase.

We use a Savitzky-Golay filter: a least-squares polynomial fit over a symmetric window
of ``window`` samples. Being symmetric, it has **no phase lag** (a pure low-pass in
amplitude). With the defaults (order 2, 31 samples at 500 Hz, a 62 ms window) the
amplitude response falls to -3 dB at 17 Hz (computed from the filter's coefficients):
above the rigid-body dynamics of a small quadrotor, below motor vibration.

Derivatives come from the same fit (``deriv=1``), scaled by the median sample period.
Samples within half a window of a gap longer than ``GAP_S`` are less accurate: see
:func:`near_gap`. A gap longer than ``SPLIT_GAP_S`` splits the signal: each side is filtered
on its own, so no window reaches across it (where the times are given).
"""

from __future__ import annotations

import functools

import numpy as np
from scipy.ndimage import convolve1d
from scipy.signal import savgol_coeffs, savgol_filter

WINDOW = 31
ORDER = 2
GAP_S = 0.02
SPLIT_GAP_S = 0.1  # 50 samples at 500 Hz: the flight before and after are separate signals


def segments(t_s: np.ndarray, gap_s: float = SPLIT_GAP_S) -> list[slice]:
    """The runs of samples between gaps longer than ``gap_s``."""
    cuts = np.flatnonzero(np.diff(t_s) > gap_s) + 1 if len(t_s) > 1 else np.empty(0, int)
    edges = [0, *cuts.tolist(), len(t_s)]
    return [slice(a, b) for a, b in zip(edges[:-1], edges[1:])]


def _split(filter_one, x: np.ndarray, t_s: np.ndarray | None) -> np.ndarray:
    """``filter_one(x_part, t_part)`` on each segment of ``t_s``, joined (once when no gap)."""
    parts = segments(t_s) if t_s is not None else []
    if t_s is None or len(parts) == 1:
        return filter_one(x, t_s)
    return np.concatenate([filter_one(x[p], t_s[p]) for p in parts], axis=0)


@functools.lru_cache(maxsize=32)
def _plan(window: int, deriv: float, delta: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The filter's coefficients and its two edge operators (``window // 2`` rows each): what
    ``savgol_filter(..., mode="interp")`` recomputes on every call. An edge is a polynomial
    fitted to the first (last) ``window`` samples, a linear map of them: the filter applied to
    the unit impulses of one window gives its matrix."""
    edges = savgol_filter(np.eye(window), window, ORDER, deriv=int(deriv), delta=delta, axis=0, mode="interp")
    half = window // 2
    return savgol_coeffs(window, ORDER, deriv=int(deriv), delta=delta), edges[:half], edges[window - half:]


def _savgol(x: np.ndarray, window: int, deriv: int = 0, delta: float = 1.0) -> np.ndarray:
    """``savgol_filter(x, window, ORDER, deriv, delta, axis=0, mode="interp")`` with its plan
    cached (:func:`_plan`): the same convolution inside (bit for bit), the same edge fits as a
    matrix product (equal to rounding), in a third of the time on a flight's columns."""
    x = np.asarray(x)
    if x.dtype not in (np.float32, np.float64):
        x = x.astype(np.float64)
    coeffs, left, right = _plan(window, deriv, float(delta))
    y = convolve1d(x, coeffs, axis=0, mode="constant")
    half = window // 2
    y[:half] = np.tensordot(left, x[:window], axes=1)
    y[len(x) - half:] = np.tensordot(right, x[len(x) - window:], axes=1)
    return y


def _window(n: int, window: int) -> int:
    w = min(window, n if n % 2 else n - 1)
    return max(w, ORDER + 1 + (ORDER % 2 == 0))


def smooth(x: np.ndarray, window: int = WINDOW, t_s: np.ndarray | None = None) -> np.ndarray:
    """Zero-phase Savitzky-Golay smoothing along axis 0 (x: (n,) or (n, k)); with ``t_s``,
    separately on each side of every long gap."""
    def one(xs, _t):
        if len(xs) <= ORDER + 2:
            return np.asarray(xs, dtype=float)
        return _savgol(xs, _window(len(xs), window))
    return _split(one, x, t_s)


def derivative(x: np.ndarray, t_s: np.ndarray, window: int = WINDOW) -> np.ndarray:
    """Zero-phase smoothed time derivative dx/dt along axis 0, per second, separately on each
    side of every long gap."""
    def one(xs, ts):
        if len(xs) < 2:
            return np.zeros_like(np.asarray(xs, dtype=float))
        if len(xs) <= ORDER + 2:
            return np.gradient(np.asarray(xs, dtype=float), ts, axis=0)
        dt = float(np.median(np.diff(ts)))
        return _savgol(xs, _window(len(xs), window), deriv=1, delta=dt)
    return _split(one, x, t_s)


def near_gap(t_s: np.ndarray, window: int = WINDOW, gap_s: float = GAP_S) -> np.ndarray:
    """True for samples whose filter window spans a gap in the log longer than ``gap_s``."""
    n = len(t_s)
    flag = np.zeros(n, dtype=bool)
    if n < 2:
        return flag
    gaps = np.flatnonzero(np.diff(t_s) > gap_s)
    if len(gaps) == 0:
        return flag
    half = window // 2
    # mark [g - half + 1, g + half] around each gap with a difference array (no loop per gap)
    marks = np.zeros(n + 1, dtype=np.int64)
    np.add.at(marks, np.clip(gaps - half + 1, 0, n), 1)
    np.add.at(marks, np.clip(gaps + half + 1, 0, n), -1)
    return np.cumsum(marks[:-1]) > 0


def near_edge(t_s: np.ndarray, window: int = WINDOW) -> np.ndarray:
    """True for the first and last ``window // 2`` samples of each segment (:func:`segments`).

    There the filters are edge fits (a polynomial fitted to the segment's first or last
    ``window`` samples), whose rows weigh the samples more unevenly than inside: for white noise
    their RMS gain is larger (the derivative's first row 3.9 times the interior's, the
    smoother's 1.9 times), so a residual there is noisier than the sensor-noise floor, which
    holds for the interior. The residual statistics leave these samples out, as they leave out
    those near a gap (:func:`near_gap`)."""
    flag = np.zeros(len(t_s), dtype=bool)
    half = window // 2
    for seg in segments(t_s) if len(t_s) else []:
        flag[seg.start:min(seg.start + half, seg.stop)] = True
        flag[max(seg.stop - half, seg.start):seg.stop] = True
    return flag


def interval_integrals(x: np.ndarray, t_s: np.ndarray, hold_s: float) -> np.ndarray:
    """``∫ x̂ dt`` over each sample interval ``[t_i, t_i+1]`` (n - 1 rows) of the signal ``x̂``
    whose samples ``x_i = x̂(t_i)`` hold for ``hold_s`` each::

        ∫_{t_i}^{t_i+1} x̂ dt = Δ_i ((1 - a_i) x_i + a_i x_i+1),   a_i = max(0, (1 - hold_s / Δ_i) / 2)

    A command set at ``t_i`` and held for ``h = hold_s``, followed by commands the log did not
    record (``Δ_i / h`` of them in the interval, each held ``h``, approximated by the line from
    ``x_i`` to ``x_i+1``), integrates to exactly this. ``h = 0`` is a sample of a continuous
    signal (the trapezoid, ``a = 1/2``); ``h >= Δ_i`` the command held until the next sample
    (``a = 0``). On a linear signal it is the integral of ``x̂(t - min(h, Δ_i) / 2)``: a held
    command acts, on average, half its hold after it is set."""
    dt = np.diff(t_s)
    a = np.maximum(0.0, 0.5 * (1.0 - hold_s / np.where(dt > 0, dt, np.inf)))
    if x.ndim == 2:
        dt, a = dt[:, None], a[:, None]
    return dt * ((1.0 - a) * x[:-1] + a * x[1:])


def matched_to_derivative(x: np.ndarray, t_s: np.ndarray, hold_s: float) -> np.ndarray:
    """``x`` through the filter that :func:`derivative` applies to a signal's rate of change.

    A measured torque is ``J dω/dt`` with the derivative taken by :func:`derivative`. To
    compare a modelled torque with it at the same bandwidth and timing, integrate the model
    over each sample interval (:func:`interval_integrals`, its samples held ``hold_s``) and
    differentiate the running integral the same way: ``d/dt ∫ x dt``.

    **Why this is exact.** The derivative is a linear filter ``D[ω]_k = Σ_j d_j ω_k-j`` whose
    weights sum to zero (the derivative of a constant), so ``d_j = c_j - c_j-1`` with
    ``c_j = Σ_{i<=j} d_i``, and::

        D[ω]_k = Σ_j c_j (ω(t_k-j) - ω(t_k-j-1)) = Σ_j c_j ∫_{t_k-j-1}^{t_k-j} dω/dt dt

    The gyro samples ``ω`` at ``t_k``: the measured torque is a fixed weighting of the true
    torque's integrals over the sample intervals, whatever the torque does inside them. The
    modelled torque ``D[Σ interval integrals]`` is the same weighting of the model's
    integrals. The only modelling choice is what the model does inside an interval: that is
    ``hold_s`` (``Vehicle.thrust_hold_s``: the command period for PWM, 0 for measured motor
    speeds). The Savitzky-Golay weights are symmetric, so the filter itself delays nothing;
    a delay comes only from the hold, ``hold / 2`` at most one sample interval long.
    """
    x = np.asarray(x, dtype=float)
    if len(x) < 2:
        return x.copy()
    integral = np.concatenate([np.zeros_like(x[:1]), np.cumsum(interval_integrals(x, t_s, hold_s), axis=0)])
    return derivative(integral, t_s)
