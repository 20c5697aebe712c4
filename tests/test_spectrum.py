"""The frequency view of the residual (quadcore.identify.spectrum) on a real flight with a gap."""

from __future__ import annotations

import numpy as np
import pytest

from quadcore.identify import fitting, spectrum
from quadcore.logs import flight
from quadcore.physics import vehicle

VEH = vehicle.load()


@pytest.fixture(scope="module")
def long_flight(real_logs):
    return flight.decode_flight(real_logs / "jana01").tables["fixedFrequency"]


def _view(tables: dict) -> dict:
    fds = [fitting.flight_data(fid, t, VEH) for fid, t in tables.items()]
    return spectrum.frequency_view(fds, {fd.flight: np.concatenate([fd.r_f, fd.r_tau], axis=1) for fd in fds}, VEH)


def test_a_gap_in_the_log_splits_the_spectra_as_two_flights_would(long_flight):
    """A flight with a 2 s hole has the spectra of its two sides logged as separate flights:
    no Welch segment spans the gap (before, they did, and mixed the two sides' edges)."""
    n = long_flight.height
    before, after = long_flight.slice(0, n // 2), long_flight.slice(n // 2 + 1000)
    assert float(after["t_s"][0] - before["t_s"][-1]) > 1.0  # a real gap, longer than signals.SPLIT_GAP_S
    one = _view({"gapped": long_flight.slice(0, n // 2).vstack(after)})
    two = _view({"before": before, "after": after})
    for a, b in zip(one["channels"], two["channels"]):
        for key in ("residual_rms", "measured_rms", "modelled_rms", "coherence", "gain", "phase_deg"):
            np.testing.assert_allclose(a[key], b[key], rtol=1e-9, atol=1e-15, err_msg=f"{a['channel']} {key}")
