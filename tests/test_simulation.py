"""The simulator: real-format logs, realistic statistics, determinism, and the residual contract
(an effect switched on in the simulator shows up in the residuals as that effect's wrench)."""

from __future__ import annotations

import ast
import contextlib
import io
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from quadcore import cli, effects
from quadcore.logs import flight, logformat
from quadcore.physics import dynamics, residuals, signals, vehicle
from quadcore.sim import simulation, trajectories, usdlog
from quadcore.sim.simulation import SimConfig

# Measured on the real logs (jana00..jana33) in steady hover: |v| < 0.1 m/s, z > 0.2 m, in
# 61-sample windows away from gaps (15 flights have enough hover). Noise = std of the signal
# minus its ``signals.smooth`` trend, times 1/sqrt(1 - h0) = 1.038 (the share of white noise
# the 31-sample quadratic Savitzky-Golay trend absorbs), median over flights.
REAL_HOVER_ACC_NOISE_G = np.array([0.0050, 0.0065, 0.0051])
REAL_HOVER_GYRO_NOISE_DPS = np.array([0.70, 0.74, 0.29])
# Per-motor mean PWM in hover over the real flights: 43840 .. 54262 (vbat 3.29-3.70 V).
REAL_HOVER_PWM = (43000, 55000)
# In-flight battery voltage of the real logs: 3.25 .. 3.61 V (jana20..33 stuck at 3.70 V).
REAL_VBAT_V = (3.2, 3.9)
# The header of every real log, as parse_header reads it.
REAL_FIXED_FREQUENCY_VARIABLES = (
    "stateEstimate.x", "stateEstimate.y", "stateEstimate.z", "stateEstimate.qx", "stateEstimate.qy",
    "stateEstimate.qz", "stateEstimate.qw", "stateEstimate.vx", "stateEstimate.vy", "stateEstimate.vz",
    "gyro.x", "gyro.y", "gyro.z", "acc.x", "acc.y", "acc.z", "rpm.m1", "rpm.m2", "rpm.m3", "rpm.m4",
    "pwm.m1_pwm", "pwm.m2_pwm", "pwm.m3_pwm", "pwm.m4_pwm", "pm.vbatMV",
)
REAL_FIXED_FREQUENCY_TYPES = "ffffffffffffffffHHHHHHHIH"
REAL_EST_POSE_VARIABLES = ("locSrv.x", "locSrv.y", "locSrv.z", "locSrv.qx", "locSrv.qy", "locSrv.qz", "locSrv.qw")
SMOOTH_DE_NOISE = 1.0 / np.sqrt(1.0 - 0.07270704823541138)

VEHICLE = vehicle.load()
F_COLS = residuals.F_RES_B
TAU_COLS = residuals.TAU_RES_B


def _random(seed: int, duration: float = 8.0, **kw) -> SimConfig:
    kw = {"speed_min_mps": 0.5, "speed_max_mps": 1.5, **kw}
    return SimConfig(kind="random", duration_s=duration, seed=seed, **kw)


def _fly(tmp_path, config: SimConfig, effs: dict | None = None, name: str = "sim"):
    """Simulate, write, decode. Returns (SimFlight, decoded fixedFrequency table, log path)."""
    sim = simulation.simulate(config, VEHICLE, effs or {})
    path = tmp_path / name
    simulation.write_flight(sim, path)
    fl = flight.decode_flight(path)
    return sim, fl, path


def _compare(df, sim):
    """Residuals of the decoded flight and the sum of the true effects' wrenches on it (filtered
    as the residuals are: force smoothed, torque through the gyro derivative's filter).
    Returns (f_res, tau_res, f_eff, tau_eff), rows away from gaps/edges."""
    table = residuals.residual_table(df, VEHICLE)
    state = dynamics.flight_state(df, VEHICLE)
    f_eff, tau_eff = np.zeros((state.n, 3)), np.zeros((state.n, 3))
    for name, params in sim.effects.items():
        f, tau = effects.get(name).wrench(state, VEHICLE, params)
        f_eff += f
        tau_eff += tau
    ok = ~table["near_gap"].to_numpy()
    ok[:50] = ok[-50:] = False  # filter edges
    return (table.select(F_COLS).to_numpy()[ok], table.select(TAU_COLS).to_numpy()[ok],
            signals.smooth(f_eff)[ok], signals.matched_to_derivative(tau_eff, state.t_s, state.thrust_hold_s)[ok])


