"""The rate level's per-flight sums kept under the data root (quadcore.identify.diagnosis.rate_cache):
a diagnosis with them equals one without, a kept flight's rows are not read again, and a kept file
that no longer describes the flight (another log, another model, another format, cut short, not
one) is computed again, never read."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from snapshot import json_differences

from quadcore import effects
from quadcore.identify import binfile, diagnosis, rates
from quadcore.identify.diagnosis import rate_cache
from quadcore.identify.fit import solve
from quadcore.logs import flight
from quadcore.physics import decoded_store
from quadcore.physics.vehicle import load as load_vehicle
from quadcore.spec.model import spec_from
from quadcore.store import store

VEHICLE = load_vehicle("crazyflie21")
CANDIDATES = ["rotor_drag", "motor_lag", "thrust_delay"]  # two timing candidates: the rate level runs


@pytest.fixture
def root(drag_fleet, tmp_path):
    """The shared fleet decoded under a data root of its own (the decoded tables record their log's digest)."""
    for path in flight.discover_logs(drag_fleet):
        decoded_store.write_decoded(tmp_path, flight.decode_flight(path))
    return tmp_path


def _tables(root) -> dict:
    return {f: store.read_decoded(root, store.MAIN_EVENT, f) for f in ("sim000", "sim001", "sim002", "sim003")}


def _diagnose(root, tables, spec=None, cache=True) -> dict:
    return diagnosis.diagnose(tables, spec or spec_from(VEHICLE, []), None, CANDIDATES,
                              rate_cache=rate_cache.stored(root) if cache else None).to_dict()


@pytest.fixture
def computed(monkeypatch) -> list[int]:
    """How many flights' rate-level sums were computed from their rows (one entry per flight)."""
    calls: list[int] = []
    made = rates.sums.rate_sums

    def counting(*args, **kwargs):
        calls.append(1)
        return made(*args, **kwargs)

    monkeypatch.setattr(rates.sums, "rate_sums", counting)  # where flight_sums looks it up
    return calls


def test_kept_sums_give_the_diagnosis_without_them_and_read_no_rows_again(root, computed):
    tables = _tables(root)
    without = _diagnose(root, tables, cache=False)
    assert len(computed) == 4 and not list(root.glob("stats/*/rates.bin"))
    first = _diagnose(root, tables)  # computed and kept
    assert len(computed) == 8 and len(list(root.glob("stats/*/rates.bin"))) == 4
    again = _diagnose(root, tables)  # read back: no flight's sums computed
    assert len(computed) == 8
    timing = [c for c in again["candidates"] if c["effect"] in ("motor_lag", "thrust_delay")]
    assert len(timing) == 2 and all(any("angular-rate level" in n for n in c["notes"]) for c in timing)
    assert json_differences(first, without) == [] and json_differences(again, without) == []


def test_a_flight_decoded_from_other_bytes_is_computed_again_and_only_it(root, drag_fleet, computed):
    tables = _tables(root)
    _diagnose(root, tables)
    # sim000 decoded again from another log's bytes: its kept sums are of the old log
    other = flight.decode_flight(next(p for p in flight.discover_logs(drag_fleet) if p.name == "sim001"), "sim000")
    decoded_store.write_decoded(root, other)
    tables = _tables(root)
    computed.clear()
    refreshed = _diagnose(root, tables)
    assert len(computed) == 1
    assert json_differences(refreshed, _diagnose(root, tables, cache=False)) == []


def test_a_flight_decoded_again_by_another_decoder_is_computed_again_and_only_it(root, drag_fleet, computed,
                                                                                 monkeypatch):
    """The same log decoded by another decoder (a release that changed the decoding or the unit
    conversion: its digest, quadcore.logs.flight.decoder_digest, in the decoded table's provenance):
    the sums kept from the old table are stale (before, they were keyed by the log's SHA-256 alone)."""
    tables = _tables(root)
    _diagnose(root, tables)
    monkeypatch.setattr(flight, "decoder_digest", lambda: "another decoder")
    decoded_store.write_decoded(root, flight.decode_flight(drag_fleet / "sim002"))
    computed.clear()
    refreshed = _diagnose(root, _tables(root))
    assert len(computed) == 1
    assert json_differences(refreshed, _diagnose(root, tables, cache=False)) == []


def test_another_model_computes_every_flight_again(root, computed):
    tables = _tables(root)
    _diagnose(root, tables)
    computed.clear()
    spec = spec_from(VEHICLE, ["rotor_drag"])
    cands = [c for c in CANDIDATES if c != "rotor_drag"]
    with_model = diagnosis.diagnose(tables, spec, None, cands, rate_cache=rate_cache.stored(root)).to_dict()
    assert len(computed) == 4  # another set of effects in the model: another key
    assert json_differences(with_model, diagnosis.diagnose(tables, spec, None, cands).to_dict()) == []


def test_a_refit_that_moves_the_models_linear_effects_reads_every_kept_flight_back(root, computed):
    """A model whose linear effect has a torque (com_offset): its values are not in the kept sums
    (their columns, RateSums.model, are taken out at the diagnosis's values), so a refit that moves
    them (here: the fit on three of the four flights) reads every flight's sums back, with the
    diagnosis the same as without them (before: every flight computed again)."""
    spec = spec_from(VEHICLE, ["com_offset"])
    cands = [c for c in CANDIDATES if c != "com_offset"]
    tables = _tables(root)
    diagnosis.diagnose(tables, spec, None, cands, rate_cache=rate_cache.stored(root))
    assert len(computed) == 4
    fewer = {f: t for f, t in tables.items() if f != "sim003"}  # another fit: com_offset's values move
    computed.clear()
    kept = diagnosis.diagnose(fewer, spec, None, cands, rate_cache=rate_cache.stored(root)).to_dict()
    assert len(computed) == 0
    assert json_differences(kept, diagnosis.diagnose(fewer, spec, None, cands).to_dict()) == []


def test_the_linear_effects_columns_give_the_sums_of_their_torque_taken_out_of_the_increments(root):
    """The model's linear effects as columns taken out at their values (rates.flight_sums) equal the
    sums with their torque taken out of the increments first (rates.rate_flight's, as before),
    within the float32 rounding of the running sums: R = R⁰ − Σ c_j T_j, and the whitening and the
    demeaning are linear."""
    from quadcore.identify import flightdata
    from quadcore.identify.model import EffectTerm, PhysicsModel

    e = effects.get("com_offset")
    model = PhysicsModel(VEHICLE, [EffectTerm("com_offset", e.from_linear([2e-3, -1e-3, 0.0][:len(e.parameters)],
                                                                           VEHICLE))])
    timing = [effects.get("motor_lag"), effects.get("thrust_delay")]
    fd = flightdata.flight_data("sim001", _tables(root)["sim001"], VEHICLE)
    columns = rates.flight_sums(fd, model, "sim001", timing, 1)
    assert columns.model and np.any(columns.at)
    tau = e.wrench(fd.state, VEHICLE, model.terms[0].params)[1]
    folded = rates.rate_sums(rates.rate_flight(fd, VEHICLE, tau, 1), timing)
    assert not folded.model
    for cand in timing:
        for value in (0.0, 0.004):
            np.testing.assert_allclose(columns.costs(cand, value), folded.costs(cand, value), rtol=1e-5)
            assert columns.cost(cand, value, np.ones(3)) == pytest.approx(folded.cost(cand, value, np.ones(3)),
                                                                          rel=1e-6)


def test_a_kept_file_that_cannot_serve_is_computed_again_not_read(root, computed):
    tables = _tables(root)
    without = _diagnose(root, tables, cache=False)
    _diagnose(root, tables)
    path = rate_cache.path(root, "sim002")
    for damage in ("cut", "garbage", "other_format", "other_key"):
        raw = path.read_bytes()
        if damage == "cut":
            path.write_bytes(raw[: len(raw) // 2])
        elif damage == "garbage":
            path.write_bytes(b"not a rate-level file")
        else:
            header, array = binfile.decode(raw)
            arrays = {n: array(n) for n in header["arrays"]}
            del header["arrays"]
            header.update({"format": rate_cache.FORMAT + 1} if damage == "other_format" else {"key": "another-key"})
            binfile.write_file(path, header, arrays)
        computed.clear()
        assert json_differences(_diagnose(root, tables), without) == [], damage
        assert len(computed) == 1, damage  # that flight's, and the file replaced by a good one
        assert rate_cache.load(root, "sim002", binfile.decode(path.read_bytes())[0]["key"]) is not None


def test_sums_read_back_equal_the_ones_written(root, tmp_path):
    tables = _tables(root)
    sums: dict[str, rates.FlightRates] = {}

    def keep(f, inputs, compute):
        sums[f] = compute()
        return sums[f]

    diagnosis.diagnose(tables, spec_from(VEHICLE, []), None, CANDIDATES, rate_cache=keep)
    s = sums["sim001"]
    assert isinstance(s, rates.RateSums)
    rate_cache.save(tmp_path, "sim001", "k", s)
    back = rate_cache.load(tmp_path, "sim001", "k")
    assert isinstance(back, rates.RateSums)
    assert back.slots == s.slots and (back.samples, back.n) == (s.samples, s.n) and back.dt_s == pytest.approx(s.dt_s)
    for name in s.grids:
        np.testing.assert_allclose(back.grids[name], s.grids[name], rtol=1e-15)
    assert back.unwhitened is not None and s.unwhitened is not None
    assert (back.unwhitened_blocks is None) == (s.unwhitened_blocks is None)
    assert (back.lagged_blocks is None) == (s.lagged_blocks is None)
    for a, b in ((back.blocks, s.blocks), (back.total, s.total), (back.noise, s.noise),
                 (back.unwhitened, s.unwhitened), *(((back.unwhitened_blocks, s.unwhitened_blocks),)
                                                    if s.unwhitened_blocks is not None else ()),
                 *(((back.lagged_blocks, s.lagged_blocks),) if s.lagged_blocks is not None else ())):
        assert a.dtype == b.dtype
        np.testing.assert_allclose(a, b, rtol=1e-15)
    assert rate_cache.load(tmp_path, "sim001", "another") is None
    # a flight with a whitening filter also keeps its blocks without it and its lagged blocks (this fleet's
    # white noise takes none: written here as a filtered flight's would be)
    k = 1 + sum(len(g) for g in s.grids.values())
    lagged = np.linspace(-1.0, 1.0, len(s.blocks) * 3 * k * k, dtype=np.float32).reshape(len(s.blocks), 3, k, k)
    filtered = replace(s, unwhitened_blocks=2 * s.blocks, lagged_blocks=lagged)
    rate_cache.save(tmp_path, "sim001", "f", filtered)
    back = rate_cache.load(tmp_path, "sim001", "f")
    assert isinstance(back, rates.RateSums) and back.unwhitened_blocks is not None and back.lagged_blocks is not None
    assert back.lagged_blocks.dtype == np.float32 and np.array_equal(back.lagged_blocks, lagged)
    assert np.array_equal(back.unwhitened_blocks, filtered.unwhitened_blocks)
    slow = rates.BelowCommandRate(0.01, 0.002)
    rate_cache.save(tmp_path, "slow", "k", slow)
    assert rate_cache.load(tmp_path, "slow", "k") == slow


def _synthetic_sums(rng: np.random.Generator, dt_s: float, timing: list) -> rates.RateSums:
    """A flight's rate-level sums from random block-demeaned running sums on ``timing``'s grids at
    the sample period ``dt_s`` (each block's Gram a real one: the costs are sums of squares)."""
    grids = {e.name: rates.rate_grid(e, dt_s) for e in timing}
    slots, k = {}, 1
    for e in timing:
        slots[e.name] = slice(k, k + len(grids[e.name]))
        k += len(grids[e.name])
    i, j = np.triu_indices(k)
    blocks = []
    for _ in range(4):
        x = rng.standard_normal((50, 3, k))
        x[:, :, 1:] += x[:, :, :1]  # the candidates' running sums near the residual's, as a fit finds them
        blocks.append(np.einsum("kai,kaj->aij", x, x)[:, i, j])
    b = np.asarray(blocks)
    return rates.RateSums(grids, slots, b.astype(np.float32), b.sum(axis=0), np.ones(3), 200, dt_s, 200)


def test_a_rate_level_fit_pools_the_flights_of_one_grid_as_their_sum_of_costs():
    """rates.fit sums the flights' weighted totals once per grid: the same fit as the sum of each
    flight's own cost (RateSums.cost), with flights at two sample rates (two grids of the delay)."""
    rng = np.random.default_rng(7)
    timing = [effects.get("motor_lag"), effects.get("thrust_delay")]
    flights = [_synthetic_sums(rng, dt, timing) for dt in (0.002, 0.004, 0.002, 0.004, 0.002)]
    assert len({len(s.grids["thrust_delay"]) for s in flights}) == 2
    w = np.array([1.0, 2.0, 0.5])
    for effect in timing:
        (p,) = effect.parameters
        got = rates.fit(effect, flights, w)
        n = sum(s.n for s in flights) * 3

        def cost(v: float, effect=effect, p=p) -> float:
            return sum(s.cost(effect, float(min(max(v, p.lower), p.upper)), w) for s in flights)

        if effect.linear_between_samples:  # a delay: every piece between the grids' whole sample periods
            knots = np.unique(np.concatenate([s.grids[effect.name] for s in flights]))
            best = rates.piecewise_quadratic_minimum(cost, knots, n)[0]
        else:
            best, _ = solve.scalar_minimum(cost, n, p.lower, p.upper, samples_per_independent=1)
        assert got.value == pytest.approx(best, rel=1e-9, abs=1e-12 * (p.upper - p.lower))
        assert got.cost == pytest.approx(cost(got.value), rel=1e-9)


def test_the_key_follows_the_code_that_makes_the_sums(tmp_path, monkeypatch):
    """A change to a module the sums are made by (a probe standing for one of rate_cache.CODE_MODULES)
    changes the key (a new process), so the kept sums are made again."""
    (tmp_path / "qc_probe_rates.py").write_text("SCALE = 1.0\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(rate_cache, "CODE_MODULES", (*rate_cache.CODE_MODULES, "qc_probe_rates"))
    inputs = {"timing": ["motor_lag"], "terms": []}
    rate_cache.code_digest.cache_clear()
    before = rate_cache.key("log", inputs)
    (tmp_path / "qc_probe_rates.py").write_text("SCALE = 2.0\n")
    rate_cache.code_digest.cache_clear()  # a new process
    assert rate_cache.key("log", inputs) != before
    rate_cache.code_digest.cache_clear()
