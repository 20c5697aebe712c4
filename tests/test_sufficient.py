"""Per-flight sufficient statistics: combined, they give the fits, folds and held-out tests the
rows give (to float rounding), and they survive a round trip through the data root."""

from __future__ import annotations

import copy
import gc
import importlib
import sys
import weakref
from pathlib import Path

import numpy as np
import pytest
from reference import rows as reference
from reference.flight import as_rows

from quadcore import effects
from quadcore.identify import evidence, fit as fitlib, flightdata, rates
from quadcore.identify.fit import model_fit, sessions
from quadcore.identify.stats import sufficient
from quadcore.logs import flight
from quadcore.physics import vehicle
from quadcore.spec.model import spec_from

VEHICLE = vehicle.load()
REL = 1e-9


@pytest.fixture(scope="module")
def fleet(drag_fleet):
    """The shared simulated fleet as FlightData, and the statistics of every linear effect."""
    fds = {p.name: flightdata.flight_data(p.name, flight.decode_flight(p).tables["fixedFrequency"], VEHICLE)
           for p in flight.discover_logs(drag_fleet)}
    layout = sufficient.library_layout()
    key = sufficient.stats_key(VEHICLE, VEHICLE, layout)
    stats = {f: sufficient.flight_stats(fd, VEHICLE, layout, key) for f, fd in fds.items()}
    return fds, stats


def _close(a: dict, b: dict, rel: float = REL) -> None:
    for e in a:
        for k in a[e]:
            assert a[e][k] == pytest.approx(b[e][k], rel=rel, abs=1e-14), f"{e}.{k}: {a[e][k]} vs {b[e][k]}"


LINEAR = [n for n, e in effects.registry().items() if e.linear]


@pytest.mark.parametrize("names", [[n] for n in LINEAR] + [["thrust_scale", "rotor_drag", "com_offset"]])
def test_combined_fit_equals_the_row_fit(fleet, names):
    fds, stats = fleet
    ids = sorted(fds)
    es = [effects.get(n) for n in names]
    rows = reference.fit_effects(es, [fds[f] for f in ids], flightdata.targets_of([fds[f] for f in ids]), VEHICLE)
    combined = fitlib.fit_effects(es, [stats[f] for f in ids], [stats[f].layout.target() for f in ids], VEHICLE)
    # a joint fit's normal equations are worse conditioned (a CoM offset of 1e-8 m beside a drag, a
    # vertical drag beside the thrust scale): the same rounding of the sums moves its solution more,
    # so it is compared in its own standard errors (a millionth of one)
    if len(es) == 1:
        _close(rows.params, combined.params)
    else:
        for e in rows.params:
            for k, v in rows.params[e].items():
                other = combined.params[e][k]
                assert abs(v - other) <= 1e-6 * rows.std[e][k], f"{e}.{k}: {v} vs {other}"
    _close(rows.std, combined.std, rel=1e-6)
    np.testing.assert_allclose(rows.weights, combined.weights, rtol=REL)


def test_fixed_effects_are_subtracted_alike(fleet):
    fds, stats = fleet
    ids = sorted(fds)
    es = [effects.get("rotor_drag"), effects.get("thrust_scale")]
    fixed = {"thrust_scale": {"scale": 0.97}}
    rows = reference.fit_effects(es, [fds[f] for f in ids], flightdata.targets_of([fds[f] for f in ids]), VEHICLE,
                                 fixed)
    combined = fitlib.fit_effects(es, [stats[f] for f in ids], [stats[f].layout.target() for f in ids], VEHICLE,
                                   fixed)
    _close(rows.params, combined.params)


def test_per_session_fit_from_statistics_equals_the_row_fit(fleet):
    fds, stats = fleet
    ids = sorted(fds)
    spec = spec_from(VEHICLE, ["thrust_scale", "rotor_drag"])
    spec.per_session = ["thrust_scale"]
    groups = {"a": ids[:2], "b": ids[2:]}
    targets = dict(zip(ids, flightdata.targets_of([fds[f] for f in ids])))
    rows = sessions.fit_per_session(spec, fds, targets, ids, groups, fit=reference.fit_effects)
    combined = sessions.fit_per_session(spec, stats, {f: stats[f].layout.target() for f in ids}, ids, groups,
                                        fit=fitlib.fit_effects)
    for a, b in zip(rows.terms, combined.terms):
        _close({a.name: a.params}, {b.name: b.params})
        for s in a.per_session:
            _close({s: a.per_session[s]}, {s: b.per_session[s]})


def test_held_out_test_from_statistics_equals_the_rows(fleet):
    fds, stats = fleet
    ids = sorted(fds)
    train, test = ids[:3], ids[3:]
    e = effects.get("rotor_drag")
    fit = reference.fit_effects([e], [fds[f] for f in train], flightdata.targets_of([fds[f] for f in train]), VEHICLE)
    w = evidence.channel_mask(["force"])
    resid_rows = {f: np.concatenate([fds[f].r_f, fds[f].r_tau], axis=1) for f in test}
    pred_rows = {f: fit.predict([e], fds[f], VEHICLE) for f in test}
    resid_vec = {f: stats[f].layout.target() for f in test}
    pred_vec = {f: fit.predict([e], stats[f], VEHICLE) for f in test}
    a = evidence.held_out_test([as_rows(fds[f]) for f in test], resid_rows, pred_rows, w)
    b = evidence.held_out_test([stats[f] for f in test], resid_vec, pred_vec, w)
    assert a.blocks == b.blocks > 0
    assert b.t == pytest.approx(a.t, rel=REL) and b.beta == pytest.approx(a.beta, rel=REL)
    assert b.p_value == pytest.approx(a.p_value, rel=1e-6, abs=1e-300)


def test_statistics_do_not_grow_with_rows_and_survive_the_data_root(fleet, tmp_path):
    fds, stats = fleet
    s = stats[sorted(stats)[0]]
    width = s.layout.width
    assert s.gram.shape == (s.blocks, 6, width, width) and s.rows.sum() == fds[s.flight].mask.sum()
    sufficient.save(s, tmp_path)
    back = sufficient.load(tmp_path, s.flight)
    assert back.layout == s.layout and back.key == s.key and back.vbat_median_V == s.vbat_median_V
    np.testing.assert_array_equal(back.gram, s.gram)
    assert sufficient.load_current(tmp_path, s.flight, s.key) is not None
    assert sufficient.load_current(tmp_path, s.flight, "another") is None
    assert not [p for p in (tmp_path / "stats").rglob("*") if p.name.endswith(".tmp")]


