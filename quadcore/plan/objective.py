"""How well a planned flight, added to the logged ones, separates two explanations, or pins a
parameter down: the quantity the search maximises.

**Separation** (a T-optimal criterion, Atkinson and Fedorov 1975, in the held-out view of the
diagnosis's folds). Suppose explanation A is true: every flight's residual is A's prediction
``y = η_A`` plus noise. The diagnosis scores the planned flight with the rival B fitted on the
logged flights, and the logged flights with B fitted on the others and the planned one: so B
fitted on the old flights predicts the planned one, and B refitted on old and planned together
(``θ_B* = argmin Σ_i Σ_c w_c (y_ic - η_B(θ)_ic)²``, ``w_c = 1 / σ_c²``) scores the old ones. What B
cannot reproduce, ``d = y - η_B``, per 1 s block ``b`` gives the expected score of the
diagnosis's comparison of the two (:func:`quadcore.identify.evidence.compare`: ``2 (a - b)·(r -
(a + b)/2)`` summed per block, t-tested over the blocks): mean ``μ_b = ½ Σ_{i∈b} w_c d²``, noise
variance ``2 W μ_b`` (``W`` samples per independent one,
:data:`quadcore.identify.flightdata.SAMPLES_PER_INDEPENDENT`), and its expected t is
``Σ μ_b / sqrt(n/(n-1) Σ (μ_b - μ̄)² + 2 W Σ μ_b)`` (:func:`t_statistic`): the blocks' spread
counts, so a difference confined to a few blocks separates less than its energy suggests. The
same with B true; the design must work whichever is true: its separation is the smaller.

The diagnosis also needs the two scores (shares of the residual explained) to differ by
``TIE_MARGIN``: the score gap is the mismatch as a share of the pooled residual energy,
``½ Σ_channel mismatch / energy`` (force and torque averaged, as the score is). The search
maximises ``min over truths of min(σ / SIGMA_GOAL, gap / GAP_GOAL)``: one number that is
above 1 when both of the diagnosis's tie conditions are broken with margin.

Both are taken on the samples the diagnosis compares candidates on: each flight's first
``skip`` blocks (:func:`quadcore.identify.evidence.memory_blocks`: within the longest memory of
the diagnosis's effects) are left out, as the diagnosis leaves them out. There an effect with
memory predicts nothing and one without (or with a shorter memory) does: counting them would
"separate" a lag from a delay by the first second of every flight, whatever the manoeuvre.

**One flight can lower σ.** A flight whose mismatch falls in a few blocks adds more to the
blocks' spread than to their sum: on the 19 real flights the first plan raised ``Σ μ_b`` 4.5-fold
and the spread term 350-fold, σ 3.17 -> 2.65 (docs/flight-planning.md).

**Repeated flights** (``evaluate(new, copies)``, :meth:`SeparationObjective.copies_to_decide`):
the planned flight's blocks ``copies`` times, each copy scored with the rival fitted on the old
flights (as one planned flight is). σ then grows about as √copies; the score gap tends to the
flight's own share of mismatch in its residual energy, so a flight whose share is below
``GAP_GOAL`` never decides, however often it is flown.

``σ_c`` per axis is the held-out residual the diagnosis leaves after the better of the two
explanations, never below the sensor-noise floor the logs show: on simulated flights that is
the floor; on real flights whatever else is unmodelled counts as noise too.

**Information on a parameter.** With ``u`` the prediction's change per unit of the parameter
(:func:`quadcore.plan.signatures.unit_wrench`), a flight adds ``I = Σ w_c u_c² / W`` to the
information, so the standard error becomes ``(1 / s_before² + I)^(-1/2)``; each parameter is
treated alone (its correlation with the others ignored, stated in the docs).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from quadcore.identify import evidence, flightdata
from quadcore.physics.vehicle import Vehicle
from quadcore.plan.signatures import Explanation, predict, unit_wrench

W = flightdata.SAMPLES_PER_INDEPENDENT
SIGMA_GOAL = 3.0  # beyond the comparison's two-sided critical value (~2.6 at ALPHA = 0.01)
GAP_GOAL = 2 * evidence.TIE_MARGIN
GRID_POINTS = 25  # values of a one-parameter nonlinear rival tried when it is refitted
NEAR = 3  # with a planned flight, the joint refit tries the grid values this close to the old flights' fit
CHANNELS = {"force": slice(0, 3), "torque": slice(3, 6)}
MAX_COPIES = 1024  # the most repeats of a planned flight :meth:`SeparationObjective.copies_to_decide` tries


def _grid(expl: Explanation) -> np.ndarray:
    """Values of a one-parameter nonlinear rival to refit over: around its fitted value (a
    quarter to four times its distance from 'no effect') and across its range."""
    p = expl.effect.parameters[0]
    fitted = float(expl.params[p.name])
    dev = fitted - p.default
    around = p.default + dev * np.geomspace(0.25, 4.0, GRID_POINTS) if dev != 0 else np.zeros(0)
    values = np.concatenate([around, np.linspace(p.lower, p.upper, GRID_POINTS), [fitted]])
    return np.unique(np.clip(values, p.lower, p.upper))


def blocks(fd: flightdata.FlightData) -> np.ndarray:
    """Block index (blocks of :data:`quadcore.identify.flightdata.BLOCK_S`) of each usable sample."""
    t = fd.state.t_s[fd.mask]
    return ((t - t[0]) // evidence.BLOCK_S).astype(int) if len(t) else np.zeros(0, dtype=int)


def compared(fd: flightdata.FlightData, skip: int) -> tuple[np.ndarray, np.ndarray]:
    """The usable samples the diagnosis compares candidates on (all but the first ``skip``
    blocks; a boolean over the usable samples) and their blocks, numbered from 0."""
    b = blocks(fd)
    keep = b >= skip
    return keep, b[keep] - skip


def _per_block(values: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Sum ``values`` (n, ...) over the samples of each block -> (blocks, ...)."""
    out = np.zeros((int(b.max(initial=-1)) + 1, *values.shape[1:]))
    np.add.at(out, b, values)
    return out