def _assert_matches(res: np.ndarray, eff: np.ndarray, label: str, min_corr: float = 0.9, max_rel: float = 0.2,
                    noise: float = 0.0):
    """The residual is the effect's wrench: correlated, and apart by less than ``max_rel`` of it;
    with ``noise`` (the sensor-noise floor of the residual, RMS) the residual holds that noise
    besides the wrench, and the allowed difference is ``max_rel`` of the wrench and the noise
    added in quadrature."""
    rms_eff = float(np.sqrt(np.mean(eff**2)))
    rms_diff = float(np.sqrt(np.mean((res - eff) ** 2)))
    corr = float(np.corrcoef(res, eff)[0, 1])
    assert rms_eff > 0, f"{label}: the effect is zero on this flight"
    assert corr > min_corr, f"{label}: corr(residual, wrench) = {corr:.3f}"
    assert rms_diff < np.hypot(max_rel * rms_eff, noise), (
        f"{label}: rms(residual - wrench) {rms_diff:.2e} vs rms(wrench) {rms_eff:.2e}, noise floor {noise:.2e}")


# ---------------------------------------------------------------------------------------
# Format and statistics
# ---------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def hover(tmp_path_factory):
    return _fly(tmp_path_factory.mktemp("hover"), SimConfig(kind="hover", duration_s=6.0, seed=11))


def test_log_has_the_real_header_and_rates(hover):
    sim, fl, path = hover
    log = logformat.decode_file(path)
    assert log.version == 2 and log.crc_ok is True and not log.warnings
    ff, ep = log.event_types["fixedFrequency"], log.event_types["estPose"]
    assert ff.event_id == 0xFFFF and ep.event_id == 8
    assert ff.variables == REAL_FIXED_FREQUENCY_VARIABLES
    assert "".join(ff.type_chars) == REAL_FIXED_FREQUENCY_TYPES
    assert ep.variables == REAL_EST_POSE_VARIABLES and set(ep.type_chars) == {"f"}
    stats = flight.sample_statistics(fl.tables["fixedFrequency"]["t_s"].to_numpy())
    assert abs(stats["rate_hz_median"] - 500) < 5
    assert abs(stats["duration_s"] - 6.0) < 0.01
    pose = flight.sample_statistics(fl.tables["estPose"]["t_s"].to_numpy())
    assert 80 < pose["rate_hz_median"] < 110  # real: 90-97 Hz median, ~55 Hz on average
    assert 40 < fl.tables["estPose"].height / stats["duration_s"] < 75


def test_header_equals_a_real_logs_header(real_logs):
    _, types, _ = logformat.parse_header((real_logs / "jana00").read_bytes())
    def by_id(e):
        return e.event_id
    assert sorted(types.values(), key=by_id) == sorted(usdlog.LOG_EVENT_TYPES, key=by_id)


def test_statistics_look_like_the_real_logs(hover):
    sim, fl, _ = hover
    df = fl.tables["fixedFrequency"]
    steady = df["t_s"].to_numpy() > 2.5  # after the take-off
    for cols, scale, real in (
        (dynamics.cols("sf_b", "mps2"), 1 / 9.80665, REAL_HOVER_ACC_NOISE_G),
        (dynamics.cols("omega_b", "radps"), 180 / np.pi, REAL_HOVER_GYRO_NOISE_DPS),
    ):
        x = df.select(cols).to_numpy()
        noise = ((x - signals.smooth(x))[steady] * SMOOTH_DE_NOISE * scale).std(axis=0)
        assert np.all(noise > real / 2) and np.all(noise < real * 2), (cols, noise, real)
    pwm = df.select([f"pwm_{i}" for i in range(1, 5)]).to_numpy()[steady] * 65535
    assert np.all((pwm.mean(axis=0) > REAL_HOVER_PWM[0]) & (pwm.mean(axis=0) < REAL_HOVER_PWM[1]))
    vbat = df["vbat_V"].to_numpy()
    assert REAL_VBAT_V[0] < vbat.min() and vbat.max() < REAL_VBAT_V[1] and vbat.std() > 0
    acc_z_g = df["sf_b_z_mps2"].to_numpy()[steady].mean() / 9.80665
    assert abs(acc_z_g - 1.0) < 0.01
    rpm = df.select([f"motor_{i}_radps" for i in range(1, 5)]).to_numpy()[steady] * 60 / (2 * np.pi)
    assert np.all((rpm.mean(axis=0) > 15000) & (rpm.mean(axis=0) < 21000))  # real hover: 15200-19900
    z = df["p_w_z_m"].to_numpy()[steady]
    assert abs(z.mean() - 0.5) < 0.01


