"""The diagnosis and the discovery on physics this project did not write: rotorpy's flights.

Every check of the diagnosis elsewhere runs on flights from this project's own simulator, which
shares the project's conventions; errors common to both are invisible there. Here the flights
come from rotorpy (:mod:`independent.rotorpy_flights`: its Crazyflie, its rotor drag with a
vertical part, its motor lag, its SE3 controller, circles, Lissajous figures and min-snap plans,
half of them logged from mid-manoeuvre), written as uSD logs by this project's writer with the
real logs' sensor noise, at 500 Hz and at 100 Hz, and diagnosed with the vehicle file of
rotorpy's Crazyflie (``quadcore/vehicles/rotorpy_crazyflie.toml``) through the public workflow
functions the CLI and the assets call (``quadcore.workflows``): cross-validation over the
flights, as ``quadcore diagnose DATA --json ...`` does.

What a user relies on, asserted at both rates: the right effect first; every fitted parameter's
truth inside three of its reported standard deviations; nothing found where nothing is hidden;
nothing spurious found once the main effect is in the model; ``discover`` keeping nothing on
clean flights and the right functional form on each effect.

Tests marked ``xfail(strict=True)`` assert behaviour that issue 21 asks for and main does not
have yet; whoever lands the fix sees the strict xfail fail and removes the marker.

The thrust source matters: with the motor-speed map the logged (actual) rotor speeds give the
thrust, so rotorpy's motor lag is not a missing effect; with the PWM map the logged commands
do, and the lag is (``tau_m`` = 0.072 s).
"""

from __future__ import annotations

import functools

import numpy as np
import pytest

pytest.importorskip("rotorpy", reason="rotorpy (the dev extra) is not installed: the independent-physics suite "
                    "needs it")

from independent import rotorpy_flights as rf  # noqa: E402

pytestmark = pytest.mark.slow

FLEETS = rf.fleets()
RATES = (500, 100)
SPEED, PWM = "motor_speed", "pwm_vbat"
HOVER_START = ("f2", "f4", "f5")  # the flights whose log starts in hover (rf.standard_flights)

# What fails on main today, by test and case (fleet, thrust map, log rate): the item of issue 21
# that owns the cause, and what is wrong. Whoever lands the fix deletes the entry (its strict
# xfail fails once the behaviour is right, naming this table).
KNOWN: dict[tuple[str, str, str, int], tuple[str, str]] = {
}


def _cases(test: str, cases) -> list:
    """``cases`` (fleet, thrust map, rate, ...) as parameters, the known failures marked strict xfail."""
    out = []
    for case in cases:
        known = KNOWN.get((test, *case[:3]))
        marks = [pytest.mark.xfail(strict=True, reason=f"issue 21 {known[0]}: {known[1]}")] if known else []
        out.append(pytest.param(*case, marks=marks, id="-".join([case[0], case[1], f"{case[2]}hz",
                                                                  *("+".join(c) for c in case[3:])])))
    return out


def _at_both_rates(*cases: tuple[str, str]) -> list[tuple[str, str, int]]:
    return [(fleet, tmap, rate) for fleet, tmap in cases for rate in RATES]


@pytest.fixture(scope="module", autouse=True)
def _simulated():
    """Every fleet simulated once (both cores), before the first test needs one."""
    rf.prepare(list(FLEETS.values()))


@functools.cache
def _flights(fleet: str, rate: int, thrust_map: str):
    return rf.decoded(FLEETS[fleet], rate, thrust_map)


@functools.cache
def _diagnosis(fleet: str, rate: int, thrust_map: str = SPEED, effects: tuple[str, ...] = (),
               only: tuple[str, ...] = ()):
    """``quadcore diagnose`` on the fleet's logs at ``rate`` (``only``: just these flights)."""
    flights = _flights(fleet, rate, thrust_map)
    return rf.diagnose(flights.only(only) if only else flights, thrust_map, effects)


@functools.cache
def _discovery(fleet: str, rate: int, thrust_map: str = SPEED, effects: tuple[str, ...] = ()):
    """``quadcore discover`` on the fleet's logs at ``rate``."""
    return rf.discover(_flights(fleet, rate, thrust_map), thrust_map, effects)


def _found(d) -> list[str]:
    return [f"{c.effect} ({c.status}: {c.reason})" for c in d.candidates if c.found]


def _terms(disc) -> list[str]:
    return [f"{t.target} ~ {t.coefficient:.3g} {t.expression}" for t in disc.terms]


def _within_3_sigma(value: float, std: float, truth: float, what: str) -> None:
    assert np.isfinite(std) and std > 0, f"{what}: no uncertainty reported ({std})"
    assert abs(value - truth) <= 3 * std, (f"{what}: fitted {value:.5g} ± {std:.2g}, truth {truth:.5g} "
                                           f"({(value - truth) / std:+.1f} σ)")