class Direction:
    """One truth and its rival (see the module), in the held-out view of the diagnosis's folds:
    the planned flight is scored with the rival fitted on the old flights, the old flights with
    the rival fitted on old and planned flights together. Each flight's part is kept per 1 s
    block and channel (the comparison's clusters), the old flights' computed once."""

    def __init__(self, truth: Explanation, rival: Explanation, old: Sequence[flightdata.FlightData], vehicle: Vehicle,
                 w: np.ndarray, skip: int = 0):
        self.truth, self.rival, self.vehicle, self.skip = truth, rival, vehicle, skip
        e = rival.effect
        self.kind = "linear" if e.linear else ("grid" if len(e.parameters) == 1 else "fixed")
        self.values = _grid(rival) if self.kind == "grid" else None
        parts = [self.sums(fd) for fd in old]
        self.old = (tuple(np.concatenate(x) for x in zip(*parts)) if self.kind == "linear"
                    else np.concatenate(parts, axis=1))
        self.near = np.zeros(1, dtype=int)
        if self.values is not None and isinstance(self.old, np.ndarray):
            # a planned flight moves the joint fit only near the old flights' own
            best = int(np.argmin(self.old.sum(axis=1) @ w))
            self.near = np.arange(max(0, best - NEAR), min(len(self.values), best + NEAR + 1))
            self.values = self.values[self.near]
            self.old = self.old[self.near]
            self.on_old = best - int(self.near[0])

    def sums(self, fd: flightdata.FlightData):
        """One flight's part per block and channel: the Gram sums of the rival's basis and the
        truth's prediction (linear rival), or the squared mismatch at each grid value
        ((values, blocks, 6))."""
        keep, b = compared(fd, self.skip)
        y = predict(self.truth, fd, self.vehicle)[fd.mask][keep]
        if self.kind == "linear":
            X = fd.basis(self.rival.effect, self.vehicle)[fd.mask][keep]
            return (_per_block(np.einsum("nci,ncj->ncij", X, X), b), _per_block(np.einsum("nci,nc->nci", X, y), b),
                    _per_block(y**2, b))
        if self.kind == "fixed":
            return _per_block((y - predict(self.rival, fd, self.vehicle)[fd.mask][keep]) ** 2, b)[None]
        name = self.rival.effect.parameters[0].name
        out = []
        for v in self.values if self.values is not None else ():
            pred = flightdata.prediction(self.rival.effect, {**self.rival.params, name: float(v)}, fd, self.vehicle)
            out.append(_per_block((y - pred[fd.mask][keep]) ** 2, b))
        return np.stack(out)

    def repeated(self, part, copies: int):
        """A flight's :meth:`sums` as if it were flown ``copies`` times (its blocks repeated)."""
        if copies == 1:
            return part
        if self.kind == "linear":
            return tuple(np.concatenate([x] * copies) for x in part)
        return np.concatenate([part] * copies, axis=1)

    def _fit(self, parts: list, w: np.ndarray):
        """The rival's best fit (linear coordinates, or a grid index) to the truth over ``parts``."""
        if self.kind != "linear":
            return int(np.argmin(sum((p.sum(axis=1) @ w) for p in parts)))  # (the old flights' own: on_old)
        G = sum(p[0].sum(axis=0) for p in parts)
        g = sum(p[1].sum(axis=0) for p in parts)
        return np.linalg.lstsq(np.tensordot(w, G, axes=1), w @ g, rcond=None)[0]

    def _mismatch(self, part, fit) -> np.ndarray:
        """(blocks, 6) what the rival at ``fit`` leaves of the truth, per block and channel."""
        if self.kind != "linear":
            return part[fit]
        G, g, yy = part
        return np.maximum(yy - 2 * g @ fit + np.einsum("i,bcij,j->bc", fit, G, fit), 0.0)

    def held_out(self, w: np.ndarray, new=None) -> np.ndarray:
        """(blocks, 6) the mismatch per block and channel (weights ``w`` for the fits): the old
        flights alone (the rival fitted on them), or with a planned flight's ``sums`` (see the class)."""
        on_old = self._fit([self.old], w) if self.kind == "linear" else getattr(self, "on_old", 0)
        if new is None:
            return self._mismatch(self.old, on_old)
        joint = self._fit([self.old, new], w)
        return np.concatenate([self._mismatch(self.old, joint), self._mismatch(new, on_old)])


