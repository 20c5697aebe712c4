"""Reports for people: one Markdown/HTML renderer (``render``), the diagnosis report (``diagnosis``),
the learning report (``learning``) and the plots (``plots``)."""
