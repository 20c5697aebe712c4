"""Term discovery: sparse regression of the residual on the candidate library
(:mod:`quadcore.identify.discovery.terms`), cross-validated over flights, from the flights' Gram
sums (:mod:`quadcore.identify.discovery.accumulate`).

Starting point: the residual the current model leaves (its effects fitted on the training
flights), force and torque in the body frame (:mod:`quadcore.physics.residuals`).

**Selection** per residual axis, from Gram matrices accumulated flight by flight (every
``stride``-th usable sample): orthogonal matching pursuit (``sklearn.linear_model.
orthogonal_mp_gram``, the greedy member of the LARS family) on each fold of a
cross-validation grouped by flight, scored on the fold's flights. The number of terms is
where one more term adds less than ``min_gain`` of the held-out variance. A term is kept
when it is selected in most folds (stability selection) and, refitted with the other kept
terms, still adds ``min_gain`` of the held-out variance. **Competing forms**: the forms of a
velocity term (``v``, ``T v``, ``v|v|``, ``|v_b| v``: :data:`quadcore.identify.discovery.terms.VELOCITY_FORMS`)
share one slot's votes in the stability selection, and the slot keeps the form with the best mean rank of
held-out error over the folds, beside the other kept terms (:func:`_prefer_forms`; chosen on the
folds, never on a holdout); every rival is reported with its held-out share, and the mechanism
is named only when the kept form beats each rival in most folds (else "form undecided").
An axis whose residual is within
``noise_margin`` (RMS) of the sensor-noise floor gets no terms, the same
margin the diagnosis uses.

**Reported** per term: the formula with its SI coefficient and grouped-jackknife standard
error, the held-out variance it explains (in the order of selection, so the shares add up),
its stability, the library effects whose basis it matches, the mechanism's name in the
literature where there is one, and the candidates it is collinear with (which the data
cannot separate from it). When the kept terms of an axis rebuild a multiple of its own modelled
force or torque, the axis' result says so.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Mapping

import numpy as np
import polars as pl
from sklearn.linear_model import orthogonal_mp_gram

from quadcore import effects as effectlib
from quadcore.effects.base import Effect
from quadcore.identify.discovery import accumulate, library_stats
from quadcore.identify.discovery.accumulate import LibrarySums
from quadcore.identify.discovery.grams import Columns
from quadcore.identify.discovery.results import AxisResult, DiscoveredTerm, Discovery, Form
from quadcore.identify.discovery.terms import (
    TARGETS,
    UNIT,
    Term,
    excluded,
    form_family,
    literature,
    mul_units,
    unit_text,
)
from quadcore.identify.evidence import scored_after_blocks
from quadcore.identify.fit import solve
from quadcore.identify.settings import DEFAULT, DiagnosisSettings
from quadcore.identify.stats import sufficient
from quadcore.spec.model import ModelSpec

MIN_STABILITY = 0.6  # selected in at least this share of the folds ("most folds")
MAX_TERMS = 8  # per axis
COLLINEAR = 0.95  # |cosine| between two terms above which the data cannot separate them
MATCH = 0.9  # share of a term's energy in an effect's basis above which the term "is" that effect


def _sse(G: np.ndarray, cols: list[int], y: int, beta: np.ndarray) -> float:
    """Residual sum of squares of ``y - X[:, cols] beta`` from a Gram matrix."""
    if not cols:
        return float(G[y, y])
    return float(G[y, y] - 2 * beta @ G[cols, y] + beta @ G[np.ix_(cols, cols)] @ beta)


def _ols(G: np.ndarray, cols: list[int], y: int) -> np.ndarray:
    if not cols:
        return np.zeros(0)
    return np.linalg.lstsq(G[np.ix_(cols, cols)], G[cols, y], rcond=1e-12)[0]


def _omp_path(G: np.ndarray, cols: list[int], y: int, n_max: int) -> list[list[int]]:
    """Supports of the greedy path (1, 2, ... terms), columns normalised for the selection."""
    sub = G[np.ix_(cols, cols)]
    d = np.sqrt(np.maximum(np.diag(sub), 1e-300))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "ended prematurely": fewer independent columns than asked
        path = orthogonal_mp_gram(sub / np.outer(d, d), G[cols, y] / d, n_nonzero_coefs=n_max, return_path=True)
    path = path.reshape(len(cols), -1)
    supports, seen = [], []
    for s in range(path.shape[1]):
        new = [cols[i] for i in np.flatnonzero(path[:, s]) if cols[i] not in seen]
        seen += new
        supports.append(list(seen))
    return supports


def _cv_ev(grams: list[tuple[np.ndarray, np.ndarray]], cols: list[int], y: int) -> float:
    """Held-out share of variance over folds: fit on each (train, test) Gram pair's train."""
    sse = sum(_sse(te, cols, y, _ols(tr, cols, y)) for tr, te in grams)
    tot = sum(te[y, y] for _, te in grams)
    return 1.0 - sse / tot if tot > 0 else 0.0