def test_a_file_that_is_not_statistics_is_a_clear_error(tmp_path):
    path = sufficient.stats_path(tmp_path, "x")
    path.parent.mkdir(parents=True)
    path.write_bytes(b"not numpy")
    with pytest.raises(sufficient.StatsError, match="not a statistics file"):
        sufficient.load(tmp_path, "x")
    assert sufficient.load_current(tmp_path, "x", "k") is None


@pytest.fixture(scope="module")
def lagged_fleet(tmp_path_factory):
    """Three short random flights with a motor lag of 30 ms hidden: FlightData, and statistics
    with the profiles of every one-parameter nonlinear effect."""
    from quadcore.sim import simulation

    folder = tmp_path_factory.mktemp("lagged")
    configs = [simulation.SimConfig(kind="random", duration_s=4.0, seed=s, speed_min_mps=0.8) for s in (31, 32, 33)]
    simulation.simulate_set(folder, configs, {"motor_lag": {"tau_s": 0.03}}, VEHICLE)
    fds = {p.name: flightdata.flight_data(p.name, flight.decode_flight(p).tables["fixedFrequency"], VEHICLE)
           for p in flight.discover_logs(folder)}
    layout = sufficient.library_layout()
    return fds, {f: sufficient.flight_stats(fd, VEHICLE, layout) for f, fd in fds.items()}


@pytest.mark.parametrize("name", ["motor_lag", "thrust_delay"])
def test_the_profile_search_equals_the_row_search(lagged_fleet, name):
    """A one-parameter nonlinear effect fitted from the flights' profiles lands where the row
    search does, within the search's own tolerance (5e-4 of the span), with the same error.
    A delay's row objective ripples with the sample period (the delay is linear between
    samples, so it smooths the thrust most half-way between them): the grid does not resolve
    that ripple, and the two agree to a tenth of a sample instead (0.08 of a sample on these
    flights since the simulator integrates a lagged thrust's mean over each physics step; 0.05
    before, when it held the step's start value)."""
    fds, stats = lagged_fleet
    ids = sorted(fds)
    e = effects.get(name)
    (p,) = e.parameters
    rows = reference.fit_effects([e], [fds[f] for f in ids], flightdata.targets_of([fds[f] for f in ids]), VEHICLE)
    combined = fitlib.fit_effects([e], [stats[f] for f in ids], [stats[f].layout.target() for f in ids], VEHICLE)
    dt_s = float(np.median(np.diff(fds[ids[0]].state.t_s)))
    tolerance = 5e-4 * (p.upper - p.lower) if name == "motor_lag" else dt_s / 10
    assert abs(rows.params[name][p.name] - combined.params[name][p.name]) <= tolerance
    assert combined.std[name][p.name] == pytest.approx(rows.std[name][p.name], rel=0.05 if name == "motor_lag" else 0.2)
    if name == "motor_lag":
        assert combined.params[name][p.name] == pytest.approx(0.03, rel=0.15)


def test_a_profiled_effect_beside_linear_ones_is_fitted_as_the_rows_fit_it(lagged_fleet):
    """Variable projection from statistics: the lag's search with a thrust scale solved inside
    (and a fixed CoM offset subtracted), then the scale on what the lag leaves, as on rows."""
    fds, stats = lagged_fleet
    ids = sorted(fds)
    es = [effects.get("thrust_scale"), effects.get("motor_lag"), effects.get("com_offset")]
    fixed = {"com_offset": {"x_c_m": 0.001, "y_c_m": 0.0}}
    rows = reference.fit_effects(es, [fds[f] for f in ids], flightdata.targets_of([fds[f] for f in ids]), VEHICLE,
                                 fixed)
    combined = fitlib.fit_effects(es, [stats[f] for f in ids], [stats[f].layout.target() for f in ids], VEHICLE,
                                   fixed)
    assert abs(rows.params["motor_lag"]["tau_s"] - combined.params["motor_lag"]["tau_s"]) <= 5e-4 * 0.2
    assert combined.std["motor_lag"]["tau_s"] == pytest.approx(rows.std["motor_lag"]["tau_s"], rel=0.05)
    assert combined.params["thrust_scale"]["scale"] == pytest.approx(rows.params["thrust_scale"]["scale"], rel=1e-6)
    assert combined.std["thrust_scale"]["scale"] == pytest.approx(rows.std["thrust_scale"]["scale"], rel=1e-3)
    assert combined.params["com_offset"] == fixed["com_offset"]


SLOW_THRUST = """
from quadcore.effects.base import Effect, Parameter, rotor_wrench


class SlowThrust(Effect):
    name = "slow_thrust"
    target = "both"
    parameters = (Parameter("k", "1", 0.0, 0.0, 0.5, "share of the thrust that comes late"),)

    def wrench(self, state, vehicle, params):
        late = state.f_rotor_N.copy()
        late[1:] = state.f_rotor_N[:-1]
        return rotor_wrench(vehicle, params["k"] ** 2 * (late - state.f_rotor_N))


EFFECT = SlowThrust()
"""


def test_a_plugin_with_one_nonlinear_parameter_is_profiled(lagged_fleet, tmp_path):
    """A user's nonlinear effect of one parameter named in the model file gets its profile in
    the stored statistics, and is fitted from it as from rows."""
    path = tmp_path / "slow_thrust.py"
    path.write_text(SLOW_THRUST)
    e = effects.load_plugin(path)
    try:
        assert "slow_thrust" in sufficient.spec_layout(spec_from(VEHICLE, ["slow_thrust"])).profiled
        fds, _ = lagged_fleet
        ids = sorted(fds)
        layout = sufficient.layout_of([e])
        stats = [sufficient.flight_stats(fds[f], VEHICLE, layout) for f in ids]
        rows = reference.fit_effects([e], [fds[f] for f in ids], flightdata.targets_of([fds[f] for f in ids]), VEHICLE)
        combined = fitlib.fit_effects([e], stats, [s.layout.target() for s in stats], VEHICLE)
        assert abs(rows.params["slow_thrust"]["k"] - combined.params["slow_thrust"]["k"]) <= 5e-4 * 0.5
        assert combined.params["slow_thrust"]["k"] > 0.1  # a lag is found as late thrust
    finally:
        effects.unregister("slow_thrust")


SCALED_LAG = Path(__file__).resolve().parent / "plugins" / "scaled_lag.py"  # two nonlinear parameters


