"""Rotor timing (a lag, a delay) fitted and compared at the angular-rate level, where the closed
loop biases it less than at the torque level (not nothing: docs/timing.md, "Calibration").

**Why not at the torque level.** The torque residual is ``J D[ω + ε] − M[A f]`` (docs/timing.md):
the gyro's noise ``ε`` enters through the derivative filter ``D``, which spans the samples on
both sides of ``t_k``. The commands ``f`` come from a controller that reads the same noisy gyro,
so ``f_j`` reacts to ``ε_i`` for every ``i <= j``. A timing effect's regressor is built from the
commands (``A (f(t - t_d) - f(t))``, through ``M``), and ``D[ε]_k`` holds ``ε_(k-15)``, which
every command in the window reacts to: regressor and noise are correlated (errors in variables
in closed loop) and the fit absorbs a few milliseconds of it. Measured on this project's
simulator (three 8 s hover flights, 10 ms delay true, seeds 0-2): ``t_d`` = 14.8-15.1 ± 0.2 ms
on the torque channels; the same flights with the gyro noise added to the log only (the
controller flying on the true rates) give 10.2-11.6 ± 0.5 ms.

**The rate level** (:mod:`.increments`): summing the torque equation over the sample intervals
undoes the derivative, and the running sum of the increments ``R_k`` holds the gyro noise as
``J (ε_k − ε_0)``: white, plus a constant, while a candidate's running sum ``C_k(θ)`` depends on
the commands before ``t_k`` only. Its parameter minimises

    J_rate(θ) = Σ_b Σ_(k∈b) Σ_axis w_a (R_ka − C_ka(θ) − c_ba)²      (N m s, body frame)

over blocks ``b`` with a free offset each. Same flights: ``t_d`` = 9.97-10.18 ± 0.11 ms.

The package, importing only downward:

* :mod:`.increments`: a flight's increments ``d_k`` (:class:`RateFlight`) and a candidate's;
* :mod:`.noise`: the gyro noise model, each flight's whitening filter (the real gyro's noise is
  coloured by the firmware's low-pass);
* :mod:`.sums`: a flight's sufficient sums (:class:`RateSums`), what the rate level keeps of a
  flight, and a timing parameter's fit from the sums (:func:`fit`);
* :mod:`.compare`: the held-out comparison of two candidates (:func:`difference_test`), of one
  against no timing effect (:func:`effect_comparison`), and when
  the noise model (:func:`noise_model_decides`) or the closed loop (:func:`closed_loop_decides`)
  decides it;
* :mod:`.judgement`: the diagnosis's use of all of it (:func:`judge`).

Used by :func:`quadcore.identify.diagnosis.diagnose` for the candidates that re-time the rotors'
commanded thrust (:attr:`quadcore.effects.Effect.retimes_thrust`), and by the planner
(:mod:`quadcore.plan.ratelevel`, :mod:`quadcore.plan.separation`); docs/timing.md has the
derivation and the measurements.
"""

from quadcore.identify.rates.compare import (
    NO_TIMING,
    PairComparison,
    block_differences,
    closed_loop_decides,
    compare_pair,
    difference_test,
    effect_comparison,
    held_out_cost,
    instrument_test,
    instrumented_differences,
    noise_model_decides,
    pair_comparison,
    pair_splits,
    timing_comparison,
    unwhitened_comparison,
)
from quadcore.identify.rates.increments import RateFlight, effect_increments, rate_flight
from quadcore.identify.rates.judgement import (
    NOT_SIGNIFICANT,
    RATE_LEVEL,
    TIE,
    Judged,
    RateEvidence,
    fold_fits,
    judge,
    timing_fit,
)
from quadcore.identify.rates.noise import (
    MAX_AR_ORDER,
    NOISE_BAND_HZ,
    NOISE_FLAT_HZ,
    NOISE_LAGS,
    NOISE_MODEL_PASSES,
    WHITE_FLOOR,
    Filter,
    NoiseModel,
    gyro_noise_model,
    noise_model,
    whitened,
)
from quadcore.identify.rates.sums import (
    BelowCommandRate,
    FlightRates,
    RateFit,
    RatesCache,
    RateSums,
    below_command_rate,
    fit,
    fit_cost,
    flight_inputs,
    flight_rates,
    flight_sums,
    grid_weights,
    piecewise_quadratic_minimum,
    rate_grid,
    rate_sums,
    split_weights,
    weights,
)

__all__ = ["MAX_AR_ORDER", "NOISE_BAND_HZ", "NOISE_FLAT_HZ", "NOISE_LAGS", "NOISE_MODEL_PASSES", "NOT_SIGNIFICANT",
           "NO_TIMING", "RATE_LEVEL", "TIE", "WHITE_FLOOR", "BelowCommandRate", "Filter", "FlightRates", "Judged",
           "NoiseModel", "PairComparison", "RateEvidence", "RateFit", "RateFlight", "RateSums", "RatesCache",
           "below_command_rate", "block_differences", "closed_loop_decides", "compare_pair", "difference_test",
           "effect_comparison", "effect_increments", "fit", "fit_cost", "flight_inputs", "flight_rates", "flight_sums",
           "fold_fits", "grid_weights", "gyro_noise_model", "held_out_cost", "instrument_test",
           "instrumented_differences", "judge", "noise_model", "noise_model_decides", "pair_comparison", "pair_splits",
           "piecewise_quadratic_minimum", "rate_flight", "rate_grid", "rate_sums", "split_weights",
           "timing_comparison", "timing_fit", "unwhitened_comparison", "weights", "whitened"]
