"""How the modelled wrench is timed against the measured one (docs/timing.md).

Known answers, at 500 Hz and 100 Hz logging, for both thrust sources:

* a signal we integrate by hand (a sinusoidal torque; a command held for the command period),
  independent of any simulator: the modelled torque through
  :func:`quadcore.physics.signals.matched_to_derivative` equals the gyro side's derivative of
  the exact angular momentum;
* simulated flights with nothing hidden: the torque residual holds no multiple of the modelled
  torque's rate (no delay), ``discover`` keeps no term and ``diagnose`` finds no effect.

A measured motor speed is a sample of a continuous state (held for no time); a PWM command
holds for the firmware's command period (2 ms), whatever the log rate. Holding either until
the next log sample, as before, delays the model by half a log period on the torque side:
1 ms at 500 Hz, 5 ms at 100 Hz.
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import numpy as np
import pytest

from quadcore import cli
from quadcore.logs import flight
from quadcore.physics import dynamics, residuals, signals, vehicle
from quadcore.sim import simulation
from quadcore.sim.simulation import SimConfig

VEHICLE = vehicle.load()
COMMAND_PERIOD_S = VEHICLE.pwm_vbat.command_period_s
RATES_HZ = (500.0, 100.0)
# A source and what flies on a flight with nothing hidden from it: the PWM map's flights have
# no effect at all; the motor-speed map's have a motor lag, which the measured speeds contain
# (and which makes them continuous, as a real rotor's speed is).
SOURCES = {"pwm_vbat": {}, "motor_speed": {"motor_lag": {"tau_s": 0.03}}}


def _hand_integrated(rate_hz: float, hold_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Log instants, the torque samples a log holds, and the exact integral of the torque
    acting (∫ tau dt, what ``J ω`` is) at those instants: a sum of two sines, continuous
    (``hold_s = 0``) or a command set every ``hold_s`` and held."""
    t = np.arange(0.0, 4.0, 1.0 / rate_hz)
    w1, w2 = 2 * np.pi * 3.0, 2 * np.pi * 7.0

    def tau(s):
        return 1e-3 * (np.sin(w1 * s) + 0.5 * np.cos(w2 * s))

    def integral(s):
        return 1e-3 * ((1 - np.cos(w1 * s)) / w1 + 0.5 * np.sin(w2 * s) / w2)

    if hold_s == 0:
        return t, tau(t), integral(t)
    t_cmd = np.arange(0.0, 4.0 + hold_s, hold_s)
    acting = np.concatenate([[0.0], np.cumsum(tau(t_cmd) * hold_s)])  # ∫ of the staircase at t_cmd
    at = np.rint(t / hold_s).astype(int)
    return t, tau(t_cmd[at]), acting[at]


@pytest.mark.parametrize("rate_hz", RATES_HZ)
@pytest.mark.parametrize("hold_s", [0.0, COMMAND_PERIOD_S], ids=["motor_speed", "pwm_command"])
def test_modelled_torque_matches_the_gyro_side_by_hand(rate_hz, hold_s):
    t, tau_logged, exact_integral = _hand_integrated(rate_hz, hold_s)
    measured = signals.derivative(exact_integral, t)  # J dω/dt through the gyro's derivative
    inner = slice(100, -100)

    def error(hold):  # RMS of modelled minus measured, relative to the measured torque's RMS
        d = signals.matched_to_derivative(tau_logged, t, hold) - measured
        return np.sqrt(np.mean(d[inner] ** 2) / np.mean(measured[inner] ** 2))

    err = error(hold_s)
    assert err < 0.005, err  # what is left: the line between samples where the signal curves (0.3 % at 100 Hz)
    if hold_s < 1.0 / rate_hz:  # holding until the next log sample (the old alignment) is a delay
        assert error(1.0 / rate_hz) > 10 * err
    if hold_s > 0:  # and a held command is not a continuous signal
        assert error(0.0) > 5 * err


