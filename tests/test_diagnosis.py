"""The diagnosis finds the effect a simulated vehicle was flown with, recovers its parameters,
and is honest where the data cannot decide; the ``quadcore diagnose`` contract; user effects.

Every flight set here is simulated once per session (closed loop, real log format, real
noise levels; :mod:`quadcore.sim.simulation`) with ONE effect switched on, then diagnosed with
the nominal model (cross-validation over flights), and again with that effect in the model.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import re
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import snapshot

from quadcore import cli, effects
from quadcore.identify import diagnosis, evidence, flightdata, model, rates
from quadcore.identify.fit import model_fit
from quadcore.logs import flight
from quadcore.physics import vehicle
from quadcore.sim import simulation
from quadcore.sim.simulation import SimConfig
from quadcore.spec.model import ModelFileError, load_model_file, spec_from

VEHICLE = vehicle.load()
REPO = Path(__file__).resolve().parents[1]
LINEAR_DRAG = REPO / "examples" / "effects" / "linear_drag.py"
DURATION_S = 8.0


def _fast(seed: int, **kw) -> SimConfig:
    """Random go-to flight at 0.8-1.5 m/s: excites drag, attitude, thrust changes."""
    return SimConfig(kind="random", duration_s=DURATION_S, seed=seed, speed_min_mps=0.8, speed_max_mps=1.5, **kw)


def _low(seed: int, **kw) -> SimConfig:
    """Repeated passes at 3-8 cm over the ground."""
    return SimConfig(kind="low_pass", duration_s=DURATION_S, seed=seed, **kw)


STANDARD = (_fast(1), _fast(2), _low(3))

# hidden effect -> (true parameters, flights, the parameters that must be recovered,
#                   where it acts: [(channel, axes)])
# Values: realistic for a 35 g quadrotor, a few times what the real logs show where they show it.
CASES = {
    # real logs: k = 0.036-0.04 s/m; anisotropic here to check both axes are recovered (the axial
    # k_z: test_rotor_drag_with_its_vertical_part_at_rotorpys_size_is_one_effect)
    "rotor_drag": ({"k_x_s_per_m": 0.12, "k_y_s_per_m": 0.10}, STANDARD,
                   ["k_x_s_per_m", "k_y_s_per_m"], [("force", (0, 1))]),
    # ½ρC_dA of a ~0.01 m² frame with C_d ~ 1.5: ~0.01 kg/m
    "parasitic_drag": ({"c_xy_kg_per_m": 0.01, "c_z_kg_per_m": 0.015}, STANDARD,
                       ["c_xy_kg_per_m", "c_z_kg_per_m"], [("force", (0, 1, 2))]),
    # k_ge = 6: +10 % thrust at 4 cm
    "ground_effect": ({"k_ge": 6.0}, (_low(4), _low(5), _fast(6)), ["k_ge"], [("force", (2,))]),
    # brushed 7 mm motors: 20-50 ms
    "motor_lag": ({"tau_s": 0.03}, STANDARD, ["tau_s"], [("force", (2,)), ("torque", (0, 1, 2))]),
    # a battery 3 mm forward and 2 mm right of the rotor centre
    "com_offset": ({"x_c_m": 0.003, "y_c_m": -0.002}, STANDARD, ["x_c_m", "y_c_m"], [("torque", (0, 1))]),
    # the real logs suggest ~0.92. Its yaw torque, 8 % of the rotors' ~35 uN m, is at the
    # gyro-derivative noise (1.5 uN m): roll and pitch carry the torque signature
    "thrust_scale": ({"scale": 0.92}, STANDARD, ["scale"], [("force", (2,)), ("torque", (0, 1))]),
    # 3 g of markers or a deck
    "added_mass": ({"m_p_kg": 0.003}, STANDARD, ["m_p_kg"], [("force", (2,))]),
    # a steady 1.1 m/s draught
    "wind": ({"k_s_per_m": 0.1, "w_x_mps": 1.0, "w_y_mps": -0.5}, STANDARD,
             ["k_s_per_m", "w_x_mps", "w_y_mps"], [("force", (0, 1))]),
    # a propeller 4 % strong, one 3 % weak, ...: the yaw torque gives it away
    "rotor_imbalance": ({"d_1": 0.04, "d_2": -0.03, "d_3": 0.02}, STANDARD, ["d_1", "d_2", "d_3"],
                        [("torque", (0, 1, 2))]),
    # 20 ms between the logged PWM and the thrust
    "thrust_delay": ({"t_d_s": 0.02}, STANDARD, ["t_d_s"], [("force", (2,)), ("torque", (0, 1, 2))]),
    # a battery mounted differently: the diagonal of J off by 10-30 %
    "inertia_scale": ({"s_x": 1.3, "s_y": 0.85, "s_z": 1.3}, STANDARD, ["s_x", "s_y", "s_z"], [("torque", (0, 1, 2))]),
}
TWO = {"rotor_drag": {"k_x_s_per_m": 0.1, "k_y_s_per_m": 0.1}, "com_offset": {"x_c_m": 0.003, "y_c_m": -0.002}}


def _decode(folder: Path) -> dict:
    return {p.name: flight.decode_flight(p).tables["fixedFrequency"] for p in flight.discover_logs(folder)}


@pytest.fixture(scope="session")
def sim_sets(tmp_path_factory):
    """Factory ``sim_sets(key, configs, effects) -> (folder, decoded tables)``, simulated once."""
    cache: dict = {}

    def get(key: str, configs, effs: dict):
        if key not in cache:
            folder = tmp_path_factory.mktemp(f"sim_{key}")
            simulation.simulate_set(folder, list(configs), effs, VEHICLE)
            cache[key] = (folder, _decode(folder))
        return cache[key]

    return get


def _diagnose(tables: dict, effect_names=(), holdout=None, candidates=None) -> dict:
    return diagnosis.diagnose(tables, spec_from(VEHICLE, list(effect_names)), holdout, candidates).to_dict()


def _rmse(result: dict, channel: str) -> np.ndarray:
    return np.array(result["baseline"]["force_rmse_N" if channel == "force" else "torque_rmse_Nm"])


def _assert_recovered(row: dict, truth: dict, names: list[str], effect: str, rel: float = 0.15) -> None:
    """Within ``rel`` of the truth, measured from 'no effect' (a thrust scale of 0.92 must come
    out as 0.92 ± 15 % of 0.08, not of 0.92)."""
    default = effects.get(effect).defaults()
    for name in names:
        true_dev, got_dev = truth[name] - default[name], row["parameters"][name] - default[name]
        assert abs(got_dev - true_dev) <= rel * abs(true_dev), (
            f"{effect}.{name}: fitted {row['parameters'][name]:.5g}, true {truth[name]:.5g}")


@pytest.fixture(scope="session")
def hidden(sim_sets):
    """Factory ``hidden(name) -> (nominal diagnosis, diagnosis with the effect in the model)``."""
    cache: dict = {}

    def get(name: str):
        if name not in cache:
            params, configs, _, _ = CASES[name]
            _, tables = sim_sets(name, configs, {name: params})
            every = list(effects.builtin_names()) if not effects.get(name).offered else None  # ranked among all
            cache[name] = (_diagnose(tables, candidates=every),
                           _diagnose(tables, [name], candidates=[n for n in every if n != name] if every else None))
        return cache[name]

    return get


# ---------------------------------------------------------------------------------------
# One hidden effect at a time
# ---------------------------------------------------------------------------------------

# The fast tier keeps rotor drag; the other effects run in the whole suite.
@pytest.mark.parametrize("name", [n if n == "rotor_drag" else pytest.param(n, marks=pytest.mark.slow) for n in CASES])
def test_hidden_effect_is_found_recovered_and_removes_the_residual(hidden, name):
    truth, _, names, acts = CASES[name]
    nominal, with_it = hidden(name)
    _check_evidence(nominal)
    _check_evidence(with_it)
    top = nominal["candidates"][0]
    # (a) ranked first, and the verdict names it
    assert top["effect"] == name, [(r["effect"], round(r["score"], 3)) for r in nominal["candidates"]]
    assert nominal["verdict"].startswith(f"Most likely missing: {name}:"), nominal["verdict"]
    assert top["useful"] and top["physical"] and top["significant"]
    assert top["explained_variance"] > 0.9
    # (b) its parameters, within 15 %
    _assert_recovered(top, truth, names, name)
    # (c) with it in the model, the held-out residual where it acts falls by at least half
    assert with_it["effects_in_model"] == [name]
    assert name not in [r["effect"] for r in with_it["candidates"]]
    for channel, axes in acts:
        before, after = _rmse(nominal, channel)[list(axes)], _rmse(with_it, channel)[list(axes)]
        assert np.all(after <= 0.5 * before), (name, channel, before, after)
    # ... and then nothing of the library explains what is left
    assert not any(r["useful"] for r in with_it["candidates"]), with_it["verdict"]
    assert with_it["verdict"].startswith("No effect of the library explains"), with_it["verdict"]


# Flights that begin in a manoeuvre (an independent simulator's start on a moving trajectory):
# five fast go-to flights start 0.1-0.16 m off the reference's start, so the first commands are a
# hard correction while the rotors still give hover thrust; a low pass starts at rest
_FAST = SimConfig(kind="random", duration_s=8.0, speed_min_mps=1.0, speed_max_mps=1.5)
MID_MANOEUVRE = (replace(_FAST, seed=1, start_offset_m=(0.12, -0.08, 0.05)),
                 replace(_FAST, seed=2, start_offset_m=(-0.1, 0.12, 0.05)),
                 replace(_FAST, seed=3, start_offset_m=(0.08, 0.1, 0.05)),
                 replace(_FAST, seed=4, start_offset_m=(-0.12, -0.1, 0.05)),
                 replace(_FAST, seed=6, start_offset_m=(0.1, -0.12, 0.05)),
                 _low(5))


@pytest.mark.slow  # simulated scenarios of their own
@pytest.mark.parametrize("name, truth", [("motor_lag", {"tau_s": 0.04}), ("thrust_delay", {"t_d_s": 0.02})])
def test_lag_and_delay_fits_on_flights_starting_mid_manoeuvre_cover_the_truth(sim_sets, name, truth):
    """A motor lag and a delay on flights that begin in a manoeuvre: the filter cannot start at
    steady state on the first command there, so the fits leave out its settling
    (Effect.memory_s), and the error bars come from the profile of the objective (not its
    curvature). The truth lies within 3 σ, as the candidate and as the model's fitted effect.
    On main at 5464bb9 (steady state assumed at the log's start, error bars from the curvature)
    the lag came out 0.03947 ± 0.00012 s, 4.4 σ low (now 0.03982 ± 0.00036), the delay
    0.02021 ± 0.00009 s, 2.2 σ high (now 0.01997 ± 0.00016)."""
    (param, true), = truth.items()
    _, tables = sim_sets(f"mid_{name}", MID_MANOEUVRE, {name: truth})
    d = _diagnose(tables)
    row = d["candidates"][0]
    assert row["effect"] == name and row["found"], d["verdict"]
    assert abs(row["parameters"][param] - true) <= 3 * row["parameter_std"][param], row
    fitted = model_fit.fit_model(spec_from(VEHICLE, [name]), tables, sorted(tables)).terms[0]
    assert abs(fitted.params[param] - true) <= 3 * fitted.std[param], (fitted.params, fitted.std)


@pytest.mark.slow  # a simulated scenario of its own
def test_rotor_drag_with_its_vertical_part_at_rotorpys_size_is_one_effect(sim_sets):
    """An independent simulator's case (rotorpy's Crazyflie: vertical rotor drag 0.0054 kg/s at
    hover, k_z = 0.02 s/m) on this one: horizontal and vertical rotor drag hidden. rotor_drag
    (``-T diag(k_x, k_y, k_z) v``) is first with all three within 3 σ, no thrust scale or added
    mass is invented, and every candidate's fit lies within its bounds (a bound held in noise is
    said so); with rotor_drag in the model nothing is left to find."""
    truth = {"k_x_s_per_m": 0.1, "k_y_s_per_m": 0.1, "k_z_s_per_m": 0.02}
    _, tables = sim_sets("drag_xyz", STANDARD, {"rotor_drag": truth})
    d = _diagnose(tables)
    top = d["candidates"][0]
    assert top["effect"] == "rotor_drag" and top["found"], d["verdict"]
    for k, v in truth.items():
        assert abs(top["parameters"][k] - v) <= 3 * top["parameter_std"][k], top
    by = {r["effect"]: r for r in d["candidates"]}
    assert not by["thrust_scale"]["found"] and not by["added_mass"]["found"]
    assert not [r["effect"] for r in _diagnose(tables, ["rotor_drag"])["candidates"] if r["found"]]
    for r in d["candidates"]:
        p = {q.name: q for q in effects.get(r["effect"]).parameters}
        assert all(p[k].lower <= v <= p[k].upper for k, v in r["parameters"].items()), r  # every fit within bounds
        for k, v in r["active_bounds"].items():
            assert v in (p[k].lower, p[k].upper) and r["parameters"][k] == v
            assert any(f"{k} held at its bound" in n for n in r["notes"]), r["notes"]
        if not r["physical"]:
            assert any("by more than 3 standard errors" in n for n in r["notes"]), r["notes"]


@pytest.mark.slow  # a simulated scenario of its own
def test_thrust_scale_and_added_mass_are_alike_in_force_and_the_torque_decides(hidden):
    """Less thrust than mapped and more mass than assumed give the SAME force residual,
    ``-c T`` along body z: in force alone they cannot be told apart, and the diagnosis says so.
    Only a thrust scale also scales the rotors' torques; on fast flights the gyros see it."""
    nominal, _ = hidden("thrust_scale")
    top, second = nominal["candidates"][:2]
    assert (top["effect"], second["effect"]) == ("thrust_scale", "added_mass")
    assert "added_mass" in top["indistinguishable_from"] and "thrust_scale" in second["indistinguishable_from"]
    assert top["separated_by"]["added_mass"] == "torque"
    assert second["explained_variance_force"] > 0.95  # added mass explains the force just as well ...
    assert top["explained_variance_torque"] > 0.8
    assert abs(second["explained_variance_torque"]) < 0.01  # ... not the torque
    assert "indistinguishable from added_mass" in nominal["verdict"] and "torque" in nominal["verdict"]
    # the payload that would explain the force: c = m_p / (m + m_p) = 1 - scale
    c = second["parameters"]["m_p_kg"] / (VEHICLE.mass_kg + second["parameters"]["m_p_kg"])
    assert c == pytest.approx(1 - CASES["thrust_scale"][0]["scale"], rel=0.15)

    nominal, _ = hidden("added_mass")
    top = nominal["candidates"][0]
    assert top["effect"] == "added_mass"
    assert "thrust_scale" in top["indistinguishable_from"] and top["separated_by"]["thrust_scale"] == "torque"
    assert "indistinguishable from thrust_scale" in nominal["verdict"]
    ts = next(r for r in nominal["candidates"] if r["effect"] == "thrust_scale")
    assert ts["score"] < top["score"] - evidence.TIE_MARGIN  # a thrust scale would leave a torque error


