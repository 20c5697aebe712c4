"""Dagster wiring for quadcore: assets, partitions, sensors, resources. No physics here."""
