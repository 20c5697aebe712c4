"""discovered_terms: terms found by ``quadcore discover``, as a linear effect. List this file under
``plugins`` in the model file and ``discovered_terms`` under ``effects``: the fit refits the coefficients.

Discovered on top of the model nominal+thrust_scale+rotor_drag+motor_lag (holdout; evaluated on
jana02):

    f_res_b_x_N ≈ +5.6e-07 kg m/(s rad) · motor_1_radps (± 4.2e-08; explains 7% held out, kept in
        5/5 folds)
    f_res_b_z_N ≈ +0.0134 s/rad · omega_b_z_radps*T_N (± 0.0023; explains 0% held out, kept in 3/5
        folds)
    f_res_b_z_N ≈ -6.97e-06 kg m/(s rad) · Omega_net_radps (± 2.2e-06; explains 9% held out, kept in
        5/5 folds)
    tau_res_b_x_Nm ≈ -8.59e-08 kg m^2/(s rad) · motor_3_radps (± 7.5e-09; explains 34% held out,
        kept in 5/5 folds)
    tau_res_b_x_Nm ≈ +0.000385 kg m/s · v_b_y_mps (± 3.5e-05; explains 57% held out, kept in 4/5
        folds)
    tau_res_b_y_Nm ≈ -0.000478 kg m/s · v_b_x_mps (± 6.3e-05; explains 83% held out, kept in 5/5
        folds)
    tau_res_b_z_Nm ≈ +0.000613 s^2/kg · T_N*T_N (± 4.8e-05; explains 87% held out, kept in 5/5
        folds)

Literature:
    v_b_y_mps: a moment growing with the horizontal velocity: the blade-flapping hub moment (Mahony,
        Kumar & Corke 2012), or rotor drag acting above the centre of mass (r × F); the two have the
        same form
    v_b_x_mps: a moment growing with the horizontal velocity: the blade-flapping hub moment (Mahony,
        Kumar & Corke 2012), or rotor drag acting above the centre of mass (r × F); the two have the
        same form
    T_N*T_N: a trim torque growing with thrust: centre-of-mass offset (r × thrust) in roll and
        pitch; in yaw, rotors whose torque-to-thrust ratios differ, or tilted motors

Kept by discover but left out here, as they have no C form for the flight controller:
    f_res_b_x_N ≈ -0.000191 kg m/rad · omega_dot_b_y_radps2 (± 3.3e-05; explains 3% held out, kept
        in 5/5 folds): a zero-phase smoothed time derivative (it needs samples after the present
        one): a flight controller cannot compute it

Each parameter is the coefficient of one term on one residual axis (SI; default 0 = no effect).
The terms are evaluated by quadcore.identify.discovery.terms.evaluate; every one has a C form (quadcore export-c).
"""

from quadcore.identify.discovery import DiscoveredEffect

# (target axis, term, parameter, unit of the parameter, bound on |parameter|)
TERMS = [
    (
        'f_res_b_x_N',
        'motor_1_radps',
        'f_x__motor_1_radps__kg_m_per_s_rad',
        'kg m/(s rad)',
        5.5994473614809026e-05,
    ),
    (
        'f_res_b_z_N',
        'omega_b_z_radps*T_N',
        'f_z__omega_b_z_radps_times_T_N__s_per_rad',
        's/rad',
        1.3434741059891138,
    ),
    (
        'f_res_b_z_N',
        'Omega_net_radps',
        'f_z__Omega_net_radps__kg_m_per_s_rad',
        'kg m/(s rad)',
        0.0006974654023385582,
    ),
    (
        'tau_res_b_x_Nm',
        'motor_3_radps',
        'tau_x__motor_3_radps__kg_m2_per_s_rad',
        'kg m^2/(s rad)',
        8.590578366959015e-06,
    ),
    (
        'tau_res_b_x_Nm',
        'v_b_y_mps',
        'tau_x__v_b_y_mps__kg_m_per_s',
        'kg m/s',
        0.03850736784246346,
    ),
    (
        'tau_res_b_y_Nm',
        'v_b_x_mps',
        'tau_y__v_b_x_mps__kg_m_per_s',
        'kg m/s',
        0.047780238978474054,
    ),
    (
        'tau_res_b_z_Nm',
        'T_N*T_N',
        'tau_z__T_N_times_T_N__s2_per_kg',
        's^2/kg',
        0.061343415170726646,
    ),
]

EFFECT = DiscoveredEffect('discovered_terms', TERMS, __doc__)
