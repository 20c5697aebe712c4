"""Compatibility path for :class:`quadcore.effects.ccode.CCode`, the C form an effect returns.

``CCode`` moved to :mod:`quadcore.effects.ccode` (issue 23: an effect must not import the export stage
above it). Effect plugins written against ``from quadcore.export.ccode import CCode`` keep working
through this re-export; new code imports ``quadcore.effects.ccode``.
"""

from quadcore.effects.ccode import CCode

__all__ = ["CCode"]