@pytest.mark.parametrize("hold_s", [0.0, 0.0007, 0.002, 0.01])
def test_a_held_sample_acts_half_its_hold_late(hold_s):
    """On a linear signal the interval integrals are those of the signal ``min(h, Δ) / 2`` late."""
    t = np.arange(0.0, 0.1, 0.002)
    slope = 3.0
    got = signals.interval_integrals(slope * t, t, hold_s)
    delay = min(hold_s, 0.002) / 2
    want = slope * ((t[1:] - delay) ** 2 - (t[:-1] - delay) ** 2) / 2
    assert np.allclose(got, want, rtol=0, atol=1e-12)


def test_vehicle_hold_per_thrust_source(tmp_path):
    assert VEHICLE.with_thrust_map("motor_speed").thrust_hold_s == 0.0
    assert VEHICLE.with_thrust_map("pwm_vbat").thrust_hold_s == COMMAND_PERIOD_S == 0.002
    text = (Path(vehicle.__file__).parent.parent / "vehicles" / "crazyflie21.toml").read_text()
    path = tmp_path / "v.toml"
    path.write_text(text.replace("command_period_s = 0.002", "command_period_s = -1"))
    with pytest.raises(vehicle.VehicleFileError, match="command_period_s"):
        vehicle.load(path)


def _flights(folder: Path, rate_hz: float, effects: dict, seeds=(1, 2, 3, 4), duration_s: float = 8.0) -> Path:
    configs = [SimConfig(kind="random", duration_s=duration_s, seed=s, speed_min_mps=0.8, speed_max_mps=1.5,
                         log_rate_hz=rate_hz) for s in seeds]
    simulation.simulate_set(folder, configs, effects, VEHICLE)
    return folder


def _apparent_delay_s(log: Path, source: str) -> np.ndarray:
    """Per torque axis, the delay ``δ`` in ``tau_res ≈ δ · d(tau_model)/dt`` (least squares;
    positive: the model lags the gyro), on samples away from gaps and edges."""
    veh = VEHICLE.with_thrust_map(source)
    state = dynamics.flight_state(flight.decode_flight(log).tables["fixedFrequency"], veh)
    r = residuals.residual_arrays(state, veh)
    rate = signals.derivative(r["tau_model_b"], state.t_s)
    ok = ~signals.near_gap(state.t_s)
    ok[:50] = ok[-50:] = False
    x, y = rate[ok], r["tau_res_b"][ok]
    return (x * y).sum(axis=0) / (x * x).sum(axis=0)


@pytest.mark.parametrize("rate_hz", RATES_HZ)
@pytest.mark.parametrize("source", SOURCES)
def test_simulated_residual_has_no_delay(tmp_path, source, rate_hz):
    folder = _flights(tmp_path, rate_hz, SOURCES[source], seeds=(3,), duration_s=6.0)
    delay = _apparent_delay_s(folder / "sim000", source)
    # holding the model to the next log sample would show half a log period here (1 ms / 5 ms)
    assert np.all(np.abs(delay[:2]) < 0.1 / rate_hz), delay