def test_a_candidate_with_two_nonlinear_parameters_is_scored_from_rows_beside_profiled_ones(lagged_fleet, tmp_path):
    """A candidate without a profile (two nonlinear parameters) is fitted on its training flights'
    rows and its held-out prediction is a column from the evaluated flight's rows, beside the
    profiled candidates' columns: all of them scored on the same flights."""
    from quadcore.identify import diagnosis

    effects.load_plugin(SCALED_LAG)
    try:
        fds, stats = lagged_fleet
        held = sorted(fds)[-1]
        read = []
        with pytest.MonkeyPatch.context() as m:
            m.setattr(flightdata, "flight_data", lambda f, decoded, veh: read.append(f) or fds[f])
            result = diagnosis.diagnose({f: "rows" for f in fds}, spec_from(VEHICLE, []), [held],
                                        ["motor_lag", "scaled_lag"], stats=stats.get).to_dict()
        assert set(read) == set(fds)  # the two-parameter candidate's training rows, the held-out flight's
        rows = {r["effect"]: r for r in result["candidates"]}
        assert rows["motor_lag"]["found"] and rows["scaled_lag"]["found"], result["verdict"]
        assert rows["scaled_lag"]["parameters"]["tau_s"] == pytest.approx(0.03, rel=0.2)
        assert rows["motor_lag"]["parameters"]["tau_s"] == pytest.approx(0.03, rel=0.15)
    finally:
        effects.unregister("scaled_lag")


def test_a_candidate_without_a_profile_beside_a_model_with_a_profiled_effect_is_described(lagged_fleet):
    """A model with a profiled effect (its prediction a column of the residual's statistics) and a
    candidate without a profile (its held-out prediction and unit wrenches columns from the
    evaluated flight's rows, before the model's column): the residual's regime tables, from its
    rows, find each column of the residual by name (before: 'a signal on extra columns has no
    rows here', the model's column looked for right after the flight's own)."""
    from quadcore.identify import diagnosis

    effects.load_plugin(SCALED_LAG)
    try:
        fds, stats = lagged_fleet
        held = sorted(fds)[-1]
        with pytest.MonkeyPatch.context() as m:
            m.setattr(flightdata, "flight_data", lambda f, decoded, veh: fds[f])
            result = diagnosis.diagnose({f: "rows" for f in fds}, spec_from(VEHICLE, ["motor_lag"]), [held],
                                        ["scaled_lag"], stats=stats.get).to_dict()
        assert [f["flight"] for f in result["flights"]] == [held] and result["regimes"]
        assert result["model"]["effects"][0]["params"]["tau_s"] == pytest.approx(0.03, rel=0.15)
    finally:
        effects.unregister("scaled_lag")


def test_the_residuals_rows_are_the_residual_its_statistics_hold(lagged_fleet):
    """A model with a profiled effect, its prediction a column ``pred:<effect>`` of the residual's
    statistics (interpolated in the profile's grid): the residual's rows (the regime tables', the
    search's extra columns) hold that same column, so their sums of squares are the statistics'
    to rounding. (Before, the rows held the exact prediction: 3e-5 relative off here, motor_lag
    fixed at 15 ms, off its profile's grid.)"""
    from quadcore.identify.diagnosis import problem

    fds, stats = lagged_fleet
    spec = spec_from(VEHICLE, ["rotor_drag", "motor_lag"], {"motor_lag": {"tau_s": 0.015}})
    with pytest.MonkeyPatch.context() as m:
        m.setattr(flightdata, "flight_data", lambda f, decoded, veh: fds[f])
        p = problem._Problem({f: "rows" for f in fds}, spec, [], stats.get)
        _, model_of = problem._fit_model(p, p.ids, None, lambda msg: None)
        resid = problem._residual(p, model_of, p.ids)
        for f in p.ids:
            assert resid.values[f] == {"motor_lag": 0.015}
            rows = p.fl.signal_rows(f, resid.signal[f], resid.on[f].layout, resid.values[f], resid.extras[f])
            np.testing.assert_allclose((rows[fds[f].mask] ** 2).sum(axis=0),
                                       resid.on[f].sum_of_squares(resid.signal[f]), rtol=1e-10)


def test_the_profile_is_exact_on_its_grid(lagged_fleet):
    """At a grid point, the held-out prediction's sums from the profile are the rows' sums."""
    from quadcore.identify.stats import profiles

    fds, stats = lagged_fleet
    f = sorted(fds)[0]
    e = effects.get("motor_lag")
    v = float(profiles.profile_grid(0.0, 0.2)[20])
    s = profiles.with_predictions(stats[f], {"motor_lag": v})
    pred = flightdata.prediction(e, {"tau_s": v}, fds[f], VEHICLE)
    y = flightdata.targets_of([fds[f]])[0]
    col = s.layout.unit(s.layout.extra("pred:motor_lag"))
    target = s.layout.pad(stats[f].layout.target())
    np.testing.assert_allclose(sufficient.channel_sums(s.total, col, target),
                               (pred * y)[fds[f].mask].sum(axis=0), rtol=1e-9)
    np.testing.assert_allclose(sufficient.channel_sums(s.gram, col, col).sum(axis=0),
                               (pred**2)[fds[f].mask].sum(axis=0), rtol=1e-6)  # per block: float32


def test_several_nonlinear_effects_are_refused(fleet):
    _, stats = fleet
    s = list(stats.values())
    with pytest.raises(sufficient.StatsError, match="nonlinear"):
        fitlib.fit_effects([effects.get("motor_lag"), effects.get("thrust_delay")], s,
                            [x.layout.target() for x in s], VEHICLE)


def test_the_fleet_fit_combines_stored_statistics_without_reading_rows(fleet):
    fds, stats = fleet
    ids = sorted(fds)
    spec = spec_from(VEHICLE, ["rotor_drag", "thrust_scale"])
    no_rows = {f: None for f in ids}  # any look at a flight's decoded table would fail
    fitted = model_fit.fit_model(spec, no_rows, ids, stats=stats.get)
    es = [effects.get(n) for n in spec.effects]
    # the model is fitted within its parameters' bounds (rotor_drag's k_z, ~0 here, falls on either side)
    rows = reference.fit_effects(es, [fds[f] for f in ids], flightdata.targets_of([fds[f] for f in ids]), VEHICLE,
                               bounded=True)
    _close({t.name: t.params for t in fitted.terms}, rows.params, rel=1e-7)


