"""The statistical settings of the identification, defaulted in one place: the diagnosis's
thresholds and folds (:class:`DiagnosisSettings`, passed to
:func:`quadcore.identify.diagnosis.diagnose` and :func:`quadcore.identify.discovery.discover` and
recorded in their JSON documents as ``settings``),
and how a flight is summed into its stored statistics (:class:`StatisticsSettings`: the held-out
test's block length, the strides of the thinned Gram matrices, the unit wrenches' secant, the
regime bins). The second are fixed: the stored statistics and summaries are made with them (a
change is a change of code, and the statistics' key, which digests this module's source, makes
the stored ones stale), so they are recorded beside the thresholds, never passed in.

The module constants other modules read (``evidence.MIN_SIGMA``, ``evidence.BLOCK_S``,
``regimes.SPEED_BINS``, ``library_stats.STRIDE``, ...) are these
defaults under their old names. Imports nothing from the project: every module may read it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from typing import Any


def _bins(values: tuple[float, ...]) -> list[float | None]:
    """Bin edges for JSON: an open edge (-inf) as None."""
    return [None if math.isinf(v) else v for v in values]


@dataclass(frozen=True)
class StatisticsSettings:
    """How a flight is summed into its statistics and summaries (fixed; see the module)."""

    block_s: float = 1.0  # length of the blocks (clusters) of the held-out test, s
    gram_stride: int = 4  # every 4th usable sample for the diagnosis's signature Gram
    library_stride: int = 4  # discovery's: every 4th usable sample in the selection's Gram matrix
    secant: float = 0.01  # share of a parameter's range over which its unit wrench is taken (profiles' unit columns)
    # the regime tables' bin edges (docs/diagnosis.md, part 1)
    speed_bins_mps: tuple[float, ...] = (0.0, 0.25, 0.5, 1.0, 1.5)
    height_bins_m: tuple[float, ...] = (-math.inf, 0.1, 0.3, 0.6, 1.0)
    thrust_to_weight_bins: tuple[float, ...] = (0.0, 0.8, 0.95, 1.05, 1.2)
    angular_rate_bins_radps: tuple[float, ...] = (0.0, 0.5, 1.0, 2.0, 4.0)
    battery_bins_V: tuple[float, ...] = (0.0, 3.5, 3.7, 3.9)
    acceleration_bins_mps2: tuple[float, ...] = (0.0, 0.5, 1.0, 2.0, 4.0)

    def to_dict(self) -> dict[str, Any]:
        """The JSON object (bin edges as lists, an open edge as null)."""
        return {k: _bins(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}


STATISTICS = StatisticsSettings()


@dataclass(frozen=True)
class DiagnosisSettings:
    """The thresholds by which the diagnosis (and discovery) decides, and its folds
    (``docs/diagnosis.md``; :mod:`quadcore.identify.evidence` explains the held-out test and the
    detection limits). The fixed :data:`STATISTICS` are recorded with them (:meth:`to_dict`)."""

    alpha: float = 0.01  # one-sided false-alarm probability of the held-out test, for the whole library
    power: float = 0.9  # detection probability the sensitivity is stated at
    noise_margin: float = 0.10  # a channel within this fraction (RMS) of its noise floor holds no evidence
    min_explained: float = 0.05  # screening: below this share of the residual a candidate adds nothing beyond the best
    min_sigma: float = 3.0  # a fit within this many standard errors of 'no effect' is not significant
    bound_sigma: float = 3.0  # a free fit beyond a physical bound by more than this many standard errors is unphysical
    library_share: float = 0.5  # found candidates removing less than this share of the above-noise residual: outside
    same_signature: float = 0.1  # share of one prediction another cannot reproduce, below which they are alike
    tie_margin: float = 0.02  # score difference within which two alike candidates are a tie (parsimony decides)
    large_snr: float = 3.0  # a found effect whose removed residual exceeds this many noise floors (RMS) is "large"
    n_folds: int = 5  # cross-validation's folds over flights (and the groups of the spread with a holdout)
    min_gain: float = 0.02  # discovery: a term must add this share of the held-out variance of its axis

    def __post_init__(self) -> None:
        for name in ("alpha", "power", "noise_margin", "min_explained", "same_signature", "library_share",
                     "tie_margin", "min_gain"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"DiagnosisSettings.{name} = {v!r}: a share or a probability, in [0, 1]")
        for name in ("min_sigma", "bound_sigma", "large_snr"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"DiagnosisSettings.{name} = {getattr(self, name)!r}: a number of standard "
                                 "errors or noise floors, >= 0")
        if self.n_folds < 2:
            raise ValueError(f"DiagnosisSettings.n_folds = {self.n_folds!r}: at least 2")

    def to_dict(self) -> dict[str, Any]:
        """The JSON object: the thresholds, the folds, and the statistics' fixed settings."""
        return {**asdict(self), "statistics": STATISTICS.to_dict()}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> DiagnosisSettings:
        """From its JSON object (the statistics' part is fixed, not read back); the defaults for a
        document written before settings were recorded."""
        if not d:
            return cls()
        return cls(**{f.name: d[f.name] for f in fields(cls) if f.name in d})


DEFAULT = DiagnosisSettings()
