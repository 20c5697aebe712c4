"""Stage 1, the flight log: the uSD binary format (``logformat``), SI names and unit conversions
(``units``), a decoded flight with its provenance (``flight``) and the checks that flag a log
(``checks``; the physics gate is ``quadcore.physics.gate``)."""

# The modules other packages import (the public surface; importing the package imports none of them).
__all__ = ["checks", "flight", "logformat", "required", "units"]
