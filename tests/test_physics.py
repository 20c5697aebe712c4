"""The physics core on cases with a known answer, on the real flights, and with a user vehicle."""

from __future__ import annotations

from dataclasses import fields, replace
from importlib import resources

import numpy as np
import polars as pl
import pytest

from quadcore import cli
from quadcore.logs import flight
from quadcore.physics import dynamics, propagation, residuals, rotations, signals, vehicle
from quadcore.sim import simulation

VEH = vehicle.load()
RATE_HZ = 500.0


def synthetic_flight(n: int, omega_b: np.ndarray, omega_dot_b: np.ndarray, f_inj_b: np.ndarray,
                     tau_inj_b: np.ndarray, vbat: float = 3.8) -> pl.DataFrame:
    """A decoded-style table whose true body force and torque are the rotors' plus (f_inj, tau_inj).

    Rotor thrusts are chosen so that the rotors alone give collective thrust = weight and
    the torque J dω/dt + ω × Jω - tau_inj; the accelerometer reads (thrust + f_inj) / m.
    """
    t = np.arange(n) / RATE_HZ
    tau_true = dynamics.torque_for_angular_acceleration(VEH, omega_b, omega_dot_b)
    wrench = np.column_stack([np.full(n, VEH.weight_N), tau_true - tau_inj_b])
    f_rotor = np.linalg.solve(VEH.allocation, wrench.T).T
    pwm = VEH.pwm_vbat.pwm_for_thrust(f_rotor, np.full((n, 1), vbat))
    f_rotor = VEH.pwm_vbat.thrust_N(pwm, np.full((n, 1), vbat))  # exactly what the map gives
    T, tau_rot = dynamics.wrench_from_thrusts(VEH, f_rotor)
    sf = (np.column_stack([np.zeros(n), np.zeros(n), T]) + f_inj_b) / VEH.mass_kg
    q = np.zeros((n, 4))
    q[0] = [0, 0, 0, 1]
    for k in range(n - 1):  # test fixture, not a hot path
        q[k + 1] = rotations.integrate_body_rate(q[k: k + 1], omega_b[k: k + 1], np.array([1 / RATE_HZ]))[0]
    # the state estimate consistent with the attitude and the accelerometer (the physics gate checks it)
    a_w = rotations.body_to_world(rotations.rotation_matrix(q), sf) + dynamics.GRAVITY_W_MPS2
    v_w = np.vstack([np.zeros((1, 3)), np.cumsum(0.5 * (a_w[1:] + a_w[:-1]) / RATE_HZ, axis=0)])
    p_w = np.array([0.0, 0.0, 1.0]) + np.vstack([np.zeros((1, 3)), np.cumsum(0.5 * (v_w[1:] + v_w[:-1]) / RATE_HZ,
                                                                             axis=0)])
    cols = {"t_s": t, "timestamp_us": (t * 1e6).astype(np.int64)}
    for i, a in enumerate("xyz"):
        cols[f"p_w_{a}_m"] = p_w[:, i]
        cols[f"v_w_{a}_mps"] = v_w[:, i]
        cols[f"omega_b_{a}_radps"] = omega_b[:, i]
        cols[f"sf_b_{a}_mps2"] = sf[:, i]
    for i, a in enumerate("xyzw"):
        cols[f"q_{a}"] = q[:, i]
    for i in range(4):
        cols[f"pwm_{i + 1}"] = pwm[:, i]
    cols["vbat_V"] = np.full(n, vbat)
    return pl.DataFrame(cols)


def interior(x: np.ndarray, margin: int = signals.WINDOW) -> np.ndarray:
    return x[margin:-margin]


def test_allocation_is_the_x_layout_of_the_readme():
    a = 0.046 / np.sqrt(2)
    f = np.array([[0.1, 0.2, 0.3, 0.4]])
    T, tau = dynamics.wrench_from_thrusts(VEH, f)
    f1, f2, f3, f4 = f[0]
    assert T[0] == pytest.approx(f.sum())
    assert tau[0, 0] == pytest.approx(a * (-f1 - f2 + f3 + f4))
    assert tau[0, 1] == pytest.approx(a * (-f1 + f2 + f3 - f4))
    assert tau[0, 2] == pytest.approx(0.006 * (-f1 + f2 - f3 + f4))


