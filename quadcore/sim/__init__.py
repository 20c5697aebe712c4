"""Simulated flights, for tests and for checking what the identification recovers: the simulator
(``simulation``), its position/attitude controller (``controller``), reference trajectories
(``trajectories``; the CSV files live in ``quadcore/trajectories/``) and the uSD log it writes
(``usdlog``)."""

# The modules other packages import (the public surface; importing the package imports none of them).
__all__ = ["simulation", "trajectories"]