def test_in_hover_thrust_scale_and_added_mass_are_an_honest_tie(sim_sets):
    """In hover the rotors' torques are tiny (the controller only trims), so 8 % of them is
    below the gyro-derivative noise: nothing in this data can tell a weak thrust map from a
    payload. The diagnosis must call it a tie, not pick one; both fits must be right."""
    hover = [SimConfig(kind="hover", duration_s=DURATION_S, seed=s) for s in (7, 8)]
    _, tables = sim_sets("thrust_scale_hover", hover, {"thrust_scale": CASES["thrust_scale"][0]})
    result = _diagnose(tables)
    assert result["at_noise_level"] == {"force": False, "torque": True}
    first, second = result["candidates"][:2]
    assert {first["effect"], second["effect"]} == {"thrust_scale", "added_mass"}
    assert second["effect"] in first["tied_with"] and first["effect"] in second["tied_with"]
    assert "cannot tell it apart from" in result["verdict"]
    ts, am = (first, second) if first["effect"] == "thrust_scale" else (second, first)
    _assert_recovered(ts, CASES["thrust_scale"][0], ["scale"], "thrust_scale")
    s = CASES["thrust_scale"][0]["scale"]  # the payload with the same force: c = m_p / (m + m_p) = 1 - s
    _assert_recovered(am, {"m_p_kg": (1 - s) * VEHICLE.mass_kg / s}, ["m_p_kg"], "added_mass")
    # and the closed loop's reaction to gyro noise is not mistaken for a motor lag
    assert not next(r for r in result["candidates"] if r["effect"] == "motor_lag")["useful"]


