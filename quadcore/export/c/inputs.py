"""Compatibility path for :mod:`quadcore.effects.c_inputs`, the C names of the on-board inputs.

They moved below ``identify`` (issue 23: discovery's effect writer names a discovered term's inputs in C,
and ``export`` sits above ``identify``). :mod:`quadcore.identify.discovery.writer` still imports this path
inside ``c_term``; once it imports ``quadcore.effects.c_inputs`` at module level, this module goes.
"""

from quadcore.effects.c_inputs import Derived, ExportError, Field, feature_expression

__all__ = ["Derived", "ExportError", "Field", "feature_expression"]
