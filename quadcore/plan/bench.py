"""The planner's test bench: simulated fleets on which two explanations are confused, and the
question whether one more flight -- the planned one, or one of the lab's existing trajectory
files flown for the same time -- makes the diagnosis rank the hidden truth first, untied.

Scenarios (:data:`SCENARIOS`; the truth alternates between the two sides with the seed, so a
plan that merely favours one side fails half the seeds):

* ``drag``: rotor drag against parasitic drag, on three flights of the lab's ``circle0`` at one
  timescale (one speed, ~0.6 m/s): at one speed ``k T v`` and ``c v²`` are the same force.
* ``mass``: thrust scale against added mass, on three hover flights: the rotors' torques are
  trims below the gyro noise, and the force of a weak thrust map is a payload's.
* ``lag``: motor lag against thrust delay, on three hover flights: on the torque channels the
  closed loop biased both fits and ranked the delay first; fitted and compared at the angular-rate
  level (:mod:`quadcore.identify.rates`) the hover flights decide it already, and the planned
  flight must keep it decided.
* ``lag_small``: the same with 2 ms, a size the rate level separates in-sample on these flights
  but the diagnosis does not reach: the residual stays within 10 % of the sensor-noise floor, so
  no timing candidate is found, before or after any added flight (docs/flight-planning.md: no
  realistic lag/delay tie at the command rate; below it the rate level does not decide,
  :func:`quadcore.identify.rates.below_command_rate`).
* ``lag_firmware``: the ``lag`` scenario with the sensor noise the Crazyflie's firmware leaves
  (``SensorNoise.lowpass_hz`` = 80 Hz, as the real logs' gyro noise is coloured): every flight,
  the old ones and the added one. The hover flights tied the lag-true seeds until the rate level
  whitened with the gyro's own noise (fa7af71; since, 1 of 5; none at 8171260, where the hovers
  decide 10 of 10); every manoeuvre decides them, the plan and circle0 by the largest separations
  (docs/flight-planning.md).
* ``lag_firmware_5ms``: the same at 5 ms: the hovers tie (the closed loop decides it); with the
  planned flight added the truth ranks first since a timing candidate is found at the angular-rate
  level (10 of 10 seeds; before, another effect ranked first: docs/flight-planning.md).
* ``lag_firmware_short``: ``lag_firmware`` on three 3 s hovers (take-off and 1 s of hover, 9 s
  of flight in all) instead of three 8 s ones: a fleet on which the lag and the delay genuinely
  tie (undecided in 9 of 10 seeds at 02e59b2 and 8f19a99; the 8 s hovers decide 10 of 10 at
  8171260), so the bench shows whether one added flight decides what the logged flights leave
  open rather than a margin on a decided question (docs/flight-planning.md).

Each outcome carries the separation in σ in favour of the truth, in the statistic the diagnosis
decides the pair by (:func:`quadcore.plan.separation.measured`); a timing trial also the
rate-level objective on the plan, each file and a hover (:class:`Added`).

Used by ``benchmarks/bench_plan.py`` (all seeds) and ``tests/test_plan.py`` (a few).
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from quadcore.identify import diagnosis as diagnosislib
from quadcore.identify.diagnosis.results import Diagnosis
from quadcore.logs import flight as flightlib
from quadcore.physics import vehicle as vehiclelib
from quadcore.plan import pieces, planner, question as questionlib, ratelevel, separation, signatures
from quadcore.plan.limits import Limits
from quadcore.sim import simulation, trajectories
from quadcore.sim.simulation import SensorNoise, SimConfig
from quadcore.spec.model import spec_from

FILES = ("figure8", "circle0", "yaw0")  # the lab's trajectory files (the simulator's built-in plans)
PLAN_S = 10.0  # the planned manoeuvre; flown with 2 s take-off, 1 s hover before and 1 s after
FIRMWARE_LOWPASS_HZ = 80.0  # the Crazyflie firmware's gyro low-pass (SensorNoise.lowpass_hz)
SHORT_HOVER_S = 3.0  # lag_firmware_short's hovers: 2 s take-off, 1 s hover


@dataclass(frozen=True)
class Scenario:
    pair: tuple[str, str]
    truths: tuple[dict[str, float], dict[str, float]]  # parameters of pair[0], pair[1]
    old: Callable[[int], list[SimConfig]]
    noise: SensorNoise = SensorNoise()  # every flight's sensor noise, the old ones' and the added one's

    @property
    def timing(self) -> bool:
        """A lag against a delay: decided at the angular-rate level."""
        return separation.timing_pair(*self.pair)


def _circles(seed: int) -> list[SimConfig]:
    return [SimConfig(kind="circle0", timescale=2.0, duration_s=10.0, seed=seed * 10 + k) for k in range(3)]


def _hover(seed: int, duration_s: float = 8.0) -> list[SimConfig]:
    return [SimConfig(kind="hover", duration_s=duration_s, seed=seed * 10 + k) for k in range(3)]


def _short_hover(seed: int) -> list[SimConfig]:
    return _hover(seed, SHORT_HOVER_S)


SCENARIOS = {
    "drag": Scenario(("rotor_drag", "parasitic_drag"),
                     ({"k_x_s_per_m": 0.1, "k_y_s_per_m": 0.1}, {"c_xy_kg_per_m": 0.01, "c_z_kg_per_m": 0.01}),
                     _circles),
    "mass": Scenario(("thrust_scale", "added_mass"), ({"scale": 0.92}, {"m_p_kg": 0.003}), _hover),
    "lag": Scenario(("motor_lag", "thrust_delay"), ({"tau_s": 0.01}, {"t_d_s": 0.01}), _hover),
    "lag_small": Scenario(("motor_lag", "thrust_delay"), ({"tau_s": 0.002}, {"t_d_s": 0.002}), _hover),
    "lag_firmware": Scenario(("motor_lag", "thrust_delay"), ({"tau_s": 0.01}, {"t_d_s": 0.01}), _hover,
                             SensorNoise(lowpass_hz=FIRMWARE_LOWPASS_HZ)),
    "lag_firmware_5ms": Scenario(("motor_lag", "thrust_delay"), ({"tau_s": 0.005}, {"t_d_s": 0.005}), _hover,
                                 SensorNoise(lowpass_hz=FIRMWARE_LOWPASS_HZ)),
    "lag_firmware_short": Scenario(("motor_lag", "thrust_delay"), ({"tau_s": 0.01}, {"t_d_s": 0.01}), _short_hover,
                                   SensorNoise(lowpass_hz=FIRMWARE_LOWPASS_HZ)),
}


@dataclass(frozen=True)
class Outcome:
    """What the diagnosis says about the truth: ranked first, and tied (or alike) with the rival;
    ``sigma`` the separation in favour of the truth, in the statistic the diagnosis decides the
    pair by (:func:`quadcore.plan.separation.measured`: the held-out t; negative: the rival fits
    better)."""

    top: str
    first: bool
    tied: bool
    alike: bool
    sigma: float = float("nan")
    undecided: str = ""  # why the diagnosis prefers neither whatever the held-out t (sigma 0 then)
    undecided_by: str = ""  # what decides it in its place: "the noise model", "the closed loop" (Comparison's)
    t: float = float("nan")  # the held-out t in favour of the truth, set aside or not (sigma where it decides)

    @property
    def decided(self) -> bool:
        """The truth ranked first and no longer tied with the rival."""
        return self.first and not self.tied

    def describe(self) -> str:
        tie = ", tied" if self.tied else (", alike" if self.alike else "")
        return f"top {self.top}{tie}, {self.sigma:+.1f} σ" + (f", undecided ({self.why_undecided})" if self.undecided
                                                             else "")

    @property
    def why_undecided(self) -> str:
        """What decides the pair where the diagnosis prefers neither, in a few words ("" when it
        goes by sigma; for a trial written before it was recorded, read from the sentence)."""
        if not self.undecided:
            return ""
        if self.undecided_by:
            return self.undecided_by.removeprefix("the ")
        return next((w for w in ("closed loop", "noise model") if w in self.undecided), "undecided")


def outcome(diag: Diagnosis, truth: str, rival: str, tables: dict, spec) -> Outcome:
    row = next(c for c in diag.candidates if c.effect == truth)
    top = diag.candidates[0].effect
    comp = separation.measured(tables, spec, diag, truth, rival)
    return Outcome(top, top == truth, rival in row.tied_with, rival in row.indistinguishable_from,
                   comp.sigma_for(truth), comp.undecided, comp.undecided_by, comp.t if truth == comp.a else -comp.t)


def _decode(folder: Path) -> dict:
    return {p.name: flightlib.decode_flight(p).tables["fixedFrequency"] for p in flightlib.discover_logs(folder)}


@dataclass(frozen=True)
class Added:
    """What one added flight is predicted to add at the rate level
    (:meth:`quadcore.plan.ratelevel.RateSeparation.own`): per truth the expected t of its blocks
    alone, its length, and the design's separation with it."""

    flight: str
    seconds: float
    own: dict[str, float]
    after: float

    def per_second(self) -> float:
        """The smaller over the truths of ``t²`` per second of flight (``t²`` adds over blocks)."""
        return min(t**2 for t in self.own.values()) / self.seconds


