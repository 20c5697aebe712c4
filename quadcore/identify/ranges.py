"""Every statistic the diagnosis reports is checked against its mathematical range where it is
computed: a probability in [0, 1], a coherence in [0, 1], a gain or a test statistic finite. A value
outside its range is a defect in how it was computed (an undefined ratio, rounding turned into a
number), never something to report: it raises :class:`StatisticOutOfRange`. A statistic that is
not defined on the data (a band the model has no power in) is ``None`` in the JSON and "n/a" in
the reports, never a number."""

from __future__ import annotations

import math

# How far above 1 rounding may carry a coherence computed from sums of products (the summaries'
# quadratic forms agree with the rows' to ~1e-12 relative; near the resolution limit of a band's
# power, RESOLVED in quadcore.identify.describe.spectrum, to ~1e-7): beyond it, the value is a defect.
ROUNDING = 1e-6


class StatisticOutOfRange(ValueError):
    """A computed statistic outside its mathematical range (a defect, not a property of the data)."""


def finite(x: float, what: str) -> float:
    """``x`` as a float if it is finite."""
    x = float(x)
    if not math.isfinite(x):
        raise StatisticOutOfRange(f"{what} is {x}, not a finite number")
    return x


def probability(p: float, what: str) -> float:
    """``p`` as a float if it lies in [0, 1]."""
    p = float(p)
    if not 0.0 <= p <= 1.0:  # NaN fails both
        raise StatisticOutOfRange(f"{what} is {p}, not a probability in [0, 1]")
    return p


def unit_fraction(x: float, what: str, rounding: float = ROUNDING) -> float:
    """``x`` (a coherence, a squared correlation) in [0, 1]: within ``rounding`` of the range it
    is rounding and is clipped into it; further out it raises."""
    x = float(x)
    if not -rounding <= x <= 1.0 + rounding:
        raise StatisticOutOfRange(f"{what} is {x}, outside [0, 1]")
    return min(max(x, 0.0), 1.0)