def test_vehicle_at_rest_has_zero_residual():
    n = 1000
    zero = np.zeros((n, 3))
    table = residuals.residual_table(synthetic_flight(n, zero, zero, zero, zero), VEH)
    for col in residuals.F_RES_B + residuals.TAU_RES_B + residuals.F_RES_W:
        assert np.abs(table[col].to_numpy()).max() < 1e-9, col
    assert table["T_N"].to_numpy() == pytest.approx(VEH.weight_N, rel=1e-9)


def test_injected_force_and_torque_come_back():
    n = 3000
    t = np.arange(n) / RATE_HZ
    amp, freq = np.array([2.0, -1.5, 0.8]), np.array([0.7, 1.1, 0.5])
    omega = amp * np.sin(2 * np.pi * freq * t[:, None])
    omega_dot = amp * 2 * np.pi * freq * np.cos(2 * np.pi * freq * t[:, None])
    f_inj = np.array([0.012, -0.020, 0.005])
    tau_inj = np.array([2.0e-4, -1.0e-4, 5.0e-5])
    table = residuals.residual_table(synthetic_flight(n, omega, omega_dot, np.tile(f_inj, (n, 1)),
                                                      np.tile(tau_inj, (n, 1))), VEH)
    f_res = interior(table.select(residuals.F_RES_B).to_numpy())
    tau_res = interior(table.select(residuals.TAU_RES_B).to_numpy())
    np.testing.assert_allclose(f_res, np.tile(f_inj, (len(f_res), 1)), atol=1e-6)
    # the derivative of a 0.5-1.1 Hz sine through the smoother: errors of a few per cent of the rate
    np.testing.assert_allclose(tau_res.mean(axis=0), tau_inj, rtol=0.02)
    assert np.abs(tau_res - tau_inj).max() < 0.1 * np.abs(tau_inj).max()
    # world frame is the body frame rotated: same norm
    f_w = interior(table.select(residuals.F_RES_W).to_numpy())
    np.testing.assert_allclose(np.linalg.norm(f_w, axis=1), np.linalg.norm(f_res, axis=1), rtol=1e-9)


def test_smoother_has_no_phase_lag():
    t = np.arange(2000) / RATE_HZ
    x = np.sin(2 * np.pi * 2.0 * t)
    y = signals.smooth(x)
    lags = np.arange(-20, 21)
    xc = [np.dot(interior(x), interior(np.roll(y, -k))) for k in lags]
    assert lags[int(np.argmax(xc))] == 0