@pytest.mark.slow  # a simulated scenario of its own
def test_rotor_drag_and_a_still_air_wind_are_a_tie_decided_by_parsimony(hidden):
    """With no wind, the wind effect IS rotor drag (w = 0): the diagnosis must say it cannot
    tell them apart, and put the model with fewer parameters first."""
    nominal, _ = hidden("rotor_drag")
    top = nominal["candidates"][0]
    wind = next(r for r in nominal["candidates"] if r["effect"] == "wind")
    assert top["effect"] == "rotor_drag" and "wind" in top["tied_with"] and "rotor_drag" in wind["tied_with"]
    assert nominal["candidates"][1]["effect"] == "wind"
    assert "cannot tell it apart from wind" in nominal["verdict"]
    assert abs(wind["parameters"]["w_x_mps"]) < 0.1 and abs(wind["parameters"]["w_y_mps"]) < 0.1

    # a real wind is not rotor drag: a force that does not vanish at zero ground speed
    nominal, _ = hidden("wind")
    top = nominal["candidates"][0]
    assert top["effect"] == "wind" and "rotor_drag" not in top["indistinguishable_from"]
    rd = next(r for r in nominal["candidates"] if r["effect"] == "rotor_drag")
    assert rd["explained_variance"] < 0.5


@pytest.mark.slow  # a simulated scenario of its own
def test_a_weak_effect_below_the_old_noise_threshold_is_found_not_called_noise(sim_sets):
    """Rotor drag at k = 0.008 s/m (a fifth of a real Crazyflie's) on three flights: its force
    is about the size of the accelerometer noise. It must be reported as found -- small but
    certain, or clear -- with k within 15 %, not as "nothing left"."""
    truth = {"k_x_s_per_m": 0.008, "k_y_s_per_m": 0.008}
    _, tables = sim_sets("weak_drag", STANDARD, {"rotor_drag": truth})
    result = _diagnose(tables)
    _check_evidence(result)
    assert result["residual_to_noise"]["force"] < 2.0  # the old threshold called this "noise"
    top = result["candidates"][0]
    assert top["effect"] == "rotor_drag" and top["found"] and top["status"] == "found", result["verdict"]
    assert top["grade"] in ("small but certain", "clear")
    assert top["explained_above_noise"] > 0.8
    _assert_recovered(top, truth, list(truth), "rotor_drag")
    assert result["verdict"].startswith("Most likely missing: rotor_drag:"), result["verdict"]
    assert "nothing left" not in result["verdict"]
    # the found drag is not a yardstick for itself: what could still hide is below the truth
    assert result["sensitivity"]["rotor_drag"]["k_x_s_per_m"] < truth["k_x_s_per_m"]


@pytest.mark.slow  # a simulated scenario of its own
def test_a_delay_and_a_lag_are_told_apart_by_the_data(hidden):
    """A pure delay and a first-order lag shift the phase of slow thrust changes alike; only
    the lag also damps the fast ones. On flights with fast thrust changes the data prefer
    the right one by more than a tie, and say that the other is the alternative."""
    delay, _ = hidden("thrust_delay")
    top, lag = delay["candidates"][0], next(r for r in delay["candidates"] if r["effect"] == "motor_lag")
    assert top["effect"] == "thrust_delay" and "motor_lag" not in top["tied_with"]
    assert lag["score"] < top["score"] - evidence.TIE_MARGIN
    assert "motor_lag" in delay["verdict"]
    lagged, _ = hidden("motor_lag")
    top, late = lagged["candidates"][0], next(r for r in lagged["candidates"] if r["effect"] == "thrust_delay")
    assert top["effect"] == "motor_lag" and "thrust_delay" not in top["tied_with"]
    assert late["score"] < top["score"] - evidence.TIE_MARGIN
    assert "thrust_delay" in lagged["verdict"]


@pytest.mark.slow  # a simulated scenario of its own
def test_hidden_rotor_inertia_is_found_beside_a_motor_lag(sim_sets):
    """Rotor inertia flown with the motor lag it needs (see test_simulation), the lag in the
    model: the diagnosis names the rotors' spin-up torque and recovers J_r."""
    truth = {"J_r_kgm2": 3e-8}
    _, tables = sim_sets("rotor_inertia", STANDARD, {"motor_lag": {"tau_s": 0.02}, "rotor_inertia": truth})
    result = _diagnose(tables, ["motor_lag"])
    top = result["candidates"][0]
    assert top["effect"] == "rotor_inertia" and top["useful"], result["verdict"]
    assert top["explained_variance_torque"] > 0.8
    _assert_recovered(top, truth, ["J_r_kgm2"], "rotor_inertia")
    assert result["model"]["effects"][0]["params"]["tau_s"] == pytest.approx(0.02, rel=0.15)



