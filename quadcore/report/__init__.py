"""Reports for people: the diagnosis as Markdown and HTML (``report``) and the plots (``plots``)."""