def _select(fold_grams, G_train, candidates: list[int], y: int, min_gain: float,
            slot_of: Mapping[int, object] | None = None) -> tuple[list[int], dict[int, int]]:
    """Stable terms of one axis and how many folds selected each. Rival forms of one term
    (``slot_of`` maps a column to its slot: :func:`quadcore.identify.discovery.terms.form_family`) share
    their folds' votes: a slot is stable when most folds select one of its forms, and stands for them with its most
    selected form (which :func:`_prefer_forms` then weighs against the others)."""
    paths = [_omp_path(tr, candidates, y, MAX_TERMS) for tr, _ in fold_grams]
    n_steps = min(len(p) for p in paths)
    ev = [0.0]
    for s in range(n_steps):  # held-out variance with s+1 terms, each fold its own path
        sse = sum(_sse(te, p[s], y, _ols(tr, p[s], y)) for (tr, te), p in zip(fold_grams, paths))
        tot = sum(te[y, y] for _, te in fold_grams)
        ev.append(1.0 - sse / tot)
    k = 0
    while k < n_steps and ev[k + 1] - ev[k] >= min_gain:
        k += 1
    counts: dict[int, int] = {}
    slots: dict[object, set[int]] = {}  # slot -> the folds that selected one of its forms
    slot = slot_of or {}
    for f, p in enumerate(paths):
        for c in (p[k - 1] if k else []):
            counts[c] = counts.get(c, 0) + 1
            slots.setdefault(slot.get(c, c), set()).add(f)
    stable = []
    for key, folds in slots.items():
        if len(folds) >= MIN_STABILITY * len(fold_grams):
            members = [c for c in counts if slot.get(c, c) == key]
            lead = max(members, key=lambda c: (counts[c], -c))
            counts[lead] = len(folds)
            stable.append(lead)
    return _order_and_prune(fold_grams, stable, y, min_gain), counts


def _order_and_prune(fold_grams, stable: list[int], y: int, min_gain: float) -> list[int]:
    """Greedy order of the stable terms by held-out gain; drop those adding < ``min_gain``."""
    chosen: list[int] = []
    left = list(stable)
    base = 0.0
    while left:
        gains = [(_cv_ev(fold_grams, chosen + [c], y) - base, c) for c in left]
        gain, best = max(gains)
        if gain < min_gain:
            break
        chosen.append(best)
        left.remove(best)
        base += gain
    return chosen


def _set_sse(pairs, cols: list[int], y: int) -> np.ndarray:
    """Held-out sum of squares per (training sum, held-out sum) pair."""
    return np.array([_sse(te, cols, y, _ols(tr, cols, y)) for tr, te in pairs])


