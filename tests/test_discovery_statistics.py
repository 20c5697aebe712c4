"""Discovery scores from its flights' statistics on every path: the held-out RMSE before and after the
kept terms, a quadratic form of the Gram matrices on every usable sample, is the rows' own sum of
squares (tests/reference/discovery.py) on drag_fleet (rotor drag hidden), under no model, a linear one
and a nonlinear one (whose residual is predicted on the rows before they become statistics); with a
linear model also from the statistics of the nominal residual with the model's fit subtracted."""

from __future__ import annotations

import numpy as np
import pytest
from reference import discovery as reference

from quadcore import effects as effectlib
from quadcore.identify import evidence
from quadcore.identify.discovery import accumulate, library_stats, select
from quadcore.identify.fit import solve
from quadcore.identify.settings import DEFAULT
from quadcore.logs import flight
from quadcore.physics import vehicle
from quadcore.spec.model import spec_from


@pytest.fixture(scope="module")
def tables(drag_fleet) -> dict:
    return {flight.flight_id_of(p): flight.decode_flight(p).tables["fixedFrequency"]
            for p in flight.discover_logs(drag_fleet)}


@pytest.mark.parametrize(("effects", "holdout"), [([], ["sim003"]), (["thrust_scale"], []),
                                                  (["motor_lag"], ["sim003"])])
def test_the_held_out_rmse_from_statistics_is_the_rows_sum_of_squares(tables, effects, holdout):
    spec = spec_from(vehicle.load(), effects)
    ids = sorted(tables)
    train = [f for f in ids if f not in holdout]
    folds = solve.folds(train, DEFAULT.n_folds)
    skip = evidence.scored_after_blocks(spec)
    rows = accumulate.residual_rows(spec, tables, ids, train, None, lambda msg: None)
    fx = library_stats.fx_effects(spec)
    lib = accumulate.from_rows(ids, rows, tables, spec, fx, folds, holdout, library_stats.STRIDE, skip,
                               lambda msg: None)
    noise = select._noise_floor([lib.samples[f] for f in train], [lib.noise_of[f] for f in train])
    _, _, coefs = select._discover_axes(lib, noise, bool(holdout), spec.effects, fx, DEFAULT)
    assert any(chosen for chosen, _ in coefs.values()), "terms are kept: an RMSE after them is compared"
    eval_ids = holdout or ids
    fold_grams, G_train = lib.sums.fold_grams(), lib.sums.training_total()
    train_gram = {f: G_train for f in eval_ids} if holdout else {
        f: fold_grams[i][0] for i, fold in enumerate(folds) for f in fold}
    want_base, want_after = reference.held_out_rmse(lambda f: rows(f, quiet=True), eval_ids, train_gram, lib.cols,
                                                    lib.terms, coefs, spec.vehicle, skip)
    libs = [lib]
    if all(effectlib.get(n).linear for n in spec.effects):  # the path of stored statistics, here computed
        libs.append(accumulate.from_statistics(ids, tables, spec, fx, folds, holdout, train, lambda f: None, None,
                                               None, lambda msg: None))
    for one in libs:
        base, after = select._held_out_errors(one, coefs, holdout, eval_ids, skip)
        for got, want in ((base, want_base), (after, want_after)):
            np.testing.assert_allclose(got["force_rmse_N"] + got["torque_rmse_Nm"], want, rtol=1e-9)
    kept = [axis for axis, (chosen, _) in coefs.items() if chosen]
    assert np.all(want_after[kept] < want_base[kept])  # what is scored is the kept terms' gain