def _gyro_noise_lag_one(fl) -> np.ndarray:
    """Per axis, the lag-one autocorrelation of the logged gyro minus its trend, where the vehicle
    turns slowly (below 20 deg/s) away from gaps and the ends: white noise gives ~0."""
    df = fl.tables["fixedFrequency"]
    t, g = df["t_s"].to_numpy(), df.select(dynamics.cols("omega_b", "radps")).to_numpy() * 180 / np.pi
    ok = ~signals.near_gap(t) & (np.linalg.norm(signals.smooth(g), axis=1) < 20.0)
    ok[:40] = ok[-40:] = False
    res, pair = g - signals.smooth(g), ok[:-1] & ok[1:]
    return np.array([np.corrcoef(res[:-1][pair, i], res[1:][pair, i])[0, 1] for i in range(3)])


def test_the_firmwares_low_pass_colours_the_gyro_noise_as_on_the_real_logs(tmp_path, hover, real_logs):
    """The real gyro noise is the firmware's 80 Hz low-pass of it (lag-one autocorrelation ~+0.7
    on jana04 and jana20); the simulator's is white unless ``SensorNoise.lowpass_hz`` says so, and
    its size stays the measured one."""
    real = np.concatenate([_gyro_noise_lag_one(flight.decode_flight(real_logs / f)) for f in ("jana04", "jana20")])
    assert np.all(real > 0.6), real
    white = _gyro_noise_lag_one(hover[1])
    assert np.all(np.abs(white) < 0.15), white
    config = SimConfig(kind="hover", duration_s=6.0, seed=11, noise=simulation.SensorNoise(lowpass_hz=80.0))
    _, fl, _ = _fly(tmp_path, config)
    coloured = _gyro_noise_lag_one(fl)
    assert np.all(np.abs(coloured - real.mean()) < 0.1), (coloured, real)
    size, white_size = _gyro_noise_size(fl), _gyro_noise_size(hover[1])
    assert np.all(size < white_size) and np.all(size > 0.85 * white_size), (size, white_size)  # the trend takes more


def _gyro_noise_size(fl) -> np.ndarray:
    """Per axis, the standard deviation of the logged gyro (deg/s) minus its trend, after the take-off."""
    df = fl.tables["fixedFrequency"]
    x = df.select(dynamics.cols("omega_b", "radps")).to_numpy()[df["t_s"].to_numpy() > 2.5] * 180 / np.pi
    return (x - signals.smooth(x)).std(axis=0)


def test_actuation_chain_is_reproduced_by_the_log(hover):
    sim, fl, _ = hover
    df = fl.tables["fixedFrequency"]
    state = dynamics.flight_state(df, VEHICLE)
    kept = sim.kept
    # logged PWM + logged vbat through the thrust map = the thrust the rotors made (no effect on);
    # exact up to the float32 the decoded SI tables are stored in
    np.testing.assert_allclose(state.f_rotor_N, sim.f_actual_N[kept], rtol=1e-6, atol=1e-9)
    # motor speed: f = k_F omega^2 with the actual thrust (15 rpm noise, 1 rpm rounding)
    rpm_expected = np.sqrt(sim.f_actual_N[kept] / VEHICLE.motor_speed.k_F_N_per_radps2) * 60 / (2 * np.pi)
    rpm = state.motor_radps * 60 / (2 * np.pi)
    assert np.abs(rpm - rpm_expected).max() < 100
    assert 5 < (rpm - rpm_expected).std() < 30


def test_dropped_samples_make_gaps():
    config = SimConfig(kind="hover", duration_s=6.0, seed=3, drop_prob=2e-3, drop_max_samples=20)
    sim = simulation.simulate(config, VEHICLE)
    log = logformat.decode_bytes(sim.data)
    dt_us = np.diff(log.timestamps_us["fixedFrequency"])
    assert len(dt_us) + 1 == sim.kept.sum() < len(sim.t_s)
    assert dt_us.max() > 2000 and dt_us.max() <= 21 * 2000
    assert set(np.unique(dt_us) % 2000) == {0}
    quiet = simulation.simulate(replace(config, drop_prob=0.0), VEHICLE)
    assert quiet.kept.all()