# ---------------------------------------------------------------------------------------
# Nothing hidden
# ---------------------------------------------------------------------------------------

NOTHING_HIDDEN = _at_both_rates(("clean", SPEED), ("clean", PWM), ("lag", SPEED))


@pytest.mark.parametrize("fleet,thrust_map,rate", _cases("nothing found", NOTHING_HIDDEN))
def test_nothing_hidden_nothing_found(fleet, thrust_map, rate):
    """rotorpy's flights without aerodynamics (and, through the PWM map, without motor lag; the
    motor-speed map carries the lag in the logged speeds): no library effect is found."""
    d = _diagnosis(fleet, rate, thrust_map)
    assert not _found(d), _found(d)
    assert d.verdict.startswith("No effect of the library explains the residual"), d.verdict


@pytest.mark.parametrize("fleet,thrust_map,rate", _cases("at the noise floor", NOTHING_HIDDEN))
def test_nothing_hidden_the_residual_is_at_the_noise_floor(fleet, thrust_map, rate):
    """... and the report says there is nothing left to explain: the nominal residual is at the
    sensor-noise floor in force and in torque (not "a physical effect outside the library")."""
    d = _diagnosis(fleet, rate, thrust_map)
    assert all(d.at_noise_level.values()), f"residual / noise floor: {dict(d.residual_to_noise)}; {d.verdict}"


@pytest.mark.parametrize("fleet,thrust_map,rate", _cases("discover keeps nothing", NOTHING_HIDDEN))
def test_discover_keeps_nothing_on_clean_flights(fleet, thrust_map, rate):
    disc = _discovery(fleet, rate, thrust_map)
    assert not disc.terms, _terms(disc)


# ---------------------------------------------------------------------------------------
# Rotor drag
# ---------------------------------------------------------------------------------------

ROTOR_DRAG = _at_both_rates(("rotor_drag", SPEED), ("rotor_drag_xy", SPEED))


@pytest.mark.parametrize("fleet,thrust_map,rate", _cases("rotor drag first", ROTOR_DRAG))
def test_rotor_drag_is_first_and_k_is_rotorpys(fleet, thrust_map, rate):
    """rotorpy's rotor drag on rotor i is ``H_i = -w_i diag(k_d, k_d, k_z) v_i`` (``w_i`` its
    speed, ``v_i`` the air velocity at its hub). Summed over the rotors, and for the body
    velocity, ``f = -(sum w_i) diag(k_d, k_d, k_z) v``. This project's ``rotor_drag`` is
    ``f = -T diag(k_x, k_y, k_z) v`` with ``T = k_eta sum w_i^2``, so ``k = k_d sum(w_i) /
    (k_eta sum(w_i^2))``, which in hover (``w_i = w_h``, ``4 k_eta w_h^2 = m g``) is ``k_d /
    (k_eta w_h) = k_d / sqrt(k_eta m g / 4)`` = 0.02492 s/m (``k_z``: 0.01836 s/m; 0 on the
    fleet without it). The two forms differ where the rotors turn faster or slower than in
    hover; on a given set of flights the value a fit of ``-k T v`` converges to is rotorpy's
    rotor drag force projected on ``T v`` by least squares (``rf.projected_truth``), 4-5 % below
    the hover value on these manoeuvring flights. rotor_drag must be first (its vertical part
    makes it explain what parasitic drag's two coefficients did), and each of its three values
    must lie within three reported standard deviations."""
    d = _diagnosis(fleet, rate, thrust_map)
    row = next(c for c in d.candidates if c.effect == "rotor_drag")
    truth = rf.projected_truth(FLEETS[fleet], rate)
    for name in ("k_x_s_per_m", "k_y_s_per_m", "k_z_s_per_m"):
        _within_3_sigma(row.parameters[name], row.parameter_std[name], truth[f"rotor_drag.{name}"],
                        f"rotor_drag.{name}")
    assert d.candidates[0].effect == "rotor_drag" and row.found, _found(d)


@pytest.mark.parametrize("fleet,thrust_map,rate", _cases("rotor drag in, outside the library", ROTOR_DRAG))
def test_with_rotor_drag_in_the_model_what_is_left_is_outside_the_library(fleet, thrust_map, rate):
    """What rotor_drag leaves of rotorpy's aerodynamics has no effect in the library: the damping
    torques of the rotor drag acting at the hubs (yaw: ``-k_d (sum w_i) d^2 Omega_z``; roll and
    pitch from the vertical part). No library effect may be reported found for it, and the
    verdict must say that the remainder lies outside the library."""
    d = _diagnosis(fleet, rate, thrust_map, effects=("rotor_drag",))
    assert not _found(d), _found(d)
    assert "outside the library" in d.verdict, d.verdict