@pytest.mark.slow  # the scenario above, diagnosed twice
def test_a_lag_model_diagnosed_from_statistics_ranks_as_from_rows(sim_sets, monkeypatch):
    """The same scenario with the lag in the model diagnosed from statistics (the lag's prediction a
    column from its profile) and from rows (the reference, forced): the same ranking and verdict
    (its figures aside), the found candidate's parameter within a tenth of its standard error, the lag within
    the row search's tolerance (xatol, 5e-4 of the span)."""
    truth = {"J_r_kgm2": 3e-8}
    _, tables = sim_sets("rotor_inertia", STANDARD, {"motor_lag": {"tau_s": 0.02}, "rotor_inertia": truth})
    cands = ["rotor_inertia", "rotor_drag", "com_offset", "thrust_scale"]
    got = _diagnose(tables, ["motor_lag"], candidates=cands)
    from quadcore.identify.diagnosis import problem

    monkeypatch.setattr(model_fit, "from_statistics", lambda *a: False)  # the model's prediction made on rows
    monkeypatch.setattr(problem, "_fit_model", lambda p, train, sessions, log: problem._model_on_rows(
        p, train, sessions, log))  # and its fit: the row search
    ref = _diagnose(tables, ["motor_lag"], candidates=cands)
    assert [r["effect"] for r in got["candidates"]] == [r["effect"] for r in ref["candidates"]]
    assert [r["found"] for r in got["candidates"]] == [r["found"] for r in ref["candidates"]]
    def words(text: str) -> str:  # the verdict without its figures
        return re.sub(r"\d[\d.]*(e[-+]?\d+)?", "#", text)

    assert words(got["verdict"]) == words(ref["verdict"])
    top, top_ref = got["candidates"][0], ref["candidates"][0]
    assert abs(top["parameters"]["J_r_kgm2"] - top_ref["parameters"]["J_r_kgm2"]) <= 0.1 * top_ref["parameter_std"][
        "J_r_kgm2"]
    assert top["score"] == pytest.approx(top_ref["score"], abs=1e-3)
    lag, lag_ref = (r["model"]["effects"][0]["params"]["tau_s"] for r in (got, ref))
    assert abs(lag - lag_ref) <= 5e-4 * effects.get("motor_lag").parameters[0].upper

# ---------------------------------------------------------------------------------------
# Two hidden effects, and none
# ---------------------------------------------------------------------------------------

@pytest.fixture(scope="session")
def two_hidden(sim_sets):
    _, tables = sim_sets("two", STANDARD, TWO)
    return tables


@pytest.mark.slow  # a simulated scenario of its own
def test_two_hidden_effects_are_the_top_two_and_each_is_found_with_the_other_in_the_model(two_hidden):
    nominal = _diagnose(two_hidden)
    assert {r["effect"] for r in nominal["candidates"][:2]} == set(TWO)
    # each is said to be missing beyond the other, not an alternative to it
    first, second = nominal["candidates"][:2]
    assert second["explained_after_top"] > 0.9
    assert f"Also missing, beyond it: {second['effect']}" in nominal["verdict"]
    for known, missing in (("rotor_drag", "com_offset"), ("com_offset", "rotor_drag")):
        result = _diagnose(two_hidden, [known])
        top = result["candidates"][0]
        assert top["effect"] == missing, result["verdict"]
        names = [p for p, v in TWO[missing].items() if v != 0]
        _assert_recovered(top, TWO[missing], names, missing)
        fitted = result["model"]["effects"][0]
        assert fitted["name"] == known
        _assert_recovered({"parameters": fitted["params"]}, TWO[known], list(TWO[known]), known)


def test_no_hidden_effect_no_explanation(sim_sets):
    _, tables = sim_sets("none", STANDARD, {})
    result = _diagnose(tables)
    _check_evidence(result)
    assert result["verdict"].startswith("No effect of the library explains the residual"), result["verdict"]
    assert "sensor-noise floor" in result["verdict"] and "nothing left to explain" in result["verdict"]
    for r in result["candidates"]:
        assert not r["found"] and not r["useful"], r
        assert r["explained_variance"] < evidence.MIN_EXPLAINED or not r["significant"], r
    # what "nothing" means here: a rotor drag a tenth of the real Crazyflie's would have been seen
    assert 0 < result["sensitivity"]["rotor_drag"]["k_x_s_per_m"] < 0.004
    # the residual is at the sensor-noise level (~0.5 mN, ~2 uN m), and the diagnosis knows it
    assert max(result["baseline"]["force_rmse_N"]) < 1e-3
    assert max(result["baseline"]["torque_rmse_Nm"]) < 5e-6
    assert result["at_noise_level"] == {"force": True, "torque": True}
    np.testing.assert_allclose(result["noise_floor"]["force_rmse_N"], result["baseline"]["force_rmse_N"], rtol=0.2)
    np.testing.assert_allclose(result["noise_floor"]["torque_rmse_Nm"], result["baseline"]["torque_rmse_Nm"], rtol=0.2)


@pytest.mark.slow
def test_nothing_hidden_nothing_found_in_19_of_20_seeds(tmp_path):
    """The false-alarm rate the held-out test promises (1 % for the library), on 20 sets of
    three flights with nothing hidden: at most one may report an effect as found.
    (The detection side, 9 of 10 seeds at 2x the reported sensitivity, is benchmarks/bench_power.py.)"""
    alarms = []
    for seed in range(1, 21):
        folder = tmp_path / f"seed{seed}"
        simulation.simulate_set(folder, [_fast(100 * seed), _fast(100 * seed + 1), _low(100 * seed + 2)], {}, VEHICLE)
        result = _diagnose(_decode(folder))
        found = [r["effect"] for r in result["candidates"] if r["found"]]
        if found:
            alarms.append((seed, found))
    assert len(alarms) <= 1, alarms


# ---------------------------------------------------------------------------------------
# The command: quadcore diagnose DATA --json OUT.json [--effects ...] [--holdout ...]
# ---------------------------------------------------------------------------------------

def _run(argv) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main(argv)
    return code, out.getvalue(), err.getvalue()


def _check_contract(d: dict) -> None:
    assert isinstance(d["effects_in_model"], list)
    for key, n in (("force_rmse_N", 3), ("torque_rmse_Nm", 3)):
        v = d["baseline"][key]
        assert isinstance(v, list) and len(v) == n and all(isinstance(x, float) and x >= 0 for x in v)
    assert isinstance(d["candidates"], list) and d["candidates"]
    for r in d["candidates"]:
        assert isinstance(r["effect"], str) and r["target"] in ("force", "torque")
        assert isinstance(r["explained_variance"], float) and 0.0 <= r["explained_variance"] <= 1.0
        assert len(r["force_rmse_N"]) == 3 and len(r["torque_rmse_Nm"]) == 3
        known = {p.name for p in effects.get(r["effect"]).parameters}
        assert set(r["parameters"]) == known
        assert all(isinstance(v, float) and math.isfinite(v) for v in r["parameters"].values())
        assert isinstance(r["indistinguishable_from"], list)
    assert isinstance(d["regimes"], list) and d["regimes"] and {"regime", "bin", "samples"} <= set(d["regimes"][0])
    assert isinstance(d["verdict"], str) and d["verdict"]
    for dis in d["disagreements"]:  # [{effect, parameter, groups: [{flights, value, std}]}]
        assert {"effect", "parameter", "groups"} <= set(dis) and len(dis["groups"]) >= 2
        assert all({"flights", "value", "std"} <= set(g) and g["flights"] for g in dis["groups"])
    _check_evidence(d)