# ---------------------------------------------------------------------------------------
# Determinism
# ---------------------------------------------------------------------------------------

def test_same_seed_same_bytes_other_seed_differs():
    eff = {"rotor_drag": {"k_x_s_per_m": 0.3, "k_y_s_per_m": 0.3}}
    a = simulation.simulate(_random(5, duration=3.0), VEHICLE, eff)
    b = simulation.simulate(_random(5, duration=3.0), VEHICLE, eff)
    c = simulation.simulate(_random(6, duration=3.0), VEHICLE, eff)
    assert a.data == b.data
    assert a.data != c.data


# ---------------------------------------------------------------------------------------
# The residual contract
# ---------------------------------------------------------------------------------------

def test_no_effect_residuals_are_at_noise_level(tmp_path):
    sim, fl, _ = _fly(tmp_path, _random(1))
    f_res, tau_res, _, _ = _compare(fl.tables["fixedFrequency"], sim)
    weight = VEHICLE.weight_N
    assert np.all(np.abs(f_res.mean(axis=0)) < 2e-4), f_res.mean(axis=0)  # < 0.06% of the weight
    assert np.all(np.sqrt(np.mean(f_res**2, axis=0)) < 1.5e-3), np.sqrt(np.mean(f_res**2, axis=0))
    assert np.all(np.sqrt(np.mean(f_res**2, axis=0)) < 0.005 * weight)
    assert np.all(np.abs(tau_res.mean(axis=0)) < 5e-6), tau_res.mean(axis=0)
    assert np.all(np.sqrt(np.mean(tau_res**2, axis=0)) < 1e-4)


EFFECT_CASES = {
    # name: (config, params, [(target, axes)])
    # rotorpy's Crazyflie: axial k_z 0.018 s/m (0.0054 kg/s at hover thrust, 0.29 N); 10x here
    "rotor_drag": (_random(17, speed_min_mps=0.8), {"k_x_s_per_m": 0.6, "k_y_s_per_m": 0.5, "k_z_s_per_m": 0.2},
                   [("force", (0, 1, 2))]),
    "parasitic_drag": (_random(1, speed_min_mps=0.8), {"c_xy_kg_per_m": 0.02, "c_z_kg_per_m": 0.03},
                       [("force", (0, 1, 2))]),
    "ground_effect": (SimConfig(kind="low_pass", duration_s=10.0, low_pass_height_m=0.04, seed=2),
                      {"k_ge": 15.0}, [("force", (2,))]),
    "motor_lag": (_random(3, speed_min_mps=0.8), {"tau_s": 0.04}, [("force", (2,)), ("torque", (0, 1, 2))]),
    "com_offset": (_random(4), {"x_c_m": 0.003, "y_c_m": -0.002}, [("torque", (0, 1))]),
    "thrust_scale": (_random(5), {"scale": 0.9}, [("force", (2,))]),
    "added_mass": (_random(6), {"m_p_kg": 0.005}, [("force", (2,))]),
    "wind": (_random(7), {"k_s_per_m": 0.5, "w_x_mps": 1.0, "w_y_mps": -0.5}, [("force", (0, 1))]),
    "rotor_imbalance": (_random(13), {"d_1": 0.05, "d_2": -0.03, "d_3": 0.02}, [("torque", (0, 1, 2))]),
    # 20 ms: at 30 ms this fast flight goes unstable under the nominal controller and hits the floor
    "thrust_delay": (_random(14, speed_min_mps=0.8), {"t_d_s": 0.02}, [("force", (2,)), ("torque", (0, 1, 2))]),
    "inertia_scale": (_random(16, speed_min_mps=0.8), {"s_x": 1.3, "s_y": 0.8, "s_z": 1.3},
                      [("torque", (0, 1))]),  # yaw: first order in ΔJ, 25 % off at s_z = 1.3
}


# The fast tier keeps rotor drag; the other effects run in the whole suite.
@pytest.mark.parametrize("name", [n if n == "rotor_drag" else pytest.param(n, marks=pytest.mark.slow)
                                  for n in EFFECT_CASES])
