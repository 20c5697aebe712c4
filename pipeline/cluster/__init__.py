"""A multi-process deployment on this machine: Dagster on PostgreSQL, runs through the daemon's
queue, steps on Celery workers through Redis, outputs in an S3-compatible store.

    python -m pipeline.cluster up [--workers 2] [--raw DIR]    (make cluster-up)
    python -m pipeline.cluster run                             (make cluster-run: the main job on it)
    python -m pipeline.cluster down [--purge]                  (make cluster-down)
"""
