"""Stage 2, the nominal physics: the vehicle file (``vehicle``), attitude maths (``rotations``),
rigid-body dynamics and thrust map (``dynamics``), filtering and derivatives (``signals``), the
measured-minus-modelled residual tables (``residuals``), uncertainty propagation (``propagation``)
and the thrust-coefficient fit (``thrustfit``)."""

# The modules other packages import (the public surface; importing the package imports none of them).
__all__ = ["dynamics", "propagation", "residuals", "rotations", "signals", "thrustfit", "vehicle"]