@pytest.mark.parametrize("shape", [(7,), (32, 3), (3900, 3), (100, 2, 2)])
def test_cached_savitzky_golay_is_scipys(shape):
    """The smoother and the derivative with their plan cached give scipy's ``savgol_filter``
    (mode ``interp``): the same convolution inside, bit for bit, the same edge fits to rounding."""
    from scipy.signal import savgol_filter

    x = np.random.default_rng(3).standard_normal(shape).cumsum(axis=0)
    t = np.arange(shape[0]) / RATE_HZ
    w = signals._window(shape[0], signals.WINDOW)
    for deriv, got in ((0, signals.smooth(x)), (1, signals.derivative(x, t))):
        want = savgol_filter(x, w, signals.ORDER, deriv=deriv, delta=float(np.median(np.diff(t))), axis=0,
                             mode="interp")
        np.testing.assert_array_equal(got[w // 2: len(x) - w // 2], want[w // 2: len(x) - w // 2])
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-13 * np.abs(want).max())


@pytest.fixture(scope="module")
def sim_flight(tmp_path_factory):
    folder = tmp_path_factory.mktemp("sim")
    cfg = simulation.SimConfig(kind="random", duration_s=8.0, seed=11)
    (log_path, _), = simulation.simulate_set(folder, [cfg], {})
    return flight.decode_flight(log_path).tables["fixedFrequency"]


@pytest.mark.parametrize("n", [1, 2])
def test_too_short_flight_gives_no_rollout_rows_but_the_columns(sim_flight, n):
    """(The fleet's physics gate refuses such a flight first; the library still answers in shape.)"""
    full = dynamics.flight_state(sim_flight, VEH)
    state = replace(full, **{f.name: getattr(full, f.name)[:n] for f in fields(full)
                             if isinstance(getattr(full, f.name), np.ndarray)})
    growth = propagation.error_growth(state, VEH, horizons_s=(0.1,))
    assert growth.height == 0 and growth.schema == propagation.GROWTH_SCHEMA
    assert propagation.horizon_summary(growth).height == 0


def test_rollout_error_grows_with_horizon_and_one_step_is_small(sim_flight):
    state = dynamics.flight_state(sim_flight, VEH)
    growth = propagation.error_growth(state, VEH, horizons_s=(0.1, 0.5))
    ends = propagation.horizon_summary(growth)
    pos = ends["pos_err_m"].to_list()
    assert pos == sorted(pos), pos  # one step < 0.1 s < 0.5 s
    one_step = ends.row(0, named=True)
    assert one_step["pos_err_m"] < 1e-3 and one_step["att_err_deg"] < 0.5
    assert ends.filter(pl.col("horizon_s") == 0.1)["pos_err_m"][0] < 0.02


def test_windows_of_several_lengths_in_one_rollout_are_each_window_alone(sim_flight):
    """One rollout with a step count per start (what error_growth runs for all its horizons)
    gives every window the errors it has when rolled out on its own (to rounding: NumPy's
    vectorised sin/cos may round a row differently in another batch), NaN past its end."""
    state = dynamics.flight_state(sim_flight, VEH)
    starts, steps = np.array([700, 100, 400, 1000]), np.array([5, 60, 1, 60])
    together = propagation.rollout(state, VEH, starts, steps)
    for row, (start, n) in enumerate(zip(starts, steps)):
        alone = propagation.rollout(state, VEH, np.array([start]), int(n))
        for key, errors in together.items():
            np.testing.assert_allclose(errors[row, :n + 1], alone[key][0], rtol=1e-12, atol=1e-15)
            assert np.isnan(errors[row, n + 1:]).all()


def test_quaternion_integration_is_exact_for_constant_rate():
    q0 = np.array([[0.0, 0.0, 0.0, 1.0]])
    w = np.array([[0.0, 0.0, np.pi]])  # half a turn per second about z
    q = q0
    for _ in range(100):
        q = rotations.integrate_body_rate(q, w, np.array([0.01]))
    assert rotations.angle_between_rad(q, np.array([[0.0, 0.0, 1.0, 0.0]]))[0] < 1e-9


def test_a_user_vehicle_file_changes_the_results(tmp_path, sim_flight):
    text = (resources.files("quadcore") / "vehicles" / "crazyflie21.toml").read_text()
    heavier = tmp_path / "heavier.toml"
    heavier.write_text(text.replace("mass_kg = 0.0347", "mass_kg = 0.0400"))
    v2 = vehicle.load(heavier)
    assert v2.mass_kg == 0.04
    base = residuals.residual_table(sim_flight, VEH)
    other = residuals.residual_table(sim_flight, v2)
    # measured force scales with the mass; the thrust model does not
    ratio = other["f_meas_b_z_N"].mean() / base["f_meas_b_z_N"].mean()
    assert ratio == pytest.approx(0.04 / 0.0347, rel=1e-6)
    assert other["f_res_b_z_N"].mean() > base["f_res_b_z_N"].mean() + 0.03


def test_cli_residuals_uses_the_vehicle_file(tmp_path, capsys):
    folder = tmp_path / "raw"
    simulation.simulate_set(folder, [simulation.SimConfig(kind="hover", duration_s=4.0, seed=2)], {})
    assert cli.main(["residuals", str(folder)]) == 0
    nominal = capsys.readouterr().out
    assert cli.main(["residuals", str(folder), "--vehicle", str(tmp_path / "missing.toml")]) == 2
    assert "vehicle file not found" in capsys.readouterr().err
    assert "crazyflie21" in nominal and "sim000" in nominal


def test_fit_thrust_recovers_the_simulated_k_F(tmp_path):
    folder = tmp_path / "raw"
    simulation.simulate_set(folder, [simulation.SimConfig(kind="figure8", duration_s=8.0, seed=4)], {})
    table = flight.decode_flight(folder / "sim000").tables["fixedFrequency"]
    from quadcore.physics import thrustfit

    k_F, _ = thrustfit.fit_k_F({"sim000": table}, VEH)
    assert k_F == pytest.approx(VEH.motor_speed.k_F_N_per_radps2, rel=0.02)
    out = thrustfit.write_k_F((resources.files("quadcore") / "vehicles" / "crazyflie21.toml").read_text(),
                              1.5e-8, tmp_path / "vehicles" / "v.toml")  # a new folder is made
    assert vehicle.load(out).motor_speed.k_F_N_per_radps2 == 1.5e-8


# ------------------------------------------------------------------ real flights


@pytest.fixture(scope="module")
def real_residuals(real_logs):
    out = {}
    for name in ("jana00", "jana02", "jana03", "jana05"):
        out[name] = residuals.residual_table(flight.decode_flight(real_logs / name).tables["fixedFrequency"], VEH)
    return out


def test_real_hover_residual_is_small(real_residuals):
    for name, table in real_residuals.items():
        hover = table.filter(~pl.col("near_gap") & (pl.col("T_N") > 0.5 * VEH.weight_N)
                             & ((pl.col("v_w_x_mps") ** 2 + pl.col("v_w_y_mps") ** 2
                                 + pl.col("v_w_z_mps") ** 2) < 0.01))
        assert hover.height > 100, name
        # horizontal: near zero; vertical: the thrust map is within 10 % of the weight at hover
        assert abs(hover["f_res_b_x_N"].mean()) < 0.01 and abs(hover["f_res_b_y_N"].mean()) < 0.01, name
        assert abs(hover["f_res_b_z_N"].mean()) < 0.1 * VEH.weight_N, name


def test_real_horizontal_residual_opposes_body_velocity(real_residuals):
    for name in ("jana00", "jana02", "jana03"):  # figure-8 flights: fast enough for drag to show
        t = real_residuals[name].filter(~pl.col("near_gap"))
        for a in "xy":
            r = np.corrcoef(t[f"f_res_b_{a}_N"], t[f"v_b_{a}_mps"])[0, 1]
            assert r < -0.5, (name, a, r)


def test_motor_speed_thrust_map_is_selectable(real_logs):
    table = flight.decode_flight(real_logs / "jana02").tables["fixedFrequency"]
    by_speed = residuals.residual_table(table, VEH.with_thrust_map("motor_speed"))
    by_pwm = residuals.residual_table(table, VEH)
    assert not np.allclose(by_speed["T_N"], by_pwm["T_N"])
    # both maps give roughly the weight on average
    for t in (by_speed, by_pwm):
        assert t["T_N"].mean() == pytest.approx(VEH.weight_N, rel=0.2)


def test_bad_vehicle_values_and_missing_columns_are_typed_errors(tmp_path, sim_flight, capsys):
    text = (resources.files("quadcore") / "vehicles" / "crazyflie21.toml").read_text()
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace("mass_kg = 0.0347", 'mass_kg = "heavy"'))
    with pytest.raises(vehicle.VehicleFileError, match="mass_kg = .heavy.: expected a finite number"):
        vehicle.load(bad)
    hexa = tmp_path / "hexa.toml"
    extra = "\n".join(f"[[rotors]]\narm_m = 0.046\nangle_deg = {a}\nyaw_sign = 1\n" for a in (90.0, -90.0))
    hexa.write_text(text.replace("[thrust_map]", extra + "\n[thrust_map]", 1))
    six = vehicle.load(hexa)
    assert six.n_rotors == 6
    with pytest.raises(dynamics.MissingColumnsError, match="pwm_5"):
        residuals.residual_table(sim_flight, six)
    without_vbat = sim_flight.drop("vbat_V")
    with pytest.raises(dynamics.MissingColumnsError, match="pm.vbatMV"):
        residuals.residual_table(without_vbat, VEH)
    folder = tmp_path / "raw"
    simulation.simulate_set(folder, [simulation.SimConfig(kind="hover", duration_s=3.0, seed=3)], {})
    assert cli.main(["residuals", str(folder), "--vehicle", str(hexa)]) == 2
    assert "pwm_5" in capsys.readouterr().err
    assert cli.main(["residuals", str(folder), "--vehicle", str(bad)]) == 2
