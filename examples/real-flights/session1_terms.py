"""session1_terms: terms found by ``quadcore discover``, as a linear effect. List this file under
``plugins`` in the model file and ``session1_terms`` under ``effects``: the fit refits the coefficients.

Discovered on top of the model nominal+thrust_scale+rotor_drag+motor_lag+discovered_terms (holdout;
evaluated on jana02):

    f_res_b_y_N ≈ -0.000148 kg m/rad^2 · omega_b_z_radps*omega_b_z_radps (± 1.8e-05; explains -0%
        held out, kept in 4/5 folds)
    f_res_b_y_N ≈ +0.000245 kg m/rad · omega_dot_b_x_radps2 (± 8.1e-05; explains 9% held out, kept
        in 4/5 folds)
    f_res_b_z_N ≈ +0.00968 kg/m · v_b_x_mps*v_b_x_mps (± 0.003; explains 32% held out, kept in 5/5
        folds)
    tau_res_b_y_Nm ≈ -0.00188 · T_N*p_w_z_m (± 0.00084; explains 37% held out, kept in 3/5 folds)
    tau_res_b_z_Nm ≈ -3.47e-07 kg m^2/(s rad) · Omega_net_radps (± 4.2e-08; explains 65% held out,
        kept in 5/5 folds)
    tau_res_b_z_Nm ≈ +3.49e-08 kg m^2/rad · d(Omega_net_radps)/dt (± 1e-08; explains -6% held out,
        kept in 5/5 folds)

Literature:
    omega_b_z_radps*omega_b_z_radps: inertia-tensor error (Euler's ω × Jω term)
    omega_dot_b_x_radps2: centre-of-mass offset (tangential acceleration α × r)
    v_b_x_mps*v_b_x_mps: a force growing with the horizontal speed squared: translational lift along
        z (momentum theory), quadratic drag in the horizontal
    d(Omega_net_radps)/dt: rotor inertia: reaction torque of accelerating rotors

Each parameter is the coefficient of one term on one residual axis (SI; default 0 = no effect).
The terms are evaluated by quadcore.identify.discovery.terms.evaluate.
"""

from quadcore.identify.discovery import DiscoveredEffect

# (target axis, term, parameter, unit of the parameter, bound on |parameter|)
TERMS = [
    (
        'f_res_b_y_N',
        'omega_b_z_radps*omega_b_z_radps',
        'f_y__omega_b_z_radps_times_omega_b_z_radps__kg_m_per_rad2',
        'kg m/rad^2',
        0.014788377209833822,
    ),
    (
        'f_res_b_y_N',
        'omega_dot_b_x_radps2',
        'f_y__omega_dot_b_x_radps2__kg_m_per_rad',
        'kg m/rad',
        0.024461380991741312,
    ),
    (
        'f_res_b_z_N',
        'v_b_x_mps*v_b_x_mps',
        'f_z__v_b_x_mps_times_v_b_x_mps__kg_per_m',
        'kg/m',
        0.9684752790402053,
    ),
    (
        'tau_res_b_y_Nm',
        'T_N*p_w_z_m',
        'tau_y__T_N_times_p_w_z_m__1',
        '1',
        0.18805957127882938,
    ),
    (
        'tau_res_b_z_Nm',
        'Omega_net_radps',
        'tau_z__Omega_net_radps__kg_m2_per_s_rad',
        'kg m^2/(s rad)',
        3.469845404995509e-05,
    ),
    (
        'tau_res_b_z_Nm',
        'd(Omega_net_radps)/dt',
        'tau_z__d_Omega_net_radps_dt__kg_m2_per_rad',
        'kg m^2/rad',
        3.4925087836462804e-06,
    ),
]

EFFECT = DiscoveredEffect('session1_terms', TERMS, __doc__)
