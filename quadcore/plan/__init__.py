"""Which flight to fly next: the flight that separates what the logged flights cannot tell apart.

From a diagnosis (:mod:`quadcore.identify.diagnosis`) to a trajectory the lab can upload, one
module per idea: the question (:mod:`~quadcore.plan.question`), the manoeuvre family
(:mod:`~quadcore.plan.family`) as 7th-order pieces (:mod:`~quadcore.plan.pieces`), the state
along it (:mod:`~quadcore.plan.flatness`) and its limits (:mod:`~quadcore.plan.limits`), what each
explanation predicts there (:mod:`~quadcore.plan.signatures`), the separation objective
(:mod:`~quadcore.plan.objective`), the search (:mod:`~quadcore.plan.search`), the measured
separation (:mod:`~quadcore.plan.separation`), the proof in the simulator
(:mod:`~quadcore.plan.proof`), the outputs (:mod:`~quadcore.plan.output`), and the planner that
joins them (:mod:`~quadcore.plan.planner`). Explained in ``docs/flight-planning.md``.
"""

# The modules other packages import (the public surface; importing the package imports none of them).
__all__ = ["limits", "output", "pieces", "planner", "question"]
