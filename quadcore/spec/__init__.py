"""What a user asks for, before anything is fitted: the model file (``model``: :class:`~quadcore.spec.model.ModelSpec`,
its parser and :class:`~quadcore.spec.model.ModelFileError`) and the sessions file (``sessions``). Below
``identify``, ``learn``, ``export``, ``sim`` and ``plan``, which read them; above ``effects``, ``physics`` and
``store``, which they name."""

# The modules other packages import (the public surface; importing the package imports none of them).
__all__ = ["model", "sessions"]