def test_a_model_with_a_lag_is_fitted_from_stored_profiles_without_reading_rows(lagged_fleet):
    fds, stats = lagged_fleet
    ids = sorted(fds)
    spec = spec_from(VEHICLE, ["thrust_scale", "motor_lag"])
    fitted = model_fit.fit_model(spec, {f: None for f in ids}, ids, stats=stats.get)  # no table may be read
    es = [effects.get(n) for n in spec.effects]
    rows = reference.fit_effects(es, [fds[f] for f in ids], flightdata.targets_of([fds[f] for f in ids]), VEHICLE)
    got = {t.name: t.params for t in fitted.terms}
    assert abs(got["motor_lag"]["tau_s"] - rows.params["motor_lag"]["tau_s"]) <= 5e-4 * 0.2
    assert got["thrust_scale"]["scale"] == pytest.approx(rows.params["thrust_scale"]["scale"], rel=1e-6)


class _OnlyThese(dict):
    """Decoded tables where only the named flights' rows may be read."""

    def __init__(self, tables: dict, readable: set[str]):
        super().__init__({f: None for f in tables})
        self._tables, self._readable = tables, readable

    def __getitem__(self, flight):
        assert flight in self._readable, f"{flight}'s rows were read"
        return self._tables[flight]


def test_the_diagnosis_reads_only_the_held_out_rows_for_linear_effects(drag_fleet, fleet):
    """Model, candidates, folds, held-out tests, sensitivity and disagreements from the stored
    statistics: the training flights' rows are never read, the held-out flight's are (its
    regime tables and spectra)."""
    from quadcore.identify import diagnosis

    _, stats = fleet
    tables = {p.name: flight.decode_flight(p).tables["fixedFrequency"] for p in flight.discover_logs(drag_fleet)}
    held = sorted(tables)[-1]
    linear = [n for n in LINEAR if n != "rotor_drag"]
    spec = spec_from(VEHICLE, ["rotor_drag"])
    result = diagnosis.diagnose(_OnlyThese(tables, {held}), spec, [held], linear, stats=stats.get).to_dict()
    again = diagnosis.diagnose(tables, spec, [held], linear).to_dict()  # statistics computed from the rows
    assert result["verdict"] == again["verdict"]
    assert [r["effect"] for r in result["candidates"]] == [r["effect"] for r in again["candidates"]]
    for key in ("force_rmse_N", "torque_rmse_Nm"):
        assert result["baseline"][key] == pytest.approx(again["baseline"][key], rel=1e-9)



def test_a_hidden_lag_is_diagnosed_from_stored_profiles_and_the_rate_level(lagged_fleet, tmp_path):
    """The nonlinear candidates' torque-level folds, held-out tests and sensitivity come from the
    flights' stored profiles; their timing fit and comparison come from the angular-rate level
    (quadcore.identify.rates, docs/timing.md), which is not in the stored statistics: it reads each
    flight's rows once (a training flight's only then) and reduces them to the flight's rate-level
    sums, so no flight's rows are held when the next one's are read, nor after the diagnosis.
    Without a timing candidate, only the held-out flight's rows are read (its regime tables and
    spectra). The hidden lag is found at its value."""
    from quadcore.identify import diagnosis

    fds, stats = lagged_fleet
    for s in stats.values():
        sufficient.save(s, tmp_path)
    loaded = {f: sufficient.load(tmp_path, f) for f in stats}
    assert all(set(s.profiles.by_effect) == {"motor_lag", "thrust_delay"} for s in loaded.values())
    tables = {f: "rows" for f in fds}
    held = sorted(tables)[-1]
    spec = spec_from(VEHICLE, [])

    def diagnose(candidates: list[str]) -> tuple[dict, list[str], list[int]]:
        read: list[str] = []
        refs: list[weakref.ref] = []
        alive: list[int] = []  # at each read, and at the end: how many rows read before are alive

        def count() -> None:
            gc.collect()
            alive.append(sum(r() is not None for r in refs))

        def rows_of(f: str, decoded: object, veh: object) -> flightdata.FlightData:
            count()
            read.append(f)
            fd = copy.copy(fds[f])  # the diagnosis's own object (the fixture keeps its own)
            refs.append(weakref.ref(fd))
            return fd

        with pytest.MonkeyPatch.context() as m:
            m.setattr(flightdata, "flight_data", rows_of)
            result = diagnosis.diagnose(tables, spec, [held], candidates, stats=loaded.get).to_dict()
        count()
        return result, read, alive

    result, read, alive = diagnose(["motor_lag", "thrust_delay", "thrust_scale"])
    assert set(read) == set(fds)  # every flight's rows (the rate level) ...
    assert all(read.count(f) == 1 for f in fds if f != held)  # ... the training flights' once each
    assert not any(alive), alive  # ... and none held beside another's, nor after
    top = result["candidates"][0]
    assert top["effect"] == "motor_lag" and top["found"], result["verdict"]
    assert top["parameters"]["tau_s"] == pytest.approx(0.03, rel=0.15)
    assert result["sensitivity"]["motor_lag"]["tau_s"] is not None
    _, read, _ = diagnose(["thrust_scale", "rotor_drag"])
    assert set(read) == {held}


def test_stored_statistics_of_a_flight_decoded_again_from_other_bytes_are_stale(drag_fleet, tmp_path):
    """The statistics follow the decoded table they were made from: a flight re-decoded from
    another log (a replaced file under the same name) must not be fitted from its old
    statistics, even before the per-flight asset has run again."""
    from quadcore.physics import decoded_store
    from quadcore.store import store

    root = tmp_path / "root"
    spec = spec_from(VEHICLE, [])
    decoded_store.write_decoded(root, flight.decode_flight(drag_fleet / "sim000"))
    decoded = store.read_decoded(root, "fixedFrequency", "sim000")
    source = sufficient.decoded_source(root, "sim000")
    sufficient.save(sufficient.compute_current(spec, "sim000", decoded, source), root)
    assert sufficient.stored(root, spec)("sim000") is not None
    other = tmp_path / "raw" / "sim000"
    other.parent.mkdir()
    other.write_bytes((drag_fleet / "sim001").read_bytes())  # new bytes under the same flight id
    decoded_store.write_decoded(root, flight.decode_flight(other))
    assert sufficient.stored(root, spec)("sim000") is None


