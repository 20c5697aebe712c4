"""The Dagster processes on this machine: the headless main job (``main``, ``python -m pipeline``) and
its second process (``parallel``), the persistent instance they and the UI share (``instance``), and
the UI with its daemon (``ui``, ``make ui``) whose webserver serves the plots (``webserver``).

A multi-process deployment with its own services (PostgreSQL, Redis, Celery workers, an S3-compatible
store) is :mod:`pipeline.cluster`; the main job submits its runs there when ``QUADCORE_CLUSTER_URL`` is
set (:mod:`pipeline.cluster.launch`)."""