def t_statistic(mu: np.ndarray) -> float:
    """The comparison's expected t from per-block expected scores ``mu`` = ½ Σ w d² (see the
    module): the blocks' spread and the noise (variance ``2 W mu`` per block) both count."""
    n = len(mu)
    if n < 3 or mu.sum() <= 0:
        return 0.0
    spread = n / (n - 1) * float(((mu - mu.mean()) ** 2).sum())
    return float(mu.sum() / np.sqrt(spread + 2 * W * mu.sum()))


@dataclass(frozen=True)
class Separation:
    """Expected separation of two explanations (see the module): per truth, the held-out
    comparison's σ and the score gap; ``value`` the search's objective."""

    sigma: float
    score_gap: float | None  # None where the diagnosis decides by the comparison alone (timing, ratelevel)
    value: float
    by_truth: Mapping[str, tuple[float, float | None]]

    def to_dict(self) -> dict:
        return {"sigma": self.sigma, "score_gap": self.score_gap, "value": self.value,
                "by_truth": {k: {"sigma": s, "score_gap": g} for k, (s, g) in self.by_truth.items()}}


class SeparationObjective:
    """The separation of ``a`` and ``b`` given the old flights, their residual energy per axis
    (``old_energy``, (6,) sums of squares of the model's residual, on the samples the diagnosis
    compared) and the noise ``sigma`` (6,); ``skip``: the first blocks of each flight the
    diagnosis leaves out of its comparison (see the module)."""

    def __init__(self, a: Explanation, b: Explanation, old: Sequence[flightdata.FlightData], vehicle: Vehicle,
                 sigma: np.ndarray, old_energy: np.ndarray, skip: int = 0):
        self.a, self.b, self.vehicle, self.skip = a, b, vehicle, skip
        self.sigma = np.maximum(np.asarray(sigma, float), 1e-12)
        self.w = 1.0 / self.sigma**2
        self.old_energy = np.asarray(old_energy, float)
        self.directions = [Direction(a, b, old, vehicle, self.w, skip), Direction(b, a, old, vehicle, self.w, skip)]

    def evaluate(self, new: flightdata.FlightData | None = None, copies: int = 1) -> Separation:
        """The separation with the planned flight ``new`` flown ``copies`` times in addition to
        the old flights (none: the old flights alone)."""
        by_truth = {}
        for d in self.directions:
            per_block = d.held_out(self.w, d.repeated(d.sums(new), copies) if new is not None else None)
            energy = self.old_energy.copy()
            if new is not None:
                keep, _ = compared(new, self.skip)
                y = predict(d.truth, new, self.vehicle)[new.mask][keep]
                energy += copies * ((y**2).sum(axis=0) + len(y) * self.sigma**2)
            sigma = t_statistic(0.5 * per_block @ self.w)
            mis = per_block.sum(axis=0)
            gap = 0.5 * sum(float(mis[sl].sum() / energy[sl].sum()) for sl in CHANNELS.values() if energy[sl].sum() > 0)
            by_truth[d.truth.name] = (sigma, gap)
        sigma = min(s for s, _ in by_truth.values())
        gap = min(g for _, g in by_truth.values())
        value = min(min(s / SIGMA_GOAL, g / GAP_GOAL) for s, g in by_truth.values())
        return Separation(sigma, gap, value, by_truth)

    def value(self, new: flightdata.FlightData) -> float:
        return self.evaluate(new).value

    def copies_to_decide(self, new: flightdata.FlightData,
                         max_copies: int = MAX_COPIES) -> tuple[int | None, Separation]:
        """How many times ``new`` must be flown for the objective to reach 1 (both of the
        diagnosis's tie conditions broken with margin), and the separation there: doubling, then
        halving the last step (taking the value to grow with the copies); ``(None, at max_copies)`` when
        even ``max_copies`` do not (the score gap tends to the flight's own share of mismatch in
        its residual energy, which more flying does not raise)."""
        lo, hi = 0, 1
        while (sep := self.evaluate(new, hi)).value < 1.0:
            if hi >= max_copies:
                return None, sep
            lo, hi = hi, min(2 * hi, max_copies)
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if self.evaluate(new, mid).value >= 1.0:
                hi = mid
            else:
                lo = mid
        return hi, self.evaluate(new, hi)


