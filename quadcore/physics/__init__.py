"""Stage 2, the nominal physics: the vehicle file (``vehicle``), frames and attitude maths
(``rotations``), the physics gate and the columns the physics reads (``gate``), a decoded flight in the
data root with the gate's facts (``decoded_store``), rigid-body dynamics and thrust map (``dynamics``),
filtering and derivatives (``signals``), the measured-minus-modelled residual tables (``residuals``),
uncertainty propagation (``propagation``) and the thrust-coefficient fit (``thrustfit``)."""

# The modules other packages import (the public surface; importing the package imports none of them).
__all__ = ["decoded_store", "dynamics", "gate", "propagation", "residuals", "rotations", "signals", "thrustfit",
           "vehicle"]