@dataclass(frozen=True)
class Trial:
    """One seed of a scenario: the truth, the diagnosis before, with the planned flight, and
    with each trajectory file flown for the same time; the plan's description and prediction."""

    scenario: str
    seed: int
    truth: str
    before: Outcome
    planned: Outcome
    files: dict[str, Outcome]
    manoeuvre: str
    predicted_sigma: float  # the design's separation with the planned flight if the truth is true
    predicted_before: float  # the same on the old flights alone
    added: tuple[Added, ...] = ()  # a timing pair: the rate-level objective on the plan, each file and a hover
    limits: dict = field(default_factory=dict)  # the plan's limits (Limits.to_dict); {} in lines written before
    checked: dict = field(default_factory=dict)  # the plan's peaks, checked on its pieces (LimitCheck.to_dict)


def run(name: str, seed: int, files: tuple[str, ...] = FILES, log: Callable[[str], None] = lambda m: None,
        limits: Limits | None = None) -> Trial:
    """One trial (see the module): simulate the old flights with the truth, diagnose, plan
    (``--between`` the pair, no proof, within ``limits``: by default the planner's), fly the plan
    and each file with the truth, diagnose again."""
    sc = SCENARIOS[name]
    limits = limits or Limits()
    k = seed % 2
    truth, rival = sc.pair[k], sc.pair[1 - k]
    effects = {truth: sc.truths[k]}
    veh = vehiclelib.load()
    spec = spec_from(veh, [])
    old, before = old_flights(name, seed)
    with tempfile.TemporaryDirectory(prefix="quadcore-plan-bench-") as tmp:
        root = Path(tmp)
        plan = planner.plan(old, spec, before, planner.PlanRequest(sc.pair, None, limits, PLAN_S, prove=False,
                                                                   seed=seed))
        assert plan.trajectory is not None and plan.manoeuvre is not None
        log(f"{name} seed {seed}: truth {truth}; plan {plan.manoeuvre.describe()}")
        added = predicted_by_flight(plan.trajectory, old, before, spec, sc.pair, (*FILES, "hover")) if sc.timing else ()
        flown = {}
        csv = root / "plan.csv"

        pieces.write_csv(plan.trajectory, csv)
        start = plan.trajectory.evaluate(np.zeros(1))[0]
        total = plan.trajectory.duration_s + 4.0  # take-off 2 s, hover 1 s, end hover 1 s
        configs = {"planned": SimConfig(kind="plan", plan_file=str(csv), height_m=float(start[2]),
                                        seed=1000 + seed, name=signatures.PLANNED, noise=sc.noise)}
        configs.update({f: SimConfig(kind=f, duration_s=total, seed=1000 + seed, name=f, noise=sc.noise)
                        for f in files})  # (kind "hover": a hover flight of the same length)
        for label, cfg in configs.items():
            simulation.write_flight(simulation.simulate(cfg, veh, effects), root / "new" / label / label)
            tables = {**old, label: _decode(root / "new" / label)[label]}
            flown[label] = outcome(diagnosislib.diagnose(tables, spec), truth, rival, tables, spec)
    return Trial(name, seed, truth, outcome(before, truth, rival, old, spec), flown.pop("planned"), flown,
                 plan.manoeuvre.describe(), float(plan.design["after"]["by_truth"][truth]["sigma"]),
                 float(plan.design["before"]["by_truth"][truth]["sigma"]), added, limits.to_dict(),
                 plan.checked.to_dict() if plan.checked is not None else {})


