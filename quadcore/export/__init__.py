"""Outputs for other tools: a flight as MCAP for Foxglove (``mcap``), the model as C for a flight
controller (``c``) and the C form an effect returns for it (``ccode``)."""

# The modules other packages import (the public surface; importing the package imports none of them).
__all__ = ["c", "ccode", "mcap"]
