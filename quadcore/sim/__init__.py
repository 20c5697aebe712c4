"""Simulated flights, for tests and for checking what the identification recovers: the simulator
(``simulation``), its position/attitude controller (``controller``) and reference trajectories
(``trajectories``; the CSV files live in ``quadcore/trajectories/``)."""