def test_each_effect_shows_up_as_its_wrench(tmp_path, name):
    config, params, checks = EFFECT_CASES[name]
    sim, fl, _ = _fly(tmp_path, config, {name: params})
    f_res, tau_res, f_eff, tau_eff = _compare(fl.tables["fixedFrequency"], sim)
    for target, axes in checks:
        res, eff = (f_res, f_eff) if target == "force" else (tau_res, tau_eff)
        for a in axes:
            _assert_matches(res[:, a], eff[:, a], f"{name} {target} {'xyz'[a]}")
    # and nothing where the effect does not act (at noise level)
    if all(target == "force" for target, _ in checks) and name not in ("thrust_scale",):
        assert np.all(np.sqrt(np.mean(tau_res**2, axis=0)) < 1e-4)
    if all(target == "torque" for target, _ in checks):
        assert np.all(np.sqrt(np.mean(f_res**2, axis=0)) < 1.5e-3)


def test_rotor_inertia_shows_up_as_its_wrench(tmp_path):
    """Spinning rotors up and down turns the body about z. Flown with a motor lag: with rotor
    speeds that step at every control sample, a rotor inertia of 3e-8 kg m^2 (a 45 mm
    propeller and its motor bell) makes the yaw loop ring. The lag's yaw torque has the
    opposite sign (it would cancel at J_r = 1e-8 with this lag), so the sum is checked. The yaw
    torque is small (1.3e-5 N m RMS): the gyro's noise floor is an eighth of it, so the
    difference allowed is a fifth of the wrench and the noise floor in quadrature."""
    from quadcore.identify.flightdata import sensor_noise_floor

    effs = {"motor_lag": {"tau_s": 0.02}, "rotor_inertia": {"J_r_kgm2": 3e-8}}
    sim, fl, _ = _fly(tmp_path, _random(15, speed_min_mps=0.8), effs)
    f_res, tau_res, f_eff, tau_eff = _compare(fl.tables["fixedFrequency"], sim)
    state = dynamics.flight_state(fl.tables["fixedFrequency"], VEHICLE)
    floor = sensor_noise_floor(state, VEHICLE, ~signals.near_gap(state.t_s))
    for a in range(3):
        _assert_matches(tau_res[:, a], tau_eff[:, a], f"rotor inertia + lag torque {'xyz'[a]}", noise=floor[3 + a])
    _, tau_spin = effects.get("rotor_inertia").wrench(state, VEHICLE, effs["rotor_inertia"])
    assert np.sqrt(np.mean(tau_spin[:, 2] ** 2)) > 5 * np.sqrt(np.mean(tau_spin[:, 0] ** 2))  # mostly yaw


def test_added_mass_is_true_mass_in_the_dynamics(tmp_path):
    sim = simulation.simulate(SimConfig(kind="hover", duration_s=4.0, seed=1), VEHICLE,
                              {"added_mass": {"m_p_kg": 0.01}})
    assert sim.true_mass_kg == pytest.approx(VEHICLE.mass_kg + 0.01)
    steady = sim.t_s > 2.5
    thrust = sim.f_actual_N[steady].sum(axis=1).mean()
    assert thrust == pytest.approx(sim.true_mass_kg * 9.80665, rel=0.01)  # it must carry the payload
    assert sim.sf_true[steady, 2].mean() == pytest.approx(9.80665, rel=0.01)  # accelerometer reads 1 g


def test_gusting_wind_still_matches_on_average(tmp_path):
    config = _random(9, wind_gust_std_mps=0.3, wind_gust_tau_s=1.0)
    params = {"k_s_per_m": 0.5, "w_x_mps": 0.8, "w_y_mps": 0.0}
    sim, fl, _ = _fly(tmp_path, config, {"wind": params})
    assert sim.wind_w_mps[:, 0].std() > 0.05  # the wind really gusts
    f_res, _, f_eff, _ = _compare(fl.tables["fixedFrequency"], sim)
    _assert_matches(f_res[:, 0], f_eff[:, 0], "gusty wind x", min_corr=0.8, max_rel=0.6)


def test_the_simulator_names_no_effect():
    """Effects with a mechanism fly through their own ``SimHook``: no effect name appears in
    the simulator's code (docstrings aside)."""
    tree = ast.parse(Path(simulation.__file__).read_text())
    docstrings = {id(node.body[0].value) for node in ast.walk(tree)
                  if isinstance(node, (ast.Module, ast.FunctionDef, ast.ClassDef)) and node.body
                  and isinstance(node.body[0], ast.Expr) and isinstance(node.body[0].value, ast.Constant)}
    literals = {node.value for node in ast.walk(tree)
                if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings}
    names = set(effects.builtin_names())
    assert not literals & names