class Information:
    """A parameter's standard error after a planned flight, ``(1/std_before² + I)^(-1/2)`` for the
    information ``I`` the flight adds (:meth:`information`, the subclass's); the search maximises
    ``std_before / std_after``."""

    std_before: float

    def information(self, new: flightdata.FlightData) -> float:
        raise NotImplementedError

    def std_after(self, new: flightdata.FlightData) -> float:
        info = self.information(new)
        prior = 1.0 / self.std_before**2 if self.std_before > 0 and np.isfinite(self.std_before) else 0.0
        return float(1.0 / np.sqrt(prior + info)) if prior + info > 0 else float("inf")

    def value(self, new: flightdata.FlightData) -> float:
        after = self.std_after(new)
        return self.std_before / after if np.isfinite(after) and after > 0 and np.isfinite(self.std_before) else 0.0


class InformationObjective(Information):
    """The information on the force and torque channels (see the module)."""

    def __init__(self, expl: Explanation, parameter: str, std_before: float, vehicle: Vehicle, sigma: np.ndarray):
        self.expl, self.parameter, self.vehicle = expl, parameter, vehicle
        self.std_before = float(std_before)
        self.w = 1.0 / np.maximum(np.asarray(sigma, float), 1e-12) ** 2

    def information(self, new: flightdata.FlightData) -> float:
        u = unit_wrench(self.expl, self.parameter, new, self.vehicle)[new.mask]
        return float((u**2).sum(axis=0) @ self.w) / W