def _check_evidence(d: dict) -> None:
    """Every candidate says why it ranks where it does; a found one is physical and confirmed
    on held-out flights; an unphysical one is never found; every verdict carries the
    sensitivity of these flights, for every candidate and parameter."""
    for r in d["candidates"]:
        assert r["status"] in ("found", "tied", "alternative", "unphysical", "noise_level", "no_gain",
                               "not_significant", "partial"), r["status"]
        assert isinstance(r["reason"], str) and r["reason"]
        assert 0.0 <= r["held_out_p_value"] <= 1.0 and 0.0 <= r["explained_above_noise"] <= 1.0
        assert r["held_out_level"] in (r["target"], "angular rate"), r["held_out_level"]
        if r["found"]:
            assert r["physical"] and r["significant"] and r["held_out_p_value"] < r["held_out_alpha"]
            assert r["grade"] in ("large", "clear", "small but certain")
        if not r["physical"]:
            assert not r["found"] and r["status"] == "unphysical" and "unphysical" in r["reason"]
    phys = [r["physical"] for r in d["candidates"]]
    assert phys == sorted(phys, reverse=True)  # unphysical fits rank last
    assert set(d["sensitivity"]) == {r["effect"] for r in d["candidates"]}
    for r in d["candidates"]:
        params = effects.get(r["effect"]).parameters
        assert set(d["sensitivity"][r["effect"]]) == {p.name for p in params}
        for p in params:
            v = d["sensitivity"][r["effect"]][p.name]
            assert v is None or (isinstance(v, float) and 0 < v <= max(p.upper - p.default, p.default - p.lower))
    assert "would go unnoticed on these flights" in d["verdict"]


@pytest.fixture(scope="module")
def cli_folder(sim_sets):
    folder, _ = sim_sets("rotor_drag", CASES["rotor_drag"][1], {"rotor_drag": CASES["rotor_drag"][0]})
    return folder


def test_cli_diagnose_writes_the_json_contract(cli_folder, tmp_path):
    out = tmp_path / "d.json"
    code, stdout, stderr = _run(["diagnose", str(cli_folder), "--json", str(out)])
    assert code == 0, stderr
    d = json.loads(out.read_text())
    _check_contract(d)
    assert d["effects_in_model"] == [] and d["evaluation"]["mode"] == "cross-validation"
    # the key structure, pinned: a refactor that renames or drops a key fails here
    by_name = ("parameters", "parameter_std", "parameter_spread_between_flights", "separated_by", "sensitivity",
               "conditions", "active_bounds", "votes")  # maps keyed by effect or parameter names (data, not the
    # contract)
    shape = snapshot.json_shape(d, data_maps=by_name)
    snapshot.assert_matches(shape, "diagnose_json_keys.txt", "the JSON of `quadcore diagnose`",
                            "tests/test_diagnosis.py -k json_contract")
    assert d["candidates"][0]["effect"] == "rotor_drag"
    assert str(out) in stdout and "rotor_drag" in stdout


def test_cli_diagnose_holdout_and_effects(cli_folder, tmp_path):
    out = tmp_path / "h.json"
    code, _, stderr = _run(["diagnose", str(cli_folder), "--json", str(out), "--holdout", "sim001", "--quiet"])
    assert code == 0, stderr
    held = json.loads(out.read_text())
    _check_contract(held)
    assert held["evaluation"]["mode"] == "holdout"
    assert held["evaluation"]["eval_flights"] == ["sim001"]
    assert held["evaluation"]["train_flights"] == ["sim000", "sim002"]
    # one held-out flight may not separate rotor_drag (k_x, k_y, k_z) from parasitic_drag (two
    # parameters) significantly: then they tie, the one with fewer parameters is listed first, and
    # the verdict says the data cannot choose
    top, by = held["candidates"][0], {r["effect"]: r for r in held["candidates"]}
    assert by["rotor_drag"]["found"], held["verdict"]
    assert top["effect"] == "rotor_drag" or ("rotor_drag" in top["tied_with"]
                                             and "cannot tell it apart from" in held["verdict"]), held["verdict"]

    out = tmp_path / "e.json"
    code, _, stderr = _run(["diagnose", str(cli_folder), "--json", str(out), "--holdout", "sim001",
                            "--effects", "rotor_drag", "--quiet"])
    assert code == 0, stderr
    with_it = json.loads(out.read_text())
    _check_contract(with_it)
    assert with_it["effects_in_model"] == ["rotor_drag"]
    assert "rotor_drag" not in [r["effect"] for r in with_it["candidates"]]
    assert with_it["model"]["effects"][0]["name"] == "rotor_drag"
    for a in (0, 1):
        assert with_it["baseline"]["force_rmse_N"][a] < 0.5 * held["baseline"]["force_rmse_N"][a]


@pytest.fixture
def garbage_folder(tmp_path):
    folder = tmp_path / "garbage"
    folder.mkdir()
    (folder / "notalog").write_bytes(b"this is not a uSD log\x00\x01\x02" * 10)
    return folder


@pytest.mark.parametrize("case", ["missing folder", "no readable logs", "unknown effect", "unknown holdout"])
def test_cli_diagnose_bad_input_is_a_message_not_a_traceback(case, cli_folder, garbage_folder, tmp_path):
    out = tmp_path / "x.json"
    argv, message = {
        "missing folder": (["diagnose", str(tmp_path / "nope"), "--json", str(out)], "no such folder"),
        "no readable logs": (["diagnose", str(garbage_folder), "--json", str(out)], "fixedFrequency"),
        "unknown effect": (["diagnose", str(cli_folder), "--json", str(out), "--effects", "rotor_drag,bogus"],
                           "unknown effect 'bogus'"),
        "unknown holdout": (["diagnose", str(cli_folder), "--json", str(out), "--holdout", "jana99"],
                            "holdout flight(s) not found"),
    }[case]
    code, stdout, stderr = _run(argv)
    assert code != 0
    assert message in stderr, stderr
    assert "Traceback" not in stderr + stdout
    assert not out.exists()


# ---------------------------------------------------------------------------------------
# A user's effect: examples/effects/linear_drag.py
# ---------------------------------------------------------------------------------------

@pytest.fixture
def forget_linear_drag():
    """The test loads the plugin through model files; afterwards it is forgotten, so the
    registry of the other tests holds the built-in effects only."""
    yield
    effects.unregister("linear_drag")


LINEAR_DRAG_TRUTH = {"d_xy_kg_per_s": 0.04, "d_z_kg_per_s": 0.06}


def test_plugin_is_a_candidate_and_is_fitted(sim_sets, tmp_path, forget_linear_drag):
    """A model file's plugin is a candidate of that model's diagnosis, found and fitted like a
    built-in effect; in the same process, a model whose file does not list it is diagnosed
    without it (the default candidates are the library's and the model file's own plugins, not
    every effect the process has loaded: a long-lived process such as the Dagster UI reads
    many model files)."""
    with_plugin, without = tmp_path / "with_plugin.toml", tmp_path / "without.toml"
    with_plugin.write_text(f'vehicle = "crazyflie21"\nplugins = ["{LINEAR_DRAG.as_posix()}"]\n')
    without.write_text('vehicle = "crazyflie21"\n')
    spec = load_model_file(with_plugin)  # loads the plugin, which the simulation needs too
    _, tables = sim_sets("linear_drag", STANDARD[:2], {"linear_drag": LINEAR_DRAG_TRUTH})
    result = diagnosis.diagnose(tables, spec).to_dict()
    names = [r["effect"] for r in result["candidates"]]
    assert names[0] == "linear_drag", result["verdict"]
    _assert_recovered(result["candidates"][0], LINEAR_DRAG_TRUTH, list(LINEAR_DRAG_TRUTH), "linear_drag")

    other = diagnosis.diagnose(tables, load_model_file(without)).to_dict()
    names = [r["effect"] for r in other["candidates"]]
    assert "linear_drag" in effects.registry() and "linear_drag" not in names, names
    assert names and set(names) <= set(effects.builtin_names()), names

    # listed under plugins, named under effects: fitted like a built-in
    model_file = tmp_path / "model.toml"
    model_file.write_text(
        f'vehicle = "crazyflie21"\neffects = ["linear_drag"]\nplugins = ["{LINEAR_DRAG.as_posix()}"]\n')
    spec = load_model_file(model_file)
    assert spec.effects == ["linear_drag"]
    fitted = model_fit.fit_model(spec, tables, sorted(tables))
    _assert_recovered({"parameters": fitted.terms[0].params}, LINEAR_DRAG_TRUTH, list(LINEAR_DRAG_TRUTH),
                      "linear_drag")