def test_a_plugin_mechanism_flies_through_its_hook(tmp_path):
    """A user effect with a simulator hook (here: one rotor weaker) is flown without any
    change to the simulator, and its wrench is what the residual shows."""
    module = tmp_path / "weak_rotor.py"
    module.write_text('''
import numpy as np
from quadcore.physics import dynamics
from quadcore.effects import Effect, Parameter, SimHook
from quadcore.effects.base import body_z

class WeakRotor(SimHook):
    def __init__(self, gain):
        self.gain = gain
    def rotor_thrusts(self, f_N, k, j):
        return [f_N[0] * self.gain, *f_N[1:]]

class WeakFirstRotor(Effect):
    name = "weak_first_rotor"
    target = "both"
    linear = True
    parameters = (Parameter("gain", "1", 1.0, 0.5, 1.5, "rotor 1 thrust / mapped thrust"),)
    def wrench(self, state, vehicle, params):
        df = np.zeros_like(state.f_rotor_N)
        df[:, 0] = (params["gain"] - 1.0) * state.f_rotor_N[:, 0]
        T, tau = dynamics.wrench_from_thrusts(vehicle, df)
        return body_z(T), tau
    def simulator(self, params, context):
        return WeakRotor(params["gain"])

EFFECT = WeakFirstRotor()
''')
    effects.load_plugin(module)
    try:
        sim, fl, _ = _fly(tmp_path, _random(12), {"weak_first_rotor": {"gain": 0.9}})
        assert np.allclose(sim.f_actual_N[:, 0], 0.9 * sim.f_map_N[:, 0])
        f_res, tau_res, f_eff, tau_eff = _compare(fl.tables["fixedFrequency"], sim)
        _assert_matches(f_res[:, 2], f_eff[:, 2], "weak rotor force z")
        for a in (0, 1):
            _assert_matches(tau_res[:, a], tau_eff[:, a], f"weak rotor torque {'xyz'[a]}")
    finally:
        effects.unregister("weak_first_rotor")


def test_two_effects_compose(tmp_path):
    effs = {"rotor_drag": {"k_x_s_per_m": 0.6, "k_y_s_per_m": 0.5}, "com_offset": {"x_c_m": 0.003, "y_c_m": -0.002}}
    sim, fl, _ = _fly(tmp_path, _random(8), effs)
    f_res, tau_res, f_eff, tau_eff = _compare(fl.tables["fixedFrequency"], sim)
    for a in (0, 1):
        _assert_matches(f_res[:, a], f_eff[:, a], f"composed force {'xyz'[a]}")
        _assert_matches(tau_res[:, a], tau_eff[:, a], f"composed torque {'xyz'[a]}")


# ---------------------------------------------------------------------------------------
# Truth files, sets, references
# ---------------------------------------------------------------------------------------

def test_simulate_set_writes_logs_and_truth(tmp_path):
    configs = [SimConfig(kind="hover", duration_s=1.5, seed=s) for s in (0, 1)]
    eff = {"thrust_scale": {"scale": 0.95}}
    written = simulation.simulate_set(tmp_path, configs, eff, VEHICLE)
    assert [p.name for p, _ in written] == ["sim000", "sim001"]
    assert flight.discover_logs(tmp_path) == [tmp_path / "sim000", tmp_path / "sim001"]  # sidecars skipped
    truth = json.loads((tmp_path / "sim001.truth.json").read_text())
    assert truth["effects"] == {"thrust_scale": {"scale": 0.95}}
    assert truth["vehicle"] == "crazyflie21" and truth["seed"] == 1 and truth["true_mass_kg"] == VEHICLE.mass_kg
    assert SimConfig.from_dict(truth["config"]) == replace(configs[1], name="sim001")


def test_default_flights_are_varied_and_fast():
    configs = simulation.default_flights(0)
    kinds = [c.kind for c in configs]
    assert {"figure8", "circle0", "yaw0", "random", "low_pass"} <= set(kinds)
    assert sum(simulation.flight_duration(c) for c in configs) < 80
    low = next(c for c in configs if c.kind == "low_pass")
    t_s = np.arange(0, simulation.flight_duration(low), 0.002)
    ref = simulation.build_reference(low, t_s, np.random.default_rng(0))
    assert 0.03 <= ref.p_w_m[:, 2].min() <= 0.08
    fast = max((c for c in configs if c.kind == "random"), key=lambda c: c.speed_max_mps)
    ref = simulation.build_reference(fast, np.arange(0, 10, 0.002), np.random.default_rng(fast.seed))
    assert np.linalg.norm(ref.v_w_mps, axis=1).max() > 1.0