def test_a_log_decoded_again_by_another_decoder_is_decoded_again_and_what_was_kept_from_it_is_stale(
        drag_fleet, tmp_path, monkeypatch):
    """The decoder's code is part of what a decoded table and everything kept from it are made
    of: after a change of the decoder (its digest, :func:`quadcore.logs.flight.decoder_digest`)
    the same log's table is not current (the pipeline decodes it again), and once it is decoded
    again the statistics and discovery statistics made from the old table are stale (before,
    both were keyed by the log's SHA-256 alone: a new decoder's tables were never made, and its
    statistics were never recomputed)."""
    from quadcore.identify.discovery import library_stats
    from quadcore.physics import decoded_store
    from quadcore.store import store

    root, log = tmp_path / "root", drag_fleet / "sim000"
    spec = spec_from(VEHICLE, [])
    decoded_store.write_decoded(root, flight.decode_flight(log))
    decoded, source = store.read_decoded(root, "fixedFrequency", "sim000"), sufficient.decoded_source(root, "sim000")
    sufficient.save(sufficient.compute_current(spec, "sim000", decoded, source), root)
    library_stats.save(library_stats.compute(spec, "sim000", decoded, source), root)
    assert decoded_store.decoded_from(root, "fixedFrequency", "sim000", log)
    assert sufficient.stored(root, spec)("sim000") is not None
    assert library_stats.stored(root, spec)("sim000") is not None
    monkeypatch.setattr(flight, "decoder_digest", lambda: "another decoder")  # a release changed the decoder
    assert not decoded_store.decoded_from(root, "fixedFrequency", "sim000", log)  # to be decoded again
    decoded_store.write_decoded(root, flight.decode_flight(log))  # the same bytes, by the new decoder
    assert decoded_store.decoded_from(root, "fixedFrequency", "sim000", log)
    assert sufficient.stored(root, spec)("sim000") is None and library_stats.stored(root, spec)("sim000") is None