def _prefer_forms(fold_grams, scored_on, chosen: list[int], y: int, col_term: dict[int, Term]
                  ) -> tuple[list[int], dict[int, tuple[Form, ...]]]:
    """Each kept term with rival forms (:func:`quadcore.identify.discovery.terms.form_family`) replaced
    by the form the cross-validation folds prefer: with the axis' other kept terms beside it, the best mean rank
    of its held-out error among the rivals over the folds (each fold one vote, so one fold's
    large variance does not decide), then the least error summed over them. Chosen where the
    terms are selected, so a holdout stays unseen; every rival scored on ``scored_on``, the
    sets the kept terms' shares are scored on."""
    column_of = {t.expression: c for c, t in col_term.items()}
    tot = sum(te[y, y] for _, te in scored_on)
    out, forms = list(chosen), {}
    for i, c in enumerate(chosen):
        rivals = [column_of[e] for e in form_family(col_term[c].expression)
                  if e in column_of and (column_of[e] == c or column_of[e] not in out)]
        if len(rivals) < 2:
            continue
        sse = {r: _set_sse(fold_grams, out[:i] + [r] + out[i + 1:], y) for r in rivals}
        ranks = np.argsort(np.argsort(np.array([sse[r] for r in rivals]), axis=0), axis=0).mean(axis=1)
        best = min(rivals, key=lambda r: (float(ranks[rivals.index(r)]), float(sse[r].sum()), r != c))
        out[i] = best
        held = {r: float(_set_sse(scored_on, out[:i] + [r] + out[i + 1:], y).sum()) for r in rivals}
        scored = [Form(col_term[r].expression, 1.0 - held[r] / tot if tot > 0 else 0.0,
                       int(np.sum(sse[r] < sse[best])), len(fold_grams)) for r in rivals]
        forms[best] = tuple(sorted(scored, key=lambda f: (f.expression != col_term[best].expression,
                                                          -f.explained_variance)))
    return out, forms


def _form_label(expression: str, forms: tuple[Form, ...], channel: str) -> str:
    """The mechanism's name when the kept form (listed first) beats each rival in most folds
    (``MIN_STABILITY``, as a term must be kept in most folds); else the rival forms with their
    held-out scores."""
    scores = ", ".join(f"{f.expression} {f.explained_variance:.1%}" for f in forms)
    decided = all(f.sets - f.better_in >= MIN_STABILITY * f.sets for f in forms if f.expression != expression)
    if not forms or decided:
        name = literature(expression, channel)
        return f"{name}; forms held out: {scores}" if forms and name else name
    return (f"form undecided: held out {scores} of the variance; the kept form is not the better one in most "
            "folds, so no mechanism is named")


def _rmse_from_sums(lib: LibrarySums, coefs: dict, pairs: list[tuple[np.ndarray, np.ndarray]],
                    eval_ids: list[str], cut: bool) -> tuple[dict, dict]:
    """:func:`_held_out_errors`' RMSE: per pair (the Gram matrix the terms are fitted on, the sum of
    ``H`` of the flights scored with them), the residual's sum of squares after the terms,
    ``Σ r² - 2 βᵀXᵀr + βᵀXᵀXβ`` (:func:`_sse`); before them, ``Σ r²`` (the flights' own sums of the
    residual's squares, as the rows give them, unless a model's linear fit was subtracted from the
    sums). ``cut``: the pairs' ``H`` are over the samples after each flight's first blocks, and so are
    the sums of squares and the samples counted here."""
    cols = lib.cols
    squares = lib.y_squares_after if cut else lib.y_squares
    if squares is not None:
        before = np.zeros(6)
        for f in eval_ids:
            before += squares[f]
    else:
        before = np.array([sum(float(H[y, y]) for _, H in pairs) for y in range(cols.target0, cols.target0 + 6)])
    after = before.copy()
    for axis, (chosen, _) in coefs.items():
        if chosen:
            y = cols.target0 + axis
            after[axis] = max(sum(_sse(H, chosen, y, _ols(G, chosen, y)) for G, H in pairs), 0.0)
    n = _scored_samples(lib, eval_ids, cut)
    return _rmse(before, n), _rmse(after, n)


def _scored_samples(lib: LibrarySums, eval_ids: list[str], cut: bool) -> int:
    """The evaluated flights' usable samples; ``cut``: after their first blocks."""
    samples = lib.samples_after if cut else lib.samples
    return sum(samples[f] for f in eval_ids)


def _rmse(ss: np.ndarray, n: int) -> dict:
    """The RMSE per axis of the sums of squares ``ss`` (6,) over ``n`` samples (:func:`_by_axis`)."""
    return _by_axis(np.sqrt(ss / max(n, 1)))


def _by_axis(rms: np.ndarray) -> dict:
    """(6,) RMS values (force x, y, z in N, torque x, y, z in N m, body frame) as the JSON document lists them."""
    return {"force_rmse_N": [float(v) for v in rms[:3]], "torque_rmse_Nm": [float(v) for v in rms[3:]]}