def test_plan_reference_is_relative_in_position_absolute_in_yaw_and_time_scaled():
    plan = trajectories.load_plan("circle0")
    assert plan.duration_s == pytest.approx(2.0)
    t = np.arange(0, 15, 0.002)
    ref = trajectories.plan_reference(t, plan, height_m=0.4, timescale=3.0, start_height_m=0.1,
                                      takeoff_s=2.0, hover_s=1.0)
    start = np.searchsorted(t, 3.0)
    np.testing.assert_allclose(ref.p_w_m[start], [0, 0, 0.4], atol=1e-6)  # plan starts at the hover point
    speed = np.linalg.norm(ref.v_w_mps, axis=1).max()
    raw_speed = np.linalg.norm(plan.evaluate(np.linspace(0, 2, 4001), 1)[:, :3], axis=1).max()
    assert speed == pytest.approx(raw_speed / 3.0, rel=0.01)
    yaw = trajectories.load_plan("yaw0")
    assert yaw.evaluate(np.zeros(1))[0, 3] == pytest.approx(1.26012)  # absolute yaw, radians
    assert trajectories.load_plan("figure8").duration_s == pytest.approx(7.283185)


# ---------------------------------------------------------------------------------------
# CLI
# ---------------------------------------------------------------------------------------

def _run(argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main(argv)
    return code, out.getvalue(), err.getvalue()


def test_cli_simulate_writes_logs_and_truth(tmp_path):
    out = tmp_path / "sims"
    code, stdout, _ = _run(["simulate", "--out", str(out), "--kind", "hover", "--duration", "2", "--flights", "2",
                            "--effect", "rotor_drag:k_x_s_per_m=0.3,k_y_s_per_m=0.2", "--seed", "4"])
    assert code == 0
    assert sorted(p.name for p in out.iterdir()) == ["sim000", "sim000.truth.json", "sim001", "sim001.truth.json"]
    assert str(out.resolve()) in stdout and "truth.json" in stdout
    truth = json.loads((out / "sim000.truth.json").read_text())
    # every parameter flown, the ones not given at their 'no effect' value
    assert truth["effects"] == {"rotor_drag": {"k_x_s_per_m": 0.3, "k_y_s_per_m": 0.2, "k_z_s_per_m": 0.0}}
    assert truth["seed"] == 4 and truth["config"]["kind"] == "hover"
    fl = flight.decode_flight(out / "sim001")
    assert fl.tables["fixedFrequency"].height > 900


@pytest.mark.parametrize("spec, message", [
    ("bogus:x=1", "unknown effect 'bogus'"),
    ("rotor_drag:k=1", "has no parameter 'k'"),
    ("rotor_drag:k_x_s_per_m=fast", "must be a number"),
    ("rotor_drag", "needs parameters"),
])
def test_cli_simulate_bad_effect_is_a_user_error(tmp_path, spec, message):
    code, _, stderr = _run(["simulate", "--out", str(tmp_path / "x"), "--kind", "hover", "--duration", "1",
                            "--effect", spec])
    assert code == 2
    assert message in stderr and "Traceback" not in stderr
    assert not (tmp_path / "x").exists()


def test_a_log_can_start_mid_manoeuvre():
    """``log_start_s``: the log holds the same flight from that time on, its clock restarting
    there: the vehicle already moving, a motor lag's state not at rest on the first command."""
    cfg = _random(1, duration=6.0, speed_min_mps=0.8)
    whole = simulation.simulate(cfg, VEHICLE, {"motor_lag": {"tau_s": 0.04}})
    late = simulation.simulate(replace(cfg, log_start_s=3.3), VEHICLE, {"motor_lag": {"tau_s": 0.04}})
    skip = int(round(3.3 * cfg.log_rate_hz))
    np.testing.assert_allclose(late.t_s, whole.t_s[skip:] - whole.t_s[skip], atol=1e-12)
    for a, b in ((late.v_true, whole.v_true), (late.f_actual_N, whole.f_actual_N), (late.pwm_raw, whole.pwm_raw)):
        np.testing.assert_array_equal(a, b[skip:])
    assert np.linalg.norm(late.v_true[0]) > 0.3  # in motion on the first logged sample
    assert np.max(np.abs(late.f_actual_N[0] - late.f_map_N[0])) > 0.01  # the lag is not at rest there
    assert late.truth()["duration_s"] == pytest.approx(6.0 - 3.3, abs=0.01)
    with pytest.raises(simulation.SimulationError, match="log_start_s"):
        simulation.simulate(replace(cfg, log_start_s=6.5), VEHICLE)


def test_a_flight_that_starts_at_the_floor_is_a_configuration_error_not_a_lost_vehicle():
    """The simulator has no ground contact, so a reference at or below the floor is refused up
    front with what to change (before, ``start_height_m = 0`` simulated and then reported "lost
    control: it reached the floor at t = 0.00 s")."""
    for bad in ({"start_height_m": 0.0}, {"height_m": -0.1}):
        with pytest.raises(simulation.SimulationError, match="above the floor"):
            simulation.simulate(replace(_random(1, duration=3.0), **bad), VEHICLE)


def test_a_flight_can_start_off_its_reference_with_the_rotors_at_hover():
    """``start_offset_m``: the vehicle starts away from the reference, so the first commands are
    a correction, while a lag's rotors (and a delay's history) still give the hover thrust."""
    cfg = replace(_random(2, duration=3.0), start_offset_m=(0.1, -0.1, 0.05))
    hover = VEHICLE.weight_N / VEHICLE.n_rotors
    for effect in ({"motor_lag": {"tau_s": 0.04}}, {"thrust_delay": {"t_d_s": 0.02}}):
        sim = simulation.simulate(cfg, VEHICLE, effect)
        np.testing.assert_allclose(sim.p_true[0], np.array([0.1, -0.1, cfg.start_height_m + 0.05]), atol=1e-12)
        np.testing.assert_allclose(sim.f_actual_N[0], hover, rtol=1e-12)
        assert np.max(np.abs(sim.f_map_N[0] - hover)) > 0.01  # the first command is no hover


def test_a_vehicle_the_controller_cannot_fly_is_an_error_not_a_log():
    """A rotor lag as slow as the one fitted on the real flights (0.106 s) makes the controller's
    attitude loop (tuned for the nominal vehicle, 30 rad/s) unstable: the vehicle flips in take-off
    and falls to the floor, where the simulator has no ground contact and only holds it out, a
    velocity jump the accelerometer never sees. That is no flight: a typed error says so, where
    before a log was written that the physics gate refuses ('the state estimate contradicts
    itself'). A lag the loop can fly still gives a flight that the gate passes."""
    cfg = SimConfig(kind="hover", duration_s=4.0, seed=0)
    with pytest.raises(simulation.SimulationError, match=r"lost control: it turned upside down at t = 1\.\d\d s.*"
                                                         r"motor_lag \(tau_s=0\.106\)"):
        simulation.simulate(cfg, VEHICLE, {"motor_lag": {"tau_s": 0.106}})
    sim = simulation.simulate(cfg, VEHICLE, {"motor_lag": {"tau_s": 0.03}})
    assert simulation.lost_control(sim.t_s, sim.p_true, sim.q_true) is None
    # what the check reads: upside down, or on the floor
    q_flipped = np.tile([1.0, 0.0, 0.0, 0.0], (len(sim.t_s), 1))  # 180 degrees about x
    assert "upside down at t = 0.00 s" in simulation.lost_control(sim.t_s, sim.p_true, q_flipped)
    p_floor = sim.p_true.copy()
    p_floor[500:, 2] = 0.0
    assert f"reached the floor at t = {sim.t_s[500]:.2f} s" in simulation.lost_control(sim.t_s, p_floor, sim.q_true)


def test_a_flight_that_loses_control_does_not_stop_the_others(tmp_path):
    """simulate_set: the flights that fly are written; one error then names the one that did not."""
    configs = [SimConfig(kind="hover", duration_s=3.0, seed=s) for s in (0, 1, 2)]
    lag = [{}, {"motor_lag": {"tau_s": 0.106}}, {}]
    with pytest.raises(simulation.SimulationError, match=r"1 of 3 flights not written \(2 written .*sim001: the "
                                                         r"simulated vehicle lost control"):
        simulation.simulate_set(tmp_path, configs, lag, VEHICLE)
    assert sorted(p.name for p in flight.discover_logs(tmp_path)) == ["sim000", "sim002"]
