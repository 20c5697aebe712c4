"""What a log must hold for the physics: the uSD deck's ``fixedFrequency`` event and its variables.

The deck writes what its configuration file (``config.txt`` on the card) lists; the lines that
produce what this project needs are :data:`DECK_CONFIG` (the configuration of the shared logs,
``/work/shared/crazyflie/usd-config.txt``). The state estimate, gyro and accelerometer are always
needed; the rotor thrusts come from one of two thrust maps, each with its own inputs (the PWM and
battery voltage, or the RPM deck's motor speeds): a log must carry at least one of them
complete. ``estPose`` (motion capture) is optional. The reference page is
``docs/reference/log-variables.md``.

:func:`check` runs once per log where the pipeline meets it: on the header alone by the raw-folder
sensor (before any record is read), and on the decoded log by ``decoded_flight``; a log that fails
it is quarantined with one message naming everything missing. Decoding itself stays generic
(``quadcore decode`` decodes any uSD log); the fleet stages name the log variables behind the
columns they miss (:func:`logged_as`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from quadcore.logs.logformat import LogFormatError
from quadcore.logs.units import SI_COLUMNS

MAIN_EVENT = "fixedFrequency"

STATE = ("stateEstimate.x", "stateEstimate.y", "stateEstimate.z",
         "stateEstimate.qx", "stateEstimate.qy", "stateEstimate.qz", "stateEstimate.qw",
         "stateEstimate.vx", "stateEstimate.vy", "stateEstimate.vz")
IMU = ("gyro.x", "gyro.y", "gyro.z", "acc.x", "acc.y", "acc.z")
ALWAYS = STATE + IMU
# The inputs of each thrust map (four rotors; a vehicle file with more rotors needs more motors).
PWM_VBAT = ("pwm.m1_pwm", "pwm.m2_pwm", "pwm.m3_pwm", "pwm.m4_pwm", "pm.vbatMV")
MOTOR_SPEED = ("rpm.m1", "rpm.m2", "rpm.m3", "rpm.m4")

# The uSD deck configuration lines that log all of it at 500 Hz (see the module docstring).
DECK_CONFIG = "\n".join([
    "on:fixedFrequency",
    "500     # frequency",
    "1       # mode (0: disabled, 1: synchronous stabilizer, 2: asynchronous)",
    *ALWAYS, *MOTOR_SPEED, *PWM_VBAT,
])


class MissingVariablesError(LogFormatError):
    """A log whose header lacks what the physics needs: every missing variable in one message."""

    def __init__(self, missing: Sequence[str], detail: str):
        super().__init__(detail)
        self.missing = tuple(missing)


def missing(events: Mapping[str, Sequence[str]]) -> list[str]:
    """The variables (``event.variable`` names as the deck logs them) this log lacks, given its
    event types (name -> variables); [] when it has all. Without the event, all of them."""
    have = set(events.get(MAIN_EVENT, ()))
    out = [v for v in ALWAYS if v not in have]
    maps = [m for m in (PWM_VBAT, MOTOR_SPEED) if all(v in have for v in m)]
    if not maps:  # neither thrust map can run: name the default map's inputs
        out += [v for v in PWM_VBAT if v not in have]
    return out


def check(events: Mapping[str, Sequence[str]]) -> None:
    """:class:`MissingVariablesError` listing everything :func:`missing` finds, with the fix."""
    lacking = missing(events)
    if not lacking:
        return
    fix = "; log them with the uSD deck (the config.txt lines: docs/reference/log-variables.md)"
    if MAIN_EVENT not in events:
        has = ", ".join(sorted(events)) or "none"
        raise MissingVariablesError(lacking, (
            f"not usable for the physics: it has no {MAIN_EVENT!r} event (it has {has}), which must hold the "
            f"{len(lacking)} variables the physics needs{fix}"))
    thrust = "" if not any(v in lacking for v in PWM_VBAT) else (
        " (the thrust map needs pwm.m1_pwm..m4_pwm and pm.vbatMV, or rpm.m1..m4)")
    raise MissingVariablesError(lacking, (
        f"not usable for the physics: its {MAIN_EVENT!r} event lacks {len(lacking)} variable(s): "
        f"{', '.join(lacking)}{thrust}{fix}"))


def logged_as(columns: Sequence[str]) -> str:
    """SI columns with the log variable behind each: ``v_w_x_mps (log variable stateEstimate.vx)``."""
    source = {si: var for var, (si, *_rest) in SI_COLUMNS.items()}
    return ", ".join(f"{c} (log variable {source[c]})" if c in source else c for c in columns)