def _discover_axis(axis: int, target: str, lib: LibrarySums, fold_grams, G_train: np.ndarray, noise: np.ndarray,
                   holdout: bool, model_effects, fx_effects: list[Effect], settings: DiagnosisSettings
                   ) -> tuple[AxisResult, list[DiscoveredTerm], tuple[list[int], np.ndarray] | None]:
    """One residual axis: nothing when its residual is at the sensor-noise floor; else the
    stable terms (:func:`_select`) fitted on all training flights, with their jackknife
    standard errors over the folds and held-out shares, and their coefficients."""
    cols, terms = lib.cols, lib.terms
    y = cols.target0 + axis
    rms = np.sqrt(G_train[y, y] / _rows(G_train))
    if rms <= (1 + settings.noise_margin) * noise[axis]:
        why = (f"residual RMS {rms:.3g} within {settings.noise_margin:.0%} of the "
               f"sensor-noise floor {noise[axis]:.3g}: nothing to discover")
        return AxisResult(target, 0.0, True, (why,)), [], None
    candidates = [cols.term_col(k, axis) for k, t in enumerate(terms)
                  if not excluded(t, target) and (k in cols.force if axis < 3 else k in cols.torque)]
    col_term = {cols.term_col(k, axis): t for k, t in enumerate(terms) if t in _usable(cols, axis, terms)}
    chosen, counts = _select(fold_grams, G_train, candidates, y, settings.min_gain,
                             {c: form_family(col_term[c].expression) or c for c in candidates})
    scored_on = [(G_train, lib.sums.held_out())] if holdout else fold_grams
    picked, forms = _prefer_forms(fold_grams, scored_on, chosen, y, {c: col_term[c] for c in candidates})
    for old, new in zip(chosen, picked):  # a form's stability is its slot's: the folds that kept a form there
        counts[new] = max(counts.get(new, 0), counts.get(old, 0))
    chosen = picked
    beta = _ols(G_train, chosen, y)
    jack = [_ols(tr, chosen, y) for tr, _ in fold_grams]
    k_f = len(fold_grams)
    std = np.sqrt((k_f - 1) / k_f * np.sum((np.array(jack) - np.mean(jack, axis=0)) ** 2, axis=0)) if chosen \
        else np.zeros(0)
    shares = _sequential_shares(scored_on, chosen, y)
    kept = []
    for i, c in enumerate(chosen):
        t = col_term[c]
        coef_unit = mul_units(UNIT["N"] if axis < 3 else UNIT["N m"], t.unit, -1)
        kept.append(DiscoveredTerm(
            target, t.expression, t.variables, float(beta[i]), float(std[i]), unit_text(coef_unit),
            unit_text(t.unit), shares[i], counts.get(c, 0) / k_f, counts.get(c, 0), k_f,
            _matches(G_train, cols, c, axis, fx_effects, model_effects),
            _form_label(t.expression, forms.get(c, ()), "force" if axis < 3 else "torque"),
            _collinear(G_train, c, [d for d in candidates if d != c], col_term), forms.get(c, ())))
    result = AxisResult(target, float(sum(shares)), False,
                        _modelled_side_note(G_train, cols, chosen, beta, axis, target))
    return result, kept, (chosen, beta)


