"""rotorpy's Crazyflie as this project's vehicle file, and the fixed-step integration of its
dynamics, checked against rotorpy itself (fast: no flight is simulated)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rotorpy", reason="rotorpy (the dev extra) is not installed: the independent-physics suite "
                    "needs it")

from independent import rotorpy_flights as rf  # noqa: E402
from quadcore.physics import vehicle  # noqa: E402


def test_the_vehicle_file_is_rotorpys_crazyflie_in_firmware_motor_order():
    """Mass, inertia, thrust coefficient, and the allocation: this project's ``A`` (thrusts in
    firmware order m1..m4 -> [T, tau_x, tau_y, tau_z]) equals rotorpy's ``f_to_TM`` with its
    rotors r1..r4 taken as m4, m1, m2, m3 (rf.FIRMWARE_FROM_ROTORPY)."""
    p = rf.base_params()
    veh = vehicle.load(rf.VEHICLE_FILE)
    assert veh.mass_kg == p["mass"]
    assert np.diag(veh.inertia_kgm2) == pytest.approx([p["Ixx"], p["Iyy"], p["Izz"]])
    assert veh.motor_speed.k_F_N_per_radps2 == p["k_eta"]
    rotors = [p["rotor_pos"][f"r{i + 1}"] for i in range(4)]
    f_to_TM = np.vstack([np.ones(4), np.array([np.cross(r, [0.0, 0.0, 1.0])[:2] for r in rotors]).T,
                         p["k_m"] / p["k_eta"] * np.asarray(p["rotor_directions"])])
    assert veh.allocation == pytest.approx(f_to_TM[:, rf.FIRMWARE_FROM_ROTORPY], abs=1e-12)


def test_fixed_step_rk4_follows_rotorpys_own_step():
    """0.2 s of a circle, rotor drag and motor lag on: the generator's RK4 at 1 kHz and rotorpy's
    ``Multirotor.step`` (solve_ivp, tight tolerances) under the same held commands agree to
    micrometres and micro-radians per second."""
    from rotorpy.controllers.quadrotor_control import SE3Control
    from rotorpy.vehicles.multirotor import Multirotor

    flight = rf.Flight("t", "circle", 3, 0.2)
    physics = rf.Physics.rotorpy_default()
    trace = rf.simulate(flight, physics)
    params = physics.params()
    traj = rf.trajectory(flight)
    quad = Multirotor(params, initial_state=None, control_abstraction="cmd_motor_speeds", aero=True,
                      integrator_kwargs={"method": "RK45", "rtol": 1e-10, "atol": 1e-12})
    controller = SE3Control(params)
    state = rf._initial_state(traj, params)
    dt = 1.0 / rf.RATE_HZ
    for k in range(len(trace.t_s)):
        assert state["x"] == pytest.approx(trace.p_w_m[k], abs=1e-6)
        assert state["w"] == pytest.approx(trace.omega_b_radps[k], abs=1e-5)
        assert state["rotor_speeds"][rf.FIRMWARE_FROM_ROTORPY] == pytest.approx(trace.rotor_radps[k], abs=1e-4)
        control = controller.update(k * dt, state, traj.update(k * dt))
        state = quad.step(state, control, dt)