def test_plugin_errors_are_clear(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("EFFECT = 3\n")
    with pytest.raises(effects.PluginError, match="no EFFECT"):
        effects.load_plugin(bad)
    broken = tmp_path / "broken.py"
    broken.write_text("import nonexistent_module_xyz\n")
    with pytest.raises(effects.PluginError, match="cannot import"):
        effects.load_plugin(broken)
    clash = tmp_path / "clash.py"
    clash.write_text(LINEAR_DRAG.read_text().replace('name = "linear_drag"', 'name = "rotor_drag"'))
    with pytest.raises(effects.PluginError, match="built-in"):
        effects.load_plugin(clash)
    assert effects.get("rotor_drag").__class__.__name__ == "RotorDrag"
    no_wrench = tmp_path / "no_wrench.py"
    no_wrench.write_text(LINEAR_DRAG.read_text().replace("def wrench(", "def not_the_wrench(")
                         .replace('"linear_drag"', '"no_wrench"'))
    with pytest.raises(effects.PluginError, match="abstract"):
        effects.load_plugin(no_wrench)
    bad_target = tmp_path / "bad_target.py"
    bad_target.write_text(LINEAR_DRAG.read_text().replace('target = "force"', 'target = "forces"')
                          .replace('"linear_drag"', '"bad_target"'))
    with pytest.raises(effects.PluginError, match="target 'forces'"):
        effects.load_plugin(bad_target)
    assert "no_wrench" not in effects.registry() and "bad_target" not in effects.registry()


def test_builtin_effects_are_the_modules_of_the_package():
    package = Path(effects.__file__).parent
    modules = {p.stem for p in package.glob("*.py")} - {"__init__", "base", "c_inputs", "ccode"}  # the C form and names
    assert set(effects.builtin_names()) == modules
    for name in effects.builtin_names():
        effect = effects.get(name)
        assert effect.name == name and effect.target in ("force", "torque", "both")


# ---------------------------------------------------------------------------------------
# The real logs
# ---------------------------------------------------------------------------------------

@pytest.mark.slow  # the real fleet
def test_real_logs_diagnosis_is_well_formed_and_physical(real_logs, tmp_path):
    out = tmp_path / "real.json"
    code, _, stderr = _run(["diagnose", str(real_logs), "--json", str(out), "--holdout", "jana02", "--quiet"])
    assert code == 0, stderr
    d = json.loads(out.read_text())  # strict JSON: no NaN or Infinity
    json.loads(out.read_text(), parse_constant=lambda c: pytest.fail(f"non-finite number {c} in the JSON"))
    _check_contract(d)
    assert d["evaluation"]["eval_flights"] == ["jana02"] and len(d["evaluation"]["train_flights"]) == 18
    assert len(d["candidates"]) == len([n for n in effects.builtin_names() if effects.get(n).offered])
    f, t = np.array(d["baseline"]["force_rmse_N"]), np.array(d["baseline"]["torque_rmse_Nm"])
    assert np.all((f > 1e-3) & (f < 0.1)) and np.all((t > 1e-6) & (t < 1e-2))  # mN and uN m to mN m scale
    top = d["candidates"][0]
    assert top["physical"] and top["useful"]
    for p in effects.get(top["effect"]).parameters:
        assert p.lower <= top["parameters"][p.name] <= p.upper
    # the thrust-vs-mass ambiguity is flagged when they top the list
    if top["effect"] in ("thrust_scale", "added_mass"):
        other = "added_mass" if top["effect"] == "thrust_scale" else "thrust_scale"
        if next(r for r in d["candidates"] if r["effect"] == other)["useful"]:
            assert other in top["indistinguishable_from"], top
            assert other in d["verdict"], d["verdict"]
    # unphysical fits are never ranked above physical ones, nor found (checked in _check_contract)
    phys = [r["physical"] for r in d["candidates"]]
    assert phys == sorted(phys, reverse=True)


@pytest.mark.slow  # a simulated scenario of its own
def test_frequency_view_shows_a_hidden_lag_as_timing(hidden):
    """A motor lag the model lacks: at 2-10 Hz the modelled and measured torque stay
    coherent, but the measurement lags (first order, 30 ms: -54° and gain 0.59 at 7.5 Hz)."""
    nominal, with_it = hidden("motor_lag")
    freq = nominal["frequency"]
    bands = [tuple(b) for b in freq["bands_hz"]]
    k = bands.index((5.0, 10.0))
    for channel in ("torque_x", "torque_y"):
        row = next(r for r in freq["channels"] if r["channel"] == channel)
        assert row["coherence"][k] > 0.8, row
        assert -80 < row["phase_deg"][k] < -30, row
        assert 0.4 < row["gain"][k] < 0.8, row
        assert abs(sum(row["residual_share"]) + row["mean_share"] - 1) < 0.1
    fixed = next(r for r in with_it["frequency"]["channels"] if r["channel"] == "torque_x")
    assert abs(fixed["phase_deg"][k]) < 15 and abs(fixed["gain"][k] - 1) < 0.15, fixed
    assert any("late or early" in line for line in freq["reading"]), freq["reading"]


# ---------------------------------------------------------------------------------------
# Parameters that differ between sessions
# ---------------------------------------------------------------------------------------

SESSION_SCALES = {"early": 0.95, "late": 0.88}


@pytest.fixture(scope="session")
def two_sessions(sim_sets):
    """Three fast flights at each of two thrust scales (another battery, other propellers)."""
    configs = [_fast(30 + i) for i in range(6)]
    effs = [{"thrust_scale": {"scale": SESSION_SCALES["early" if i < 3 else "late"]}} for i in range(6)]
    folder, tables = sim_sets("two_sessions", configs, effs)
    return folder, tables


def _scale_groups(result: dict) -> list[dict]:
    found = [d for d in result["disagreements"] if (d["effect"], d["parameter"]) == ("thrust_scale", "scale")]
    assert len(found) == 1, result["disagreements"]
    return found[0]["groups"]


@pytest.mark.slow  # a simulated scenario of its own
def test_two_sessions_are_found_from_the_data(two_sessions):
    _, tables = two_sessions
    result = _diagnose(tables)
    assert result["candidates"][0]["effect"] in ("thrust_scale", "added_mass")
    groups = _scale_groups(result)
    assert [g["flights"] for g in groups] == [["sim003", "sim004", "sim005"], ["sim000", "sim001", "sim002"]]
    for g, truth in zip(groups, (SESSION_SCALES["late"], SESSION_SCALES["early"])):
        assert g["value"] == pytest.approx(truth, rel=0.02) and 0 < g["std"] < 0.02
    assert "differ between groups of flights" in result["verdict"]
    # the same with the model's own thrust scale: one fleet value hides two
    with_it = _diagnose(tables, ["thrust_scale"])
    assert [g["flights"] for g in _scale_groups(with_it)] == [g["flights"] for g in groups]


@pytest.mark.slow  # a simulated scenario of its own; in the fast tier the pinned drag_fleet JSON has no disagreement
def test_one_session_no_disagreement(hidden):
    nominal, with_it = hidden("thrust_scale")
    assert nominal["disagreements"] == [] and with_it["disagreements"] == []


def test_cli_sessions_file_names_the_groups(two_sessions, tmp_path):
    folder, _ = two_sessions
    sessions_file = tmp_path / "sessions.toml"
    sessions_file.write_text('[sessions]\nmonday = ["sim000", "sim001", "sim002"]\ntuesday = ["sim00[345]"]\n')
    out = tmp_path / "d.json"
    code, stdout, stderr = _run(["diagnose", str(folder), "--json", str(out), "--effects", "thrust_scale",
                                 "--sessions", str(sessions_file), "--quiet"])
    assert code == 0, stderr
    groups = _scale_groups(json.loads(out.read_text()))
    assert [(g["session"], g["flights"]) for g in groups] == [("tuesday", ["sim003", "sim004", "sim005"]),
                                                             ("monday", ["sim000", "sim001", "sim002"])]
    for g, truth in zip(groups, (SESSION_SCALES["late"], SESSION_SCALES["early"])):
        assert g["value"] == pytest.approx(truth, rel=0.02)
    assert "thrust_scale.scale differs between groups of flights (sessions file)" in stdout
    # a flight in two sessions is a user error, not a traceback
    sessions_file.write_text('[sessions]\na = ["sim000"]\nb = ["sim00*"]\n')
    code, _, stderr = _run(["diagnose", str(folder), "--json", str(out), "--sessions", str(sessions_file), "--quiet"])
    assert code == 2 and "'sim000' is in sessions 'a' and 'b'" in stderr and "Traceback" not in stderr


def test_a_model_file_fits_a_parameter_per_session(two_sessions, tmp_path):
    """``[per_session] thrust_scale = ["scale"]``: one scale per session, found from the data
    when the file names no sessions; a flight of a named session is scored with its session's
    value, a flight of none with the fleet value."""
    _, tables = two_sessions
    path = tmp_path / "model.toml"
    path.write_text('effects = ["thrust_scale"]\n[per_session]\nthrust_scale = ["scale"]\n')
    spec = load_model_file(path)
    fitted = model_fit.fit_model(spec, tables, sorted(tables))
    term = fitted.terms[0]
    assert sorted(fitted.sessions.values()) == [["sim000", "sim001", "sim002"], ["sim003", "sim004", "sim005"]]
    for session, flights in fitted.sessions.items():
        truth = SESSION_SCALES["early" if "sim000" in flights else "late"]
        assert term.per_session[session]["scale"] == pytest.approx(truth, rel=0.02)
    assert fitted.for_flight("sim004").terms[0].params["scale"] == pytest.approx(SESSION_SCALES["late"], rel=0.02)
    with pytest.warns(UserWarning, match="in no fitted session"):
        assert fitted.for_flight("elsewhere").terms[0].params == term.params  # the fleet value
    restored = model.PhysicsModel.from_dict(fitted.to_dict(), VEHICLE)
    assert restored.terms[0].per_session == term.per_session and restored.sessions == fitted.sessions

    # held out, with named sessions: sim005 is scored with its session's scale, better than one fleet scale
    path.write_text(path.read_text() + '[sessions]\nmonday = ["sim00[012]"]\ntuesday = ["sim00[345]"]\n')
    per_session = diagnosis.diagnose(tables, load_model_file(path), ["sim005"]).to_dict()
    fleet = _diagnose(tables, ["thrust_scale"], holdout=["sim005"])
    assert per_session["model"]["effects"][0]["per_session"]["tuesday"]["scale"] == pytest.approx(
        SESSION_SCALES["late"], rel=0.02)
    assert _rmse(per_session, "force")[2] < 0.5 * _rmse(fleet, "force")[2]


@pytest.mark.parametrize("text, message", [
    ('effects = ["rotor_drag"]\n[per_session]\nrotor_drag = ["k_x_s_per_m"]\n', "all of rotor_drag's parameters"),
    ('effects = []\n[per_session]\nthrust_scale = ["scale"]\n', "must be in effects"),
    ('effects = ["thrust_scale"]\n[sessions]\na = "jana0*"\n', "expected NAME"),
])
def test_per_session_model_file_errors(tmp_path, text, message):
    path = tmp_path / "model.toml"
    path.write_text(text)
    with pytest.raises(ModelFileError, match=message):
        load_model_file(path)


def test_a_session_can_switch_thrust_maps(two_sessions, tmp_path):
    """One session on the motor-speed map: the logged rotor speeds carry the true thrust, so
    that session needs no thrust scale, while the PWM/voltage session keeps its 0.95."""
    _, tables = two_sessions
    path = tmp_path / "model.toml"
    path.write_text('effects = ["thrust_scale"]\n[per_session]\nthrust_scale = ["scale"]\n'
                    '[sessions]\nmonday = ["sim00[012]"]\ntuesday = ["sim00[345]", "sim01*"]\n'
                    '[session_thrust_map]\ntuesday = "motor_speed"\n')
    spec = load_model_file(path)
    assert spec.vehicle_for("sim004").thrust_map_kind == "motor_speed"
    assert spec.vehicle_for("sim001").thrust_map_kind == spec.vehicle.thrust_map_kind == "pwm_vbat"
    fitted = model_fit.fit_model(spec, tables, sorted(tables))
    scales = {s: v["scale"] for s, v in fitted.terms[0].per_session.items()}
    assert scales["monday"] == pytest.approx(SESSION_SCALES["early"], rel=0.02)
    assert scales["tuesday"] == pytest.approx(1.0, abs=0.02)
    assert fitted.for_flight("sim005").vehicle.thrust_map_kind == "motor_speed"
    # a new flight that the session's patterns name joins it: its map and its scale
    new = model.PhysicsModel.from_dict(fitted.to_dict(), VEHICLE).for_flight("sim017")
    assert new.vehicle.thrust_map_kind == "motor_speed"
    assert new.terms[0].params == fitted.terms[0].per_session["tuesday"]
    restored = model.PhysicsModel.from_dict(fitted.to_dict(), VEHICLE)
    assert restored.for_flight("sim005").vehicle.thrust_map_kind == "motor_speed"
    path.write_text(path.read_text().replace('tuesday = "motor_speed"', 'friday = "motor_speed"'))
    with pytest.raises(ModelFileError, match="no session 'friday'"):
        load_model_file(path)


def test_a_gap_in_the_log_adds_no_empty_cluster_to_the_held_out_test(tmp_path):
    """Blocks of the held-out test are the 1 s stretches that hold samples: a 3 s hole in the
    log is no three clusters with a zero score (which would inflate the degrees of freedom)."""
    import polars as pl
    from reference.flight import as_rows

    from quadcore.identify import evidence

    simulation.simulate_set(tmp_path, [SimConfig(kind="random", duration_s=8.0, seed=5)], {}, VEHICLE)
    (table,) = _decode(tmp_path).values()
    holed = table.filter((pl.col("t_s") < 2.0) | (pl.col("t_s") >= 5.0))
    fd = as_rows(flightdata.flight_data("sim000", holed, VEHICLE))
    resid = {"sim000": np.concatenate([fd.r_f, fd.r_tau], axis=1)}
    sums = evidence.block_sums([fd], resid, resid, np.ones(6))
    t = fd.state.t_s[fd.mask]
    assert len(sums) == len(np.unique((t - t[0]) // evidence.BLOCK_S)) and np.all(sums > 0)
    assert evidence.held_out_test([fd], resid, resid, np.ones(6)).blocks == len(sums)


def test_the_stability_of_the_top_answer_says_undecided_when_it_flips_between_folds():
    """Every fold's answer counted against the top one and what the data cannot tell from it:
    a flip to another candidate in any fold is 'undecided between A and B'; a single held-out
    flight cannot measure it."""
    from quadcore.identify.diagnosis.results import NO_EVIDENCE, NOTHING, Stability

    stable = Stability("rotor_drag", ("rotor_drag", "wind"), "fold", {"rotor_drag": 3, "wind": 2}, 5)
    assert stable.agree == 5 and stable.undecided_between == ()
    assert stable.sentence().startswith("Stable: rotor_drag (or wind, which the data cannot tell from it) comes "
                                        "first in 5 of 5 folds")
    flips = Stability("com_offset", ("com_offset",), "fold", {"com_offset": 3, "ground_effect": 2}, 5)
    assert flips.agree == 3 and flips.undecided_between == ("com_offset", "ground_effect")
    assert flips.sentence().startswith("Undecided between com_offset and ground_effect: the answer depends on which "
                                       "flights are held out (first in each of 5 folds: com_offset in 3, "
                                       "ground_effect in 2)")
    # a fold whose flights are at their noise floor (a hover shows no drag) abstains
    quiet = Stability("rotor_drag", ("rotor_drag", "wind"), "fold", {"rotor_drag": 2, "wind": 2, NO_EVIDENCE: 1}, 5)
    assert quiet.agree == 4 and quiet.undecided_between == ()
    assert quiet.sentence().startswith("Stable: rotor_drag (or wind, which the data cannot tell from it) comes first "
                                       "in 4 of 5 folds (rotor_drag in 2, wind in 2, none (flights at the "
                                       "sensor-noise floor: no evidence) in 1).")
    flat = Stability(NOTHING, (NOTHING,), "fold", {NO_EVIDENCE: 5}, 5)
    assert flat.undecided_between == () and flat.sentence().startswith("Stability not measured")
    nothing = Stability(NOTHING, (NOTHING,), "fold", {NOTHING: 4, "wind": 1}, 5)
    assert "Undecided between no effect of the library and wind" in nothing.sentence()
    one = Stability("rotor_drag", ("rotor_drag",), "held-out flight", {"rotor_drag": 1}, 1)
    assert one.sentence().startswith("Stability not measured") and one.to_dict()["agree"] == 1
    other = Stability(NOTHING, (NOTHING,), "held-out flight", {"ground_effect": 1}, 1)  # one answer cannot flip
    assert other.undecided_between == () and other.sentence().startswith("Stability not measured")
    # a fold where the rate level prefers none of two timing candidates (rates.Judged.answer): a tie,
    # agreeing when the top answer is tied with the other one too, else a flip
    tie = f"motor_lag{rates.TIE}thrust_delay"
    tied = Stability("thrust_delay", ("thrust_delay", "motor_lag"), "fold", {"thrust_delay": 4, tie: 1}, 5)
    assert tied.agree == 5 and tied.undecided_between == ()
    apart = Stability("thrust_delay", ("thrust_delay",), "fold", {"thrust_delay": 4, tie: 1}, 5)
    assert apart.agree == 4 and apart.undecided_between == ("thrust_delay", tie)
    assert ("Undecided between thrust_delay and a tie (motor_lag = thrust_delay, at the angular-rate level)"
            in apart.sentence())


def _row(effect: str, target: str, found: bool, explained: float, reason: str = "") -> Any:
    """A physical candidate row of the diagnosis, decided: ``found`` or not, removing ``explained``
    of its ``target`` channel's held-out residual (the same share above the noise floor)."""
    from dataclasses import fields

    from quadcore.identify.diagnosis.rows import CandidateRow

    blank: dict[str, Any] = {f.name: None for f in fields(CandidateRow) if f.name != "explained_alone_screen"}
    ev = {"force": explained if target == "force" else 0.0, "torque": explained if target == "torque" else 0.0}
    return CandidateRow(**{**blank, "effect": effect, "target": target, "acts_on": target, "found": found,
                           "physical": True, "status": "found" if found else "not_significant", "reason": reason,
                           "grade": "large", "explained_variance": explained, "explained_above_noise": explained,
                           "explained_variance_force": ev["force"], "explained_variance_torque": ev["torque"],
                           "held_out_p_value": 1e-20 if found else 0.4, "parameters": {"k": 1.0},
                           "parameter_std": {"k": 0.1}, "notes": (), "tied_with": (), "separated_by": {},
                           "indistinguishable_from": (), "explained_after_top": 0.0, "rate_level": None})


def test_a_channel_above_its_floor_with_nothing_confirmed_points_outside_the_library():
    """The torque residual is mostly explained by a found candidate; the force residual stands 8
    noise floors above its floor (RMS) and nothing in the library is confirmed there: the outside
    section gets a force entry with no best candidate, and the verdict says what is left there
    and gives the discover command. With force at its floor, no such entry."""
    from types import SimpleNamespace

    from quadcore.identify.diagnosis import run
    from quadcore.identify.diagnosis.verdict import verdict

    rows = [_row("com_offset", "torque", True, 0.6), _row("ground_effect", "force", False, 0.03, "not significant")]
    command = "quadcore discover LOGS --model m.toml --json discovery.json"
    # sums of squares per axis: force 3 x 64 over a floor of 3 x 1 (8 floors RMS), torque 3 x 100 over 3 x 1
    held = SimpleNamespace(before=np.array([64.0] * 3 + [100.0] * 3), noise_ss=np.ones(6),
                           at_noise={"force": False, "torque": False})
    outside = run._outside_library(rows, held, command, evidence.LIBRARY_SHARE)
    assert outside is not None and outside["command"] == command
    (part,) = outside["channels"]
    assert part["channel"] == "force" and part["best"] is None and part["held_out_p_value"] is None
    assert part["explained_above_noise"] == 0.0
    assert part["residual_to_noise_after"] == pytest.approx(8.0, rel=1e-12)
    assert rows[0].found and rows[0].status == "found"  # the torque finding stays what is missing
    text = verdict(rows, held.at_noise, None, outside)
    assert text.startswith("Most likely missing: com_offset"), text
    assert "Nothing in the library is confirmed in the force channel" in text and "8.0 times" in text, text
    assert f"`{command}`" in text
    at_floor = SimpleNamespace(before=held.before, noise_ss=held.noise_ss, at_noise={"force": True, "torque": False})
    assert run._outside_library(rows, at_floor, command, evidence.LIBRARY_SHARE) is None
