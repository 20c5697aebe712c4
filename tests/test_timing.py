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
