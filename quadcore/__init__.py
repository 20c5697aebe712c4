"""quadcore: a small physics and data library for quadrotor flight logs.

One package per stage of the data flow: ``logs`` (the uSD format, SI units, a decoded
flight), ``physics`` (vehicle, dynamics, residuals), ``effects``, ``sim``, ``identify``
(model fitting, diagnosis, discovery), ``learn`` (learned residual models), ``report``,
``store`` (the data root) and ``export`` (MCAP, C); ``cli`` and ``workflows`` on top.
"""

__version__ = "0.1.0"

__all__ = ["__version__"]