@pytest.mark.parametrize("fleet,thrust_map,rate", _cases("discover names vertical drag and damping",
                                                         _at_both_rates(("rotor_drag", SPEED))))
def test_discover_names_rotorpys_vertical_drag_and_rotor_damping_with_their_sizes(fleet, thrust_map, rate):
    """On the nominal model, discover keeps what rotorpy has, each within three reported
    standard deviations of its value on these flights (``rf.projection``): vertical drag
    ``f_z = -c v_z`` (in hover ``c = 4 k_z w_h`` = 0.0054 kg/s; rotor_drag's ``k_z`` in the
    library) and, outside the library, rate damping ``tau = -D Omega`` (yaw ``4 k_d w_h d^2`` =
    1.36e-5 N m s; roll and pitch ``2 k_z w_h d^2`` = 5.0e-6 N m s, the vertical drag at hubs
    that move up and down as the body rolls)."""
    disc = _discovery(fleet, rate, thrust_map)
    for target, base in (("f_res_b_z_N", "v_b_z_mps"), ("tau_res_b_x_Nm", "omega_b_x_radps"),
                         ("tau_res_b_y_Nm", "omega_b_y_radps"), ("tau_res_b_z_Nm", "omega_b_z_radps")):
        term = next((t for t in disc.terms if t.target == target and _linear_in(t.expression, base)), None)
        assert term is not None, f"{target}: no term linear in {base} kept; kept: {_terms(disc)}"
        _within_3_sigma(term.coefficient, term.std, rf.projection(FLEETS[fleet], rate, target, term.expression),
                        f"{target} ~ {term.expression}")


def _linear_in(expression: str, base: str) -> bool:
    """``base`` or ``base`` times the thrust: the forms of a drag linear in the velocity or rate
    (rotorpy's ``(sum w_i) v`` lies between them)."""
    return expression in (base, f"{base}*T_N", f"T_N*{base}")


@pytest.mark.parametrize("fleet,thrust_map,rate", _cases("discover keeps linear rotor drag",
                                                         _at_both_rates(("rotor_drag_xy", SPEED))))
def test_discover_keeps_rotor_drag_linear_and_nothing_else(fleet, thrust_map, rate):
    """Rotor drag without its vertical part, nothing in the model: the horizontal force terms
    are linear in the velocity (``v`` or ``T v``), the yaw torque is damped by the rate, and
    nothing else is kept (no vertical drag, no roll or pitch damping: rotorpy has none without
    ``k_z``)."""
    disc = _discovery(fleet, rate, thrust_map)
    allowed = {"f_res_b_x_N": "v_b_x_mps", "f_res_b_y_N": "v_b_y_mps", "tau_res_b_z_Nm": "omega_b_z_radps"}
    for target in ("f_res_b_x_N", "f_res_b_y_N"):
        assert any(t.target == target for t in disc.terms), f"{target}: no term kept: {_terms(disc)}"
    wrong = [t for t in disc.terms if t.target not in allowed or not _linear_in(t.expression, allowed[t.target])]
    assert not wrong, f"kept beyond linear rotor drag and yaw damping: {_terms(disc)}"


# ---------------------------------------------------------------------------------------
# Parasitic drag
# ---------------------------------------------------------------------------------------

PARASITIC = _at_both_rates(("parasitic", SPEED))


@pytest.mark.parametrize("fleet,thrust_map,rate", _cases("parasitic first", PARASITIC))
def test_parasitic_drag_is_first_and_recovered(fleet, thrust_map, rate):
    """rotorpy's parasitic drag ``D = -|v| diag(c_Dx, c_Dy, c_Dz) v`` is this project's
    ``parasitic_drag`` with ``c_xy = c_Dx = c_Dy`` and ``c_z = c_Dz``: first, and both within
    three reported standard deviations of rotorpy's values."""
    d = _diagnosis(fleet, rate, thrust_map)
    top = d.candidates[0]
    assert top.effect == "parasitic_drag" and top.found, _found(d)
    truth = rf.truth(FLEETS[fleet].physics)
    for name in ("c_xy_kg_per_m", "c_z_kg_per_m"):
        _within_3_sigma(top.parameters[name], top.parameter_std[name], truth[f"parasitic_drag.{name}"],
                        f"parasitic_drag.{name}")


@pytest.mark.parametrize("fleet,thrust_map,rate", _cases("parasitic in, nothing left", PARASITIC))
def test_with_parasitic_drag_in_the_model_nothing_is_left(fleet, thrust_map, rate):
    d = _diagnosis(fleet, rate, thrust_map, effects=("parasitic_drag",))
    assert not _found(d), _found(d)


