"""Reports for people: one Markdown/HTML renderer (``render``), the diagnosis report (``diagnosis``),
the learning report (``learning``) and the plots (``plots``)."""

# The modules other packages import (the public surface; importing the package imports none of them).
__all__ = ["diagnosis", "learning", "plots", "render"]