def discover(
    decoded: Mapping[str, pl.DataFrame],
    spec: ModelSpec,
    holdout: list[str] | None = None,
    settings: DiagnosisSettings = DEFAULT,
    stride: int = library_stats.STRIDE,
    log=lambda msg: None,
    sessions: dict[str, list[str]] | None = None,
    stored: Callable[[str], library_stats.FlightLibrary | None] | None = None,
    stats: Callable[[str], sufficient.FlightStats | None] | None = None,
) -> Discovery:
    """Find the terms the model lacks (see the module docstring). ``sessions`` (name ->
    flights, from a sessions file) group the flights of per-session effects, as in
    :func:`quadcore.identify.diagnosis.diagnose`; None: the model file's, else the groups the data show.

    Every path selects and scores from the flights' discovery statistics
    (:mod:`quadcore.identify.discovery.library_stats`: the selection's Gram matrices, and the held-out
    RMSE before and after the terms as a quadratic form of the matrices on every usable sample).

    A model without effects or of linear effects fitted fleet-wide, at the default ``stride``: from
    the flights' nominal statistics, ``stored`` (flight -> its stored discovery statistics or None:
    :func:`quadcore.identify.discovery.library_stats.stored`; no flight with stored statistics is
    read), the others computed from their rows; the model's effects fitted (from the sufficient
    statistics ``stats`` when given: :func:`quadcore.identify.stats.sufficient.stored`) and subtracted
    from the sums (the residual's Gram matrices ``TᵀGT``, equal to the rows' to rounding).

    Any other model (a nonlinear effect, effects fitted per session) or stride: from rows, flight by
    flight: each flight's rows and its residual under the model (the model's effects predicted on
    them) become its statistics (:func:`quadcore.identify.discovery.library_stats.compute`) and are
    dropped, each flight read once. ``decoded`` may read each table as it is looked up
    (:class:`quadcore.store.store.FlightTables`). Fitting the model's own effects reads the training
    flights' rows together (and every flight's for per-session effects).

    ``settings``: its folds, ``min_gain`` and ``noise_margin``
    (:class:`~quadcore.identify.settings.DiagnosisSettings`), recorded in the result."""
    ids = sorted(decoded)
    holdout = [h for h in (holdout or []) if h in decoded]
    train = [f for f in ids if f not in holdout]
    if len(train) < 2:
        raise ValueError("discovery needs at least two training flights (folds are grouped by flight)")
    fx_effects = library_stats.fx_effects(spec)  # the effects the stored statistics hold
    folds = solve.folds(train, settings.n_folds)
    skip = scored_after_blocks(spec)  # the first blocks of an evaluated flight the diagnosis does not score
    combinable = (stride == library_stats.STRIDE and not spec.per_session
                  and all(effectlib.get(n).linear for n in spec.effects)
                  and skip in (0, library_stats.head_blocks(spec)))
    if combinable:  # without stored statistics: each flight's computed from its rows
        lib = accumulate.from_statistics(ids, decoded, spec, fx_effects, folds, holdout, train,
                                         stored or (lambda f: None), stats, sessions, log)
    else:
        flight = accumulate.residual_rows(spec, decoded, ids, train, sessions, log)
        lib = accumulate.from_rows(ids, flight, decoded, spec, fx_effects, folds, holdout, stride, skip, log)
    noise = _noise_floor([lib.samples[f] for f in train], [lib.noise_of[f] for f in train])
    kept, axes, coefs = _discover_axes(lib, noise, bool(holdout), spec.effects, fx_effects, settings)
    eval_ids = holdout or ids
    base, after = _held_out_errors(lib, coefs, holdout, eval_ids, skip)
    return Discovery(
        tuple(kept), tuple(axes), base, after,
        _by_axis(noise),
        {"mode": "holdout" if holdout else "cross-validation", "train_flights": train, "eval_flights": eval_ids,
         "folds": len(folds), "stride": stride,
         # with a holdout the model's effects never see it; without one they are fitted on all flights
         "model_effects_fitted_on": train},
        tuple(spec.effects), {"force": len(lib.cols.force), "torque": len(lib.cols.torque)}, settings)


def _discover_axes(lib: LibrarySums, noise: np.ndarray, holdout: bool, model_effects, fx_effects: list[Effect],
                   settings: DiagnosisSettings
                   ) -> tuple[list[DiscoveredTerm], list[AxisResult], dict[int, tuple[list[int], np.ndarray]]]:
    """Every residual axis through :func:`_discover_axis`: the kept terms, each axis' result, and the
    kept columns with their coefficients per axis that kept any."""
    fold_grams, G_train = lib.sums.fold_grams(), lib.sums.training_total()
    kept: list[DiscoveredTerm] = []
    axes: list[AxisResult] = []
    coefs: dict[int, tuple[list[int], np.ndarray]] = {}
    for axis, target in enumerate(TARGETS):
        result, terms, coef = _discover_axis(axis, target, lib, fold_grams, G_train, noise, holdout,
                                             model_effects, fx_effects, settings)
        axes.append(result)
        kept += terms
        if coef is not None:
            coefs[axis] = coef
    return kept, axes, coefs