@pytest.mark.parametrize("fleet,thrust_map,rate", _cases("discover keeps quadratic drag", PARASITIC))
def test_discover_keeps_parasitic_drag_quadratic(fleet, thrust_map, rate):
    """Parasitic drag alone: the force terms discover keeps are quadratic in the velocity
    (``|v| v`` or ``v |v|`` forms), never the linear ``-k T v`` of rotor drag."""
    disc = _discovery(fleet, rate, thrust_map)
    force = [t for t in disc.terms if t.target.startswith("f_res")]
    assert force, f"no force term kept: {_terms(disc)}"
    for t in force:
        factors = t.expression.split("*")
        assert len([f for f in factors if f.strip("|").startswith("v_b")]) == 2 and "T_N" not in factors, (
            f"{t.target} ~ {t.expression}: not a quadratic drag; kept: {_terms(disc)}")


# ---------------------------------------------------------------------------------------
# Motor lag (the PWM map: the logged commands, not the rotors' speeds)
# ---------------------------------------------------------------------------------------

LAG = _at_both_rates(("lag", PWM))


@pytest.mark.parametrize("fleet,thrust_map,rate", _cases("motor lag first", LAG))
def test_motor_lag_is_first_and_recovered(fleet, thrust_map, rate):
    """rotorpy's rotors follow their commanded speed with ``tau_m dw/dt = w_cmd - w`` (0.072 s);
    thrust ``k_eta w^2`` then lags its command ``k_eta w_cmd^2`` with the same time constant to
    first order. Through the PWM map (the logged commands) motor_lag is first and tau within three
    reported standard deviations of 0.072 s, on flights half of which start mid-manoeuvre."""
    _assert_lag_recovered_and_first(_diagnosis(fleet, rate, thrust_map), FLEETS[fleet].physics.tau_m or 0.0)


def _assert_lag_recovered_and_first(d, tau_s: float) -> None:
    row = next(c for c in d.candidates if c.effect == "motor_lag")
    _within_3_sigma(row.parameters["tau_s"], row.parameter_std["tau_s"], tau_s, "motor_lag.tau_s")
    assert d.candidates[0].effect == "motor_lag" and row.found, _found(d)


@pytest.mark.parametrize("fleet,thrust_map,rate", _cases("motor lag from hover starts", LAG))
def test_motor_lag_is_recovered_on_flights_that_start_in_hover(fleet, thrust_map, rate):
    """The same on the three flights whose log starts in hover (the rotors at their steady
    state), where the lag filter's steady start is right."""
    _assert_lag_recovered_and_first(_diagnosis(fleet, rate, thrust_map, only=HOVER_START),
                                    FLEETS[fleet].physics.tau_m or 0.0)


@pytest.mark.parametrize("fleet,thrust_map,rate", _cases("motor lag in, nothing left", LAG))
def test_with_motor_lag_in_the_model_nothing_is_left(fleet, thrust_map, rate):
    d = _diagnosis(fleet, rate, thrust_map, effects=("motor_lag",))
    assert not _found(d), _found(d)


# ---------------------------------------------------------------------------------------
# The logs themselves
# ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("rate", RATES)
def test_the_logs_hold_rotorpys_flights(rate):
    """A decoded log gives back the simulated flight at the log's rate: rotor speeds (firmware
    order) within their 15 rpm noise and quantisation, the accelerometer within its noise, the
    PWM and battery voltage back to rotorpy's commanded thrust through the PWM map."""
    from quadcore.logs import flight
    from quadcore.physics import vehicle

    fleet = FLEETS["rotor_drag"]
    trace = rf.traces(fleet, rate)[0]
    table = flight.decode_flight(rf.folder(fleet, rate) / fleet.flights[0].name).tables["fixedFrequency"]
    t = table["t_s"].to_numpy()
    assert np.median(np.diff(t)) == pytest.approx(1.0 / rate, rel=1e-3)
    k = np.rint((t - t[0]) * rate).astype(int)  # the kept samples (a few gaps)
    assert len(k) > 0.95 * len(trace.t_s)
    motors = table.select([f"motor_{i}_radps" for i in range(1, 5)]).to_numpy()
    assert np.sqrt(np.mean((motors - trace.rotor_radps[k]) ** 2)) < 2.0  # rad/s: 15 rpm = 1.6 rad/s
    sf = table.select([f"sf_b_{a}_mps2" for a in "xyz"]).to_numpy()
    assert np.sqrt(np.mean((sf - trace.sf_b_mps2[k]) ** 2, axis=0)) == pytest.approx([0.049, 0.064, 0.05], rel=0.1)
    veh = vehicle.load(rf.VEHICLE_FILE)
    pwm = table.select([f"pwm_{i}" for i in range(1, 5)]).to_numpy()  # decoded: 0..1
    f_cmd = veh.pwm_vbat.thrust_N(pwm, table["vbat_V"].to_numpy()[:, None])
    assert f_cmd == pytest.approx(veh.motor_speed.k_F_N_per_radps2 * trace.cmd_radps[k] ** 2, abs=2e-5)