def test_the_decoder_digest_follows_the_decoders_code(tmp_path, monkeypatch):
    """The digest a decoded table records changes with the source of any module in
    :data:`quadcore.logs.flight.DECODER_MODULES` (a probe module standing for one of them)."""
    (tmp_path / "qc_probe_decoder.py").write_text("SCALE = 1.0\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(flight, "DECODER_MODULES", (*flight.DECODER_MODULES, "qc_probe_decoder"))
    flight.decoder_digest.cache_clear()
    before = flight.decoder_digest()
    (tmp_path / "qc_probe_decoder.py").write_text("SCALE = 2.0\n")  # the unit conversion changed
    flight.decoder_digest.cache_clear()  # a new process
    assert flight.decoder_digest() != before
    flight.decoder_digest.cache_clear()



def test_the_decoder_digest_follows_the_code_not_its_comments_docstrings_or_layout(tmp_path, monkeypatch):
    """An edit of a comment, a docstring or the layout of a module in
    :data:`quadcore.logs.flight.DECODER_MODULES` keeps every decoded table current (before, any
    byte of quadcore.logs.flight, the flight's assembly and its folder helpers alike, decoded every
    flight again); an edit of its code does not: on the decoder's own source, and through the
    digest of a probe module standing for one of them."""
    from quadcore.store import codedigest

    source = Path(flight.__file__).read_text()
    assert '"""A decoded flight' in source and "# The code a decoded table's rows" in source
    words = (source.replace('"""A decoded flight', '"""A flight decoded', 1)
             .replace("# The code a decoded table's rows", "# The code that makes a decoded table's rows", 1)
             .replace("\n\n\n", "\n\n\n\n", 1) + "\n# a last comment\n")
    code = source.replace('TRUTH_SUFFIX = ".truth.json"', 'TRUTH_SUFFIX = ".true.json"', 1)
    assert words != source and code != source
    assert codedigest.code_of(words.encode()) == codedigest.code_of(source.encode())
    assert codedigest.code_of(code.encode()) != codedigest.code_of(source.encode())

    probe = tmp_path / "qc_probe_decoder.py"
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(flight, "DECODER_MODULES", (*flight.DECODER_MODULES, "qc_probe_decoder"))

    def digest(text: str) -> str:
        probe.write_text(text)
        flight.decoder_digest.cache_clear()  # a new process
        return flight.decoder_digest()

    try:
        first = digest('"""Unit scale."""\n\n\ndef scale(x):\n    """Times one."""\n    return x * 1.0  # SI\n')
        assert digest('"""The unit\'s scale."""\n\n\ndef scale(x):\n    """x, as is."""\n\n    return x*1.0\n') == first
        assert digest('"""Unit scale."""\n\n\ndef scale(x):\n    """Times one."""\n    return x * 2.0  # SI\n') != first
    finally:
        flight.decoder_digest.cache_clear()

def _modules_that_run(work):
    """``work()``'s result and the quadcore modules whose functions it called (a profile hook)."""
    ran: set[str] = set()

    def seen(frame, event, arg):
        name = frame.f_globals.get("__name__", "")
        if event == "call" and name.startswith("quadcore"):
            ran.add(name)

    sys.setprofile(seen)
    try:
        out = work()
    finally:
        sys.setprofile(None)
    return out, ran


def test_the_code_that_decodes_a_log_is_in_the_decoder_digest(drag_fleet):
    """Every quadcore module whose functions run while a log is decoded into its tables is in
    :data:`quadcore.logs.flight.DECODER_MODULES`, or makes none of the table's numbers
    (``quadcore.store.names`` names the flight, ``quadcore.store.codedigest`` digests the decoder):
    a change to the decoding or the unit conversion makes every decoded table, and what was kept
    from it, stale."""
    decoded, ran = _modules_that_run(lambda: flight.decode_flight(drag_fleet / "sim000"))
    assert {"quadcore.logs.logformat", "quadcore.logs.units"} <= ran  # the work was traced
    assert not ran - {*flight.DECODER_MODULES, "quadcore.store.names", "quadcore.store.codedigest"}, sorted(ran)
    assert decoded.provenance.decoder == flight.decoder_digest()


def test_the_code_that_finds_a_decoded_tables_footer_facts_is_in_their_digest(drag_fleet):
    """Every quadcore module whose functions run while the physics facts of a decoded table (its
    footer's, quadcore.physics.decoded_store.write_decoded) are found is in gate.FACTS_MODULES:
    facts found by another gate are not used (gate.PhysicsFacts.from_dict)."""
    from quadcore.physics import gate

    table = flight.decode_flight(drag_fleet / "sim000").tables["fixedFrequency"]
    facts, ran = _modules_that_run(lambda: gate.physics_facts(table).to_dict())
    assert "quadcore.physics.gate" in ran and facts["code"] == gate.facts_digest()
    assert not ran - {*gate.FACTS_MODULES, "quadcore.store.codedigest"}, sorted(ran)


def test_the_statistics_key_follows_the_spec_not_the_plugins_this_process_loaded():
    """What a flight's stored statistics must hold is decided by the model spec alone: a plugin
    another code path registered in a long-lived process (the code server keeps every plugin it
    ever loaded, such as one a model file named before it was edited) must not change the key,
    or the statistics computed in a fresh run process would look outdated on every tick."""
    from pathlib import Path

    plugin = Path(__file__).resolve().parent / "plugins" / "hidden_terms.py"
    spec = spec_from(VEHICLE, [])
    before = sufficient.current_key(spec, "sim000")
    effects.load_plugin(plugin)
    try:
        assert sufficient.current_key(spec, "sim000") == before
        with_plugin = spec_from(VEHICLE, ["hidden_terms"])
        assert sufficient.current_key(with_plugin, "sim000") != before  # a model that uses it stores it
        assert "hidden_terms" in sufficient.spec_layout(with_plugin).effects
        assert "hidden_terms" not in sufficient.spec_layout(spec).effects
    finally:
        effects.unregister("hidden_terms")


def test_statistics_made_by_other_code_are_stale(tmp_path, monkeypatch):
    """The key names the code that makes the statistics (the state and nominal residual, the
    smoothing, the usable mask and noise floor, the blocks), not only the effects' classes: a
    change there makes every stored statistic stale instead of silently mixing old sums with
    new rows."""
    assert {"quadcore.physics.dynamics", "quadcore.physics.signals", "quadcore.identify.flightdata",
            "quadcore.identify.stats.sufficient"} <= set(sufficient.CODE_MODULES)
    (tmp_path / "qc_probe_code.py").write_text("SCALE = 1.0\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(sufficient, "CODE_MODULES", (*sufficient.CODE_MODULES, "qc_probe_code"))
    spec = spec_from(VEHICLE, [])
    sufficient.code_digest.cache_clear()
    before = sufficient.current_key(spec, "sim000")
    (tmp_path / "qc_probe_code.py").write_text("SCALE = 2.0\n")  # the code changed (a new release)
    sufficient.code_digest.cache_clear()  # a new process
    assert sufficient.current_key(spec, "sim000") != before
    sufficient.code_digest.cache_clear()


def test_a_cut_statistics_file_is_refused_when_read_not_midway_through_a_diagnosis(fleet, tmp_path):
    """A file cut short (a copy interrupted, a disk that filled) fails the check when it is read,
    so the caller recomputes the flight, instead of the per-block matrices (read lazily) raising
    in the middle of a held-out test."""
    _, stats = fleet
    s = stats[sorted(stats)[0]]
    path = sufficient.save(s, tmp_path)
    path.write_bytes(path.read_bytes()[:-100])
    with pytest.raises(sufficient.StatsError, match="not a statistics file"):
        sufficient.load(tmp_path, s.flight)
    assert sufficient.load_current(tmp_path, s.flight, s.key) is None


@pytest.mark.parametrize("name, shift", [("parasitic_drag", [-1e-3, 0.0]), ("added_mass", [-0.01])])
def test_a_fit_outside_its_bounds_is_refitted_with_the_bound_active(fleet, name, shift):
    """A target pushed so that one parameter's free fit leaves its physical range (a negative
    c_xy, a negative payload): the bounded fit holds it at the bound and fits the others to
    what is left, from rows and from statistics alike; for a drag, the others are the least
    squares of their own columns (the oracle, by hand)."""
    fds, stats = fleet
    ids, e = sorted(fds), effects.get(name)
    free = reference.fit_effects([e], [fds[f] for f in ids], flightdata.targets_of([fds[f] for f in ids]), VEHICLE)
    # the free fit is linear in the target: add the first column to move its first coordinate
    delta = shift[0] - e.to_linear(free.params[name], VEHICLE)[0]
    targets = flightdata.targets_of([fds[f] for f in ids])
    ys = [y + delta * fds[f].basis(e, VEHICLE)[:, :, 0] for f, y in zip(ids, targets)]
    rows = reference.fit_effects([e], [fds[f] for f in ids], ys, VEHICLE, bounded=True)
    first = e.parameters[0]
    assert rows.free is not None and rows.free.params[name][first.name] < first.lower
    assert rows.active == {name: {first.name: first.lower}}
    assert rows.params[name][first.name] == first.lower
    assert all(p.lower <= rows.params[name][p.name] <= p.upper for p in e.parameters)
    targets = [stats[f].layout.target() + delta * stats[f].layout.unit(stats[f].layout.cols(name)[0]) for f in ids]
    combined = fitlib.fit_effects([e], [stats[f] for f in ids], targets, VEHICLE, bounded=True)
    assert combined.active == rows.active
    _close(rows.params, combined.params, rel=1e-6)
    _close(rows.std, combined.std, rel=1e-6)
    if name == "parasitic_drag":  # c_z alone on what c_xy = 0 leaves
        w = rows.weights
        num = sum(float(np.einsum("nc,nc,c->", fds[f].basis(e, VEHICLE)[fds[f].mask, :, 1], y[fds[f].mask], w))
                  for f, y in zip(ids, ys))
        den = sum(float(np.einsum("nc,nc,c->", fds[f].basis(e, VEHICLE)[fds[f].mask, :, 1],
                                  fds[f].basis(e, VEHICLE)[fds[f].mask, :, 1], w)) for f in ids)
        assert rows.params[name]["c_z_kg_per_m"] == pytest.approx(num / den, rel=1e-9)


def test_a_fit_inside_its_bounds_is_the_free_fit(fleet):
    fds, stats = fleet
    ids, e = sorted(fds), effects.get("thrust_scale")
    free = reference.fit_effects([e], [fds[f] for f in ids], flightdata.targets_of([fds[f] for f in ids]), VEHICLE)
    for p in e.parameters:  # inside its bounds by far more than its noise (not by chance)
        value, std = free.params[e.name][p.name], free.std[e.name][p.name]
        assert p.lower + 10 * std < value < p.upper - 10 * std, (p.name, value, std)
    bounded = reference.fit_effects([e], [fds[f] for f in ids], flightdata.targets_of([fds[f] for f in ids]), VEHICLE,
                                  bounded=True)
    assert bounded.free is None and bounded.active == {}
    assert bounded.params == free.params and bounded.std == free.std


def test_a_models_profiled_prediction_as_a_column_equals_the_rows(lagged_fleet):
    """A model's one-parameter nonlinear effect predicts as an extra column of the flight's
    statistics, from its profile (profiles.with_predictions): on a grid point, its sums with every
    column, and the other profiled effects' sums against it (a thrust_delay candidate fitted to a
    residual that holds the model's motor_lag), equal those of the column made from the rows."""
    from quadcore.identify.flightdata import prediction
    from quadcore.identify.stats import profiles

    fds, stats = lagged_fleet
    f = sorted(fds)[0]
    lag = effects.get("motor_lag")
    (p,) = lag.parameters
    tau = float(profiles.profile_grid(p.lower, p.upper)[12])
    grown = profiles.with_predictions(stats[f], {"motor_lag": tau})
    extra = {"pred:motor_lag": prediction(lag, {p.name: tau}, fds[f], VEHICLE)}
    rows = sufficient.flight_stats(fds[f], VEHICLE, stats[f].layout.with_extras(list(extra)), extras=extra)
    assert grown.layout == rows.layout
    scale = np.abs(rows.total).max()
    np.testing.assert_allclose(grown.total, rows.total, rtol=1e-9, atol=1e-12 * scale)
    assert grown.profiles is not None and set(grown.profiles.by_effect) == {"thrust_delay"}
    want = rows.profiles.by_effect["thrust_delay"].total
    np.testing.assert_allclose(grown.profiles.by_effect["thrust_delay"].total, want, rtol=1e-9,
                               atol=1e-12 * np.abs(want).max())
    # the strided sums hold the strided cross in float32
    want = rows.profiles.by_effect["thrust_delay"].strided
    np.testing.assert_allclose(grown.profiles.by_effect["thrust_delay"].strided, want, rtol=1e-5,
                               atol=1e-6 * np.abs(want).max())


def _diagnose_counting_rows(monkeypatch_target, fds, tables, spec, held, candidates, stored):
    """A diagnosis whose flights' rows are the given FlightData, and the flights whose rows it read."""
    from quadcore.identify import diagnosis

    read: list[str] = []

    def rows_of(f: str, decoded: object, veh: object) -> flightdata.FlightData:
        read.append(f)
        return fds[f]

    with pytest.MonkeyPatch.context() as m:
        m.setattr(flightdata, "flight_data", rows_of)
        if monkeypatch_target is not None:
            monkeypatch_target(m)
        result = diagnosis.diagnose(tables, spec, [held], candidates, stats=stored).to_dict()
    return result, read


@pytest.mark.parametrize("per_session", [[], ["thrust_scale"]])
def test_a_model_with_a_lag_is_diagnosed_from_statistics_without_the_training_flights_rows(lagged_fleet, tmp_path,
                                                                                             per_session):
    """The committed real model's kind (linear effects and motor_lag): its fit in the fold, its
    residual, the candidates' fits, held-out tests, sensitivity and disagreements come from the
    flights' stored statistics and profiles, the model's lag as an extra column; only the held-out
    flight's rows are read (its residual's summary: regime tables and spectra), without a timing
    candidate (the rate level reads every flight's: docs/timing.md). The model is the one fit_model
    fits; with a per-session thrust scale beside the lag (the committed real model's kind) too."""
    fds, stats = lagged_fleet
    for s in stats.values():
        sufficient.save(s, tmp_path)
    loaded = {f: sufficient.load(tmp_path, f) for f in stats}
    tables = {f: "rows" for f in fds}
    held = sorted(tables)[-1]
    spec = spec_from(VEHICLE, ["thrust_scale", "motor_lag"])
    spec.per_session = per_session

    # the tables come from summaries: the row tables are no longer in quadcore (tests/reference/tables.py)
    result, read = _diagnose_counting_rows(None, fds, tables, spec, held, ["rotor_drag", "com_offset"], loaded.get)
    assert set(read) == {held}
    assert [r["flight"] for r in result["flights"]] == [held] and result["regimes"] and result["worst_segments"]
    train = [f for f in sorted(fds) if f != held]
    fitted = model_fit.fit_model(spec, {f: None for f in train}, train, stats=loaded.get)
    got = {e["name"]: e["params"] for e in result["model"]["effects"]}
    _close({t.name: t.params for t in fitted.terms}, got, rel=1e-12)
    assert got["motor_lag"]["tau_s"] == pytest.approx(0.03, rel=0.15)


def _model_on_rows(m: pytest.MonkeyPatch) -> None:
    """The diagnosis's model fitted as one with a nonlinear effect per session is (on the rows: the
    row search, fit.fit_rows) and predicting on the rows (its prediction a column of the statistics)."""
    from quadcore.identify.diagnosis import problem

    m.setattr(problem.model_fit, "from_statistics", lambda *a: False)
    m.setattr(problem, "_fit_model", lambda p, train, sessions, log: problem._model_on_rows(p, train, sessions, log))


def test_a_model_with_a_lag_diagnosed_from_statistics_agrees_with_its_rows(lagged_fleet):
    """The same diagnosis with the model fitted on rows (the reference: the row search of the lag,
    its prediction made on the rows, what a model the statistics cannot express still takes) and from
    statistics (the lag from its profile, interpolated between grid points). Measured on these
    flights: the lag 1.9e-6 s apart (1 % of its σ), its σ 0.15 %, the held-out residual's RMS
    1.2e-4 relative, the candidates' scores 3e-4 (a delay's row objective ripples with the sample
    period: its trough against the smooth curve's minimum, profiles' docstring). Tolerances: the
    row search's own (xatol, 5e-4 of the span) for the lag, 4 % for its σ (the profile interval's,
    benchmarks/bench_profiles.py), 1e-3 for the RMS and for a score (a fiftieth of min_explained)."""
    fds, stats = lagged_fleet
    tables = {f: "rows" for f in fds}
    held = sorted(tables)[-1]
    spec = spec_from(VEHICLE, ["thrust_scale", "motor_lag"])
    cands = ["rotor_drag", "com_offset", "thrust_delay"]
    got, _ = _diagnose_counting_rows(None, fds, tables, spec, held, cands, stats.get)
    ref, _ = _diagnose_counting_rows(_model_on_rows, fds, tables, spec, held, cands, stats.get)
    lag, lag_ref = ({d["name"]: d for d in r["model"]["effects"]}["motor_lag"] for r in (got, ref))
    span = effects.get("motor_lag").parameters[0].upper - effects.get("motor_lag").parameters[0].lower
    assert abs(lag["params"]["tau_s"] - lag_ref["params"]["tau_s"]) <= 5e-4 * span
    assert lag["std"]["tau_s"] == pytest.approx(lag_ref["std"]["tau_s"], rel=0.04)
    for k in ("force_rmse_N", "torque_rmse_Nm"):
        np.testing.assert_allclose(got["baseline"][k], ref["baseline"][k], rtol=1e-3)
    scores = {r["effect"]: r["score"] for r in ref["candidates"]}
    for r in got["candidates"]:
        assert r["score"] == pytest.approx(scores[r["effect"]], abs=1e-3), r["effect"]
    assert {r["effect"] for r in got["candidates"] if r["found"]} == {r["effect"] for r in ref["candidates"]
                                                                      if r["found"]}
    assert got["verdict"].split(". ")[0] == ref["verdict"].split(". ")[0]


def test_a_per_session_model_beside_a_lag_is_fitted_from_statistics_as_the_rows_fit_it(lagged_fleet):
    """The committed real model's kind (a per-session thrust scale beside a shared motor_lag):
    fit_model fits it from statistics (the lag fixed at its shared value in the per-session fits is
    its column at that value), no table read, as the rows fit it: the lag within the row search's
    own tolerance (xatol, 5e-4 of the span), every value within a tenth of its standard error."""
    fds, stats = lagged_fleet
    ids = sorted(fds)
    spec = spec_from(VEHICLE, ["thrust_scale", "motor_lag"])
    spec.per_session = ["thrust_scale"]
    groups = {"a": ids[:2], "b": ids[2:]}
    assert model_fit.from_statistics(spec, [effects.get(n) for n in spec.effects])
    targets = dict(zip(ids, flightdata.targets_of([fds[f] for f in ids])))
    rows = sessions.fit_per_session(spec, fds, targets, ids, groups, fit=reference.fit_effects)
    got = model_fit.fit_model(spec, {f: None for f in ids}, ids, groups, stats=stats.get)
    span = effects.get("motor_lag").parameters[0].upper
    lag, lag_rows = (next(t for t in m.terms if t.name == "motor_lag") for m in (got, rows))
    assert abs(lag.params["tau_s"] - lag_rows.params["tau_s"]) <= 5e-4 * span
    for a, b in zip(rows.terms, got.terms):
        for k, v in a.params.items():
            assert abs(b.params[k] - v) <= 0.1 * a.std[k], f"{a.name}.{k}"
        for s in a.per_session:
            for k, v in a.per_session[s].items():
                assert abs(b.per_session[s][k] - v) <= 0.1 * a.per_session_std[s][k], f"{a.name}.{k}[{s}]"


_PLUGIN = '''from quadcore.effects.base import Effect, Parameter, rotor_wrench


def share(x):
    return {factor} * x


class Scaled(Effect):
    name = "{name}"
    target = "both"
    parameters = (Parameter("k", "", 0.0, 0.0, 1.0, "a share of the rotors' thrust"),)

    def wrench(self, state, vehicle, params):
        return rotor_wrench(vehicle, share(params["k"]) * state.f_rotor_N)


EFFECT = Scaled()
'''


def test_an_effects_source_digest_follows_its_modules_code_not_only_its_class(tmp_path, monkeypatch):
    """What keys the statistics kept under a data root (and the rate level's sums) changes when
    the code an effect's wrench runs changes: a module-level function its class calls (as
    motor_lag's wrench calls first_order_lag), and a plugin's file edited between two loads. Before,
    the digest was the class's source alone (the same text here), and every plugin's 'unknown'
    (its module is in no sys.modules), so kept statistics of the old code stayed current. A
    comment or docstring edited in the module keeps it (quadcore.store.codedigest.code_of)."""
    monkeypatch.syspath_prepend(str(tmp_path))
    digests = []
    comment = '"""An edited docstring."""\n# and a comment\n'
    for i, (factor, words) in enumerate((("1.0", ""), ("2.0", ""), ("1.0", comment))):  # the same class, another helper
        (tmp_path / f"digest_mod_{i}.py").write_text(words + _PLUGIN.format(factor=factor, name="digest"))
        try:
            digests.append(sufficient.source_digest(type(importlib.import_module(f"digest_mod_{i}").EFFECT)))
        finally:
            sys.modules.pop(f"digest_mod_{i}", None)
    assert digests[0] != digests[1] and "unknown" not in digests
    assert digests[2] == digests[0]  # the words changed, not the code
    plugin = tmp_path / "edited_plugin.py"
    plugins = []
    for factor in ("1.0", "2.0"):  # one plugin file, edited between two loads
        plugin.write_text(_PLUGIN.format(factor=factor, name="edited"))
        plugins.append(sufficient.source_digest(type(effects.load_plugin(plugin))))
        effects.unregister("edited")
    assert plugins[0] != plugins[1] and "unknown" not in plugins


# What runs while a flight's statistics and its rate-level sums are made, and is in no code digest
# on purpose: each effect's own module (its source digest, sufficient.source_digest, is in the keys
# of the effects they hold), the effect registry, the physics gate's checks (they refuse a flight
# or pass it: nothing they compute is kept), and the model and spec that resolve a flight's
# vehicle and effect values (those values are in the keys, not the code that looked them up), and
# the digest itself (quadcore.store.codedigest: it reads the modules' source, it makes no number).
_OUTSIDE_THE_DIGEST = ("quadcore.effects", "quadcore.physics.gate", "quadcore.logs.checks", "quadcore.identify.model",
                       "quadcore.spec.model", "quadcore.store.codedigest")


def test_the_code_that_makes_a_flights_statistics_and_rate_sums_is_in_their_code_digest(drag_fleet):
    """Every quadcore module whose functions run while a flight's statistics (stats.bin, its
    summary) and rate-level sums (rates.bin) are made is in the digest of code their keys carry
    (sufficient.CODE_MODULES, rate_cache.CODE_MODULES), or is one of those outside it on purpose
    (_OUTSIDE_THE_DIGEST): code that changes kept numbers makes them stale. Before,
    quadcore.physics.vehicle (the rotors' thrust from the thrust map, the allocation, the thrust
    hold) was in neither: a change to the thrust map's formula left every kept file current."""
    from quadcore.identify.diagnosis import rate_cache
    from quadcore.identify.model import PhysicsModel

    path = sorted(flight.discover_logs(drag_fleet))[0]
    table = flight.decode_flight(path).tables["fixedFrequency"]
    spec = spec_from(VEHICLE, ["rotor_drag", "motor_lag"])
    timing = [effects.get("motor_lag"), effects.get("thrust_delay")]
    model = PhysicsModel(spec.vehicle, [])

    def make() -> None:
        sufficient.compute_current(spec, path.name, table)
        fd = flightdata.flight_data(path.name, table, spec.vehicle_for(path.name))
        rates.flight_sums(fd, model, path.name, timing, evidence.memory_blocks(timing))

    _, ran = _modules_that_run(make)
    digested = {*sufficient.CODE_MODULES, *rate_cache.CODE_MODULES}
    outside = {m for m in ran - digested if not any(m == o or m.startswith(o + ".") for o in _OUTSIDE_THE_DIGEST)}
    assert {"quadcore.identify.rates.sums", "quadcore.identify.flightdata"} <= ran  # the work was traced
    assert not outside, sorted(outside)