def old_flights(name: str, seed: int) -> tuple[dict, Diagnosis]:
    """A scenario's old flights, simulated with the seed's truth (decoded tables), and their diagnosis."""
    sc = SCENARIOS[name]
    k = seed % 2
    veh = vehiclelib.load()
    with tempfile.TemporaryDirectory(prefix="quadcore-plan-bench-") as tmp:
        simulation.simulate_set(Path(tmp), [replace(c, noise=sc.noise) for c in sc.old(seed)],
                                {sc.pair[k]: sc.truths[k]}, veh)
        old = _decode(Path(tmp))
    return old, diagnosislib.diagnose(old, spec_from(veh, []))


def predicted_by_flight(planned: trajectories.PolyTrajectory, old: dict, before: Diagnosis, spec,
                        pair: tuple[str, str], files: tuple[str, ...]) -> tuple[Added, ...]:
    """For a timing pair: the rate-level objective (:class:`quadcore.plan.ratelevel.RateSeparation`)
    on the ``planned`` path and on each of ``files`` (the lab's trajectory as written; ``hover``:
    a hover as long as the plan), each with the logged flights' closed-loop rotor activity, as
    the search scores its candidates."""
    a, b = (questionlib.explanation(before, n) for n in pair)
    flights = planner.fitting_flights(old, spec)
    obj = planner.separation_objective(a, b, flights, before, spec.vehicle)
    assert isinstance(obj, ratelevel.RateSeparation)
    loop = signatures.activity(list(flights.values()))
    paths = {"planned": planned,
             **{f: hover_path(planned) if f == "hover" else trajectories.load_plan(f) for f in files}}
    out = []
    for label, traj in paths.items():
        fd = signatures.planned_flight(traj, spec.vehicle, loop)
        out.append(Added(label, traj.duration_s, obj.own(fd), obj.evaluate(fd).sigma))
    return tuple(out)


def hover_path(like: trajectories.PolyTrajectory) -> trajectories.PolyTrajectory:
    """A hover at ``like``'s first point for as long as ``like``."""
    start = like.evaluate(np.zeros(1))[0]
    coeffs = np.zeros((1, 4, 8))
    coeffs[0, :, 0] = start
    return trajectories.PolyTrajectory("hover", np.array([like.duration_s]), coeffs)
