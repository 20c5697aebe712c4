"""The diagnosis's thresholds and folds are one frozen DiagnosisSettings (quadcore.identify.settings):
defaulted in one place, passed in, obeyed, and recorded in the JSON document."""

from __future__ import annotations

import json

import pytest

from quadcore.identify import evidence
from quadcore.identify.describe import regimes
from quadcore.identify.discovery import library_stats
from quadcore.identify.settings import DEFAULT, STATISTICS, DiagnosisSettings
from quadcore.identify.stats import sufficient
from quadcore.physics import vehicle
from quadcore.spec import model
from quadcore.workflows import fleet as fleetlib, identify


def test_the_module_constants_are_the_settings_defaults():
    assert (evidence.ALPHA, evidence.MIN_SIGMA, evidence.TIE_MARGIN, evidence.NOISE_MARGIN) == (
        DEFAULT.alpha, DEFAULT.min_sigma, DEFAULT.tie_margin, DEFAULT.noise_margin)
    assert (evidence.BLOCK_S, evidence.SECANT, sufficient.GRAM_STRIDE, library_stats.STRIDE) == (
        STATISTICS.block_s, STATISTICS.secant, STATISTICS.gram_stride, STATISTICS.library_stride)
    assert regimes.HEIGHT_BINS == list(STATISTICS.height_bins_m)


def test_the_settings_go_to_json_and_back():
    s = DiagnosisSettings(min_sigma=5.0, n_folds=3)
    d = json.loads(json.dumps(s.to_dict(), allow_nan=False))  # an open bin edge is null, not -Infinity
    assert DiagnosisSettings.from_dict(d) == s and d["statistics"]["height_bins_m"][0] is None
    assert DiagnosisSettings.from_dict(None) == DEFAULT  # a document written before settings were recorded


@pytest.mark.parametrize("bad", [{"alpha": 1.5}, {"noise_margin": -0.1}, {"min_sigma": -1.0}, {"n_folds": 1}])
def test_a_setting_out_of_its_range_is_a_clear_error(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        DiagnosisSettings(**bad)


def test_the_diagnosis_obeys_and_records_its_settings(drag_fleet):
    """The shared fleet's hidden rotor drag is found with the defaults; asked for 10^6 standard
    errors of significance, nothing is, and the document says which settings it used."""
    veh = vehicle.load()
    flights = fleetlib.fleet_from_logs([str(drag_fleet)], veh)
    strict = DiagnosisSettings(min_sigma=1e6, n_folds=2)
    by_default = identify.diagnose(flights, model.spec_from(veh, []), [])
    demanding = identify.diagnose(flights, model.spec_from(veh, []), [], settings=strict)
    assert by_default.candidates[0].found and by_default.candidates[0].effect == "rotor_drag"
    assert not any(c.found for c in demanding.candidates)
    assert all(not c.significant for c in demanding.candidates)
    assert demanding.evaluation.folds == 2
    doc = json.loads(identify.diagnosis_json(demanding))
    assert DiagnosisSettings.from_dict(doc["settings"]) == strict
    assert json.loads(identify.diagnosis_json(by_default))["settings"] == DEFAULT.to_dict()


def test_discovery_obeys_and_records_its_settings(drag_fleet):
    """Discovery on the shared fleet keeps terms with the defaults (rotor drag's v T explains over 99 % of
    the held-out f_x); asked that a term add all of an axis' held-out variance, it keeps none, says so
    with that share, and records the settings."""
    veh = vehicle.load()
    flights = fleetlib.fleet_from_logs([str(drag_fleet)], veh)
    demanding = DiagnosisSettings(min_gain=1.0)
    by_default = identify.discover(flights, model.spec_from(veh, []), ["sim003"])
    strict = identify.discover(flights, model.spec_from(veh, []), ["sim003"], settings=demanding)
    assert by_default.terms and not strict.terms
    assert "at least 100% of an axis' variance" in strict.summary
    assert DiagnosisSettings.from_dict(strict.to_dict()["settings"]) == demanding
