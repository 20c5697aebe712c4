"""The reference the frequency view from stored summaries
(:func:`quadcore.identify.describe.summaries.frequency_view`) is tested against: the same spectra computed
on the flights' rows with ``scipy.signal.welch`` / ``csd``, stretch by stretch, summed into a
:class:`quadcore.identify.describe.spectrum.SpectrumSums` as the module's docstring defines them. Nothing in
quadcore uses it; tests/test_summaries.py and tests/test_spectrum.py compare against it."""

from __future__ import annotations

import numpy as np
from scipy import signal

from quadcore.identify.describe.spectrum import SEGMENT, SpectrumSums, sample_rate_hz
from quadcore.identify.flightdata import FlightData
from quadcore.physics import residuals, signals


def _spectra(meas: np.ndarray, model: np.ndarray, fs: float):
    """Frequencies and (n_freq, 6) auto/cross spectra of model p, measurement m and residual."""
    n = min(SEGMENT, len(meas))
    kw = {"fs": fs, "nperseg": n, "axis": 0, "detrend": "constant"}  # each segment's mean is reported apart
    f, s_pp = signal.welch(model, **kw)
    _, s_mm = signal.welch(meas, **kw)
    _, s_rr = signal.welch(meas - model, **kw)
    _, s_pm = signal.csd(model, meas, **kw)
    return f, s_pp, s_mm, s_rr, s_pm


def add(sums: SpectrumSums, fd: FlightData, resid: np.ndarray, vehicle) -> None:
    """One flight and its (n, 6) residual (force N, torque N m) added to ``sums`` from its rows."""
    # Welch segments must not straddle a gap in the log: each gap-free stretch is its own signal
    stretches = [p for p in signals.segments(fd.state.t_s) if p.stop - p.start >= 2 * SEGMENT]
    if not stretches:
        return  # too short to resolve the slow bands
    arrays = residuals.residual_arrays(fd.state, vehicle)
    meas = np.concatenate([arrays["f_meas_b"], arrays["tau_meas_b"]], axis=1)
    model = meas - resid
    for part in stretches:
        _, *specs = _spectra(meas[part], model[part], sums.fs)
        for key, s in zip(("pp", "mm", "rr", "pm"), specs):
            sums.acc[key] += (part.stop - part.start) * s
    n = sum(p.stop - p.start for p in stretches)
    sums.mean_sq += n * resid[fd.mask].mean(axis=0) ** 2
    sums.weight += n


def frequency_view(flights: list[FlightData], resid: dict[str, np.ndarray], vehicle) -> dict:
    """The residual by frequency band and the coherence of model and measurement (JSON-ready),
    at the flights' median sample rate; ``resid[flight]`` their (n, 6) residual under the evaluated
    model (force N, torque N m)."""
    sums = SpectrumSums(float(np.median([sample_rate_hz(fd.state.t_s) for fd in flights])), vehicle)
    for fd in flights:
        add(sums, fd, resid[fd.flight], vehicle)
    return sums.view()
