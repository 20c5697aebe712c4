"""quadcore: a small physics and data library for quadrotor flight logs.

One module per idea: ``logformat`` (the uSD binary format), ``units`` (SI names and
conversions), ``flight`` (a decoded flight), ``store`` (Parquet layout under the data
root), and the physics modules built on them.
"""

__version__ = "0.1.0"