def _held_out_errors(lib: LibrarySums, coefs: dict, holdout: list[str], eval_ids: list[str],
                     skip: int) -> tuple[dict, dict]:
    """The RMSE per axis on the evaluated flights before and after the kept terms (``coefs``), each
    flight scored with the terms fitted on its fold's training flights (a holdout: on every training
    flight), from the flights' statistics (:func:`_rmse_from_sums`), on the usable samples after each
    evaluated flight's first ``skip`` blocks, the samples the diagnosis scores (on every usable sample
    when none is left there, as the diagnosis: ``problem._on_common_samples``)."""
    fold_grams, G_train = lib.sums.fold_grams(), lib.sums.training_total()
    cut = skip > 0 and _scored_samples(lib, eval_ids, True) > 0
    scored = lib.after if cut else lib.full
    pairs = [(G_train, scored.held_out())] if holdout else [
        (tr, inside) for (tr, _), inside in zip(fold_grams, scored.own_sums())]
    return _rmse_from_sums(lib, coefs, pairs, eval_ids, cut)


def _usable(cols: Columns, axis: int, terms: list[Term]) -> list[Term]:
    idx = cols.force if axis < 3 else cols.torque
    return [terms[k] for k in idx]


def _rows(G: np.ndarray) -> float:
    """Samples behind a Gram matrix: the constant term "1" is the first force column."""
    return float(G[0, 0])


def _noise_floor(samples: list[int], noises: list[np.ndarray]) -> np.ndarray:
    """(6,) the flights' sensor-noise floors pooled by their usable samples."""
    n = np.array(samples, dtype=float)
    return np.sqrt(np.sum(n[:, None] * np.array(noises) ** 2, axis=0) / n.sum())


def _sequential_shares(pairs, chosen, y) -> list[float]:
    """Held-out variance each term adds, in the order of selection (they sum to the total):
    ``pairs`` (training sum, held-out sum) per fold, or the one of the holdout."""
    evs = [_cv_ev(pairs, chosen[:i], y) for i in range(len(chosen) + 1)]
    return [float(evs[i + 1] - evs[i]) for i in range(len(chosen))]


def _matches(G, cols: Columns, c: int, axis: int, fx_effects, in_model) -> tuple[str, ...]:
    """Library effects whose basis (on this axis) holds at least MATCH of the term's energy."""
    out = []
    gcc = G[c, c]
    for e in fx_effects:
        b = cols.effect_cols[(e.name, axis)]
        if not b or gcc <= 0 or np.allclose(G[np.ix_(b, b)], 0):
            continue
        coef = np.linalg.lstsq(G[np.ix_(b, b)], G[b, c], rcond=1e-12)[0]
        r2 = float(G[c, b] @ coef / gcc)
        if r2 >= MATCH:
            out.append(f"{e.name}{' (in the model)' if e.name in in_model else ''}")
    return tuple(out)


def _collinear(G, c: int, others: list[int], col_term: dict[int, Term]) -> tuple[str, ...]:
    d = np.sqrt(np.maximum(np.diag(G), 1e-300))
    return tuple(col_term[o].expression for o in others if abs(G[c, o] / (d[c] * d[o])) >= COLLINEAR)


def _modelled_side_note(G, cols: Columns, chosen, beta, axis: int, target: str) -> tuple[str, ...]:
    """Say so when the kept terms rebuild a multiple of the axis' own modelled side."""
    m = cols.model0 + axis
    if not chosen or G[m, m] <= 0:
        return ()
    # prediction p = X beta; its projection on the modelled side: k = <p, m> / <m, m>
    pm = float(beta @ G[chosen, m])
    pp = float(beta @ G[np.ix_(chosen, chosen)] @ beta)
    if pp <= 0:
        return ()
    r2 = pm**2 / (pp * G[m, m])
    if r2 < 0.5:
        return ()
    k = pm / G[m, m]
    side = "thrust T" if axis < 3 else "rotor torque the thrust map gives"
    return ((f"{r2:.0%} of what the kept terms predict on {target} is {k:+.2f} × the modelled {side}: the model's own "
            f"term is mis-scaled or cancelled by something it does not model (a thrust-map error, or a disturbance "
            f"the controller holds off), not a new mechanism by itself"),)