def _run(argv: list[str]) -> tuple[int, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main(argv)
    return code, out.getvalue() + err.getvalue()


@pytest.mark.slow
@pytest.mark.parametrize("rate_hz", RATES_HZ)
@pytest.mark.parametrize("source", SOURCES)
def test_nothing_found_on_clean_flights(tmp_path, source, rate_hz):
    """``discover`` keeps no term (in particular no timing term ``d(...)/dt``) and ``diagnose``
    finds no effect (no lag, no delay) on four flights with nothing hidden from the map."""
    folder = _flights(tmp_path / "logs", rate_hz, SOURCES[source])
    code, text = _run(["discover", str(folder), "--thrust-map", source, "--json", str(tmp_path / "d.json"),
                       "--quiet"])
    assert code == 0, text
    found = json.loads((tmp_path / "d.json").read_text())["terms"]
    assert found == [], [(t["target"], t["expression"], t["coefficient"]) for t in found]
    code, text = _run(["diagnose", str(folder), "--thrust-map", source, "--json", str(tmp_path / "g.json"),
                       "--quiet"])
    assert code == 0, text
    verdict = json.loads((tmp_path / "g.json").read_text())
    found = [c["effect"] for c in verdict["candidates"] if c["found"]]
    assert found == [], verdict["verdict"]


def _turning_body(rate_hz: float) -> dynamics.FlightState:
    """A body turning with known rates (roll 1.3 Hz, pitch 0.9 Hz, yaw 2 rad/s plus 1.1 Hz: the
    band where a 100 Hz log's derivative filter passes 67-95 %), its rotors giving exactly
    Euler's torque ``J dω/dt + ω × J ω`` at every instant (continuous: held for no time), the
    gyro sampling ``ω`` at the log instants. Nothing else acts."""
    t = np.arange(0.0, 8.0, 1.0 / rate_hz)
    w = 2 * np.pi * np.array([1.3, 0.9, 1.1])
    amp, offset, phase = np.array([0.8, 0.6, 1.0]), np.array([0.0, 0.0, 2.0]), np.array([0.0, 1.0, 0.4])
    omega = offset + amp * np.sin(w * t[:, None] + phase)
    omega_dot = amp * w * np.cos(w * t[:, None] + phase)
    tau = dynamics.torque_for_angular_acceleration(VEHICLE, omega, omega_dot)
    wrench = np.column_stack([np.full(len(t), VEHICLE.mass_kg * 9.81), tau])
    f_rotor = np.linalg.solve(VEHICLE.allocation, wrench.T).T
    n, q = len(t), np.tile([0.0, 0.0, 0.0, 1.0], (len(t), 1))
    zeros = np.zeros((n, 3))
    return dynamics.FlightState(t_s=t, p_w_m=zeros, v_w_mps=zeros, q_xyzw=q, omega_b_radps=omega,
                                sf_b_mps2=zeros, pwm=np.zeros((n, 4)), vbat_V=np.full(n, 3.7), motor_radps=None,
                                R_wb=np.tile(np.eye(3), (n, 1, 1)), v_b_mps=zeros, f_rotor_N=f_rotor,
                                thrust_hold_s=0.0)


@pytest.mark.parametrize("rate_hz", RATES_HZ)
def test_the_gyroscopic_term_goes_through_the_gyro_derivatives_filter(rate_hz):
    """Euler's ``J dω/dt = tau - ω × J ω`` holds at every instant, so the derivative's filter
    ``D`` gives ``J D[ω] = M[tau] - M[ω × J ω]`` (``M``: :func:`signals.matched_to_derivative`):
    the measured torque is ``J D[ω] + M[ω × J ω]`` and the residual of a body with nothing
    hidden is what the line between samples leaves (0.01 % of the gyroscopic term at 500 Hz,
    0.2 % at 100 Hz). Smoothing the rates instead (the measured torque before:
    ``J D[ω] + S[ω] × J S[ω]``) leaves the difference of the two filters on ``ω × J ω``: 6-12 %
    of it at 100 Hz, 0.3-0.6 % at 500 Hz, 25-250 times more."""
    state = _turning_body(rate_hz)
    inner = slice(int(0.5 * rate_hz), -int(0.5 * rate_hz))
    r = residuals.residual_arrays(state, VEHICLE)
    J = VEHICLE.inertia_kgm2
    gyroscopic = np.cross(state.omega_b_radps, state.omega_b_radps @ J.T)[inner]

    def share(tau_res):  # RMS of the torque residual, per axis, relative to the gyroscopic term's (all axes)
        return np.sqrt(np.mean(tau_res[inner] ** 2, axis=0) / np.mean(np.sum(gyroscopic**2, axis=1)))

    got = share(r["tau_res_b"])
    assert np.all(got < 0.005), got  # the line between samples: 0.01 % at 500 Hz, 0.2 % at 100 Hz
    omega_s = signals.smooth(state.omega_b_radps)
    smoothed = J @ signals.derivative(state.omega_b_radps, state.t_s).T
    before = share(smoothed.T + np.cross(omega_s, omega_s @ J.T) - r["tau_model_b"])
    # roll and pitch, where the gyroscopic term lives (J_xx ≈ J_yy: little of it in yaw)
    assert np.all(before[:2] > 10 * got[:2]), (before, got)
    if rate_hz == 100.0:
        assert np.all(before[:2] > 0.05), before
