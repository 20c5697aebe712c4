"""The diagnosis against an independent simulator: rotorpy's effects, its values, what
`quadcore diagnose` and `quadcore discover` make of them, at 500 Hz and 100 Hz logging.

    python benchmarks/bench_independent.py [--rates 500,100] [--markdown] [--sections rotor_drag,parasitic]

The flights are the independent-physics suite's (tests/independent/rotorpy_flights.py: six
flights per fleet, simulated with rotorpy once and cached under tests/.cache); the diagnosis
runs as the CLI runs it (cross-validation over the flights) with the vehicle file
quadcore/vehicles/rotorpy_crazyflie.toml. Prints one table: the effect rotorpy flew with,
rotorpy's value in this project's terms (for rotor drag and the discovered terms the value a fit
of this project's form converges to on these flights, see rf.projected_truth), the fitted value
± its reported standard deviation, and the verdict in words. docs/validation.md holds a run.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from independent import rotorpy_flights as rf  # noqa: E402

SPEED, PWM = "motor_speed", "pwm_vbat"


def _verdict(d) -> str:
    """The diagnosis's answer in a few words: the top candidate found, or nothing."""
    found = [c for c in d.candidates if c.found]
    if not found:
        return "nothing found" + (" (outside the library)" if "outside the library" in d.verdict else "")
    top = found[0]
    text = f"{top.effect} first, {top.grade}"
    if top.tied_with:
        text += f" (tied with {', '.join(top.tied_with)})"
    if len(found) > 1:
        text += f"; also found: {', '.join(c.effect for c in found[1:3])}"
    return text


def _fitted(d, effect: str, name: str) -> str:
    row = next((c for c in d.candidates if c.effect == effect), None)
    if row is None:
        return "not a candidate"
    return f"{row.parameters[name]:.4g} ± {row.parameter_std[name]:.2g}"


def _term(disc, target: str, base: str):
    """The kept term of ``target`` linear in ``base`` (``base`` or ``base`` times the thrust)."""
    return next((t for t in disc.terms if t.target == target and t.expression in (base, f"{base}*T_N", f"T_N*{base}")),
                None)


def _kept(disc) -> str:
    return "; ".join(f"{t.target} ~ {t.expression}" for t in disc.terms) or "nothing kept"


def rows_at(rate: int, fleets: dict[str, rf.Fleet], sections: tuple[str, ...] = ()) -> list[list[str]]:
    """The rows of ``sections`` (all of :data:`SECTIONS` when empty) at ``rate``."""
    return [r for name, section in SECTIONS.items() if not sections or name in sections
            for r in section(rate, fleets, lambda fleet, tmap: rf.decoded(fleets[fleet], rate, tmap))]


def _nothing_rows(rate: int, fleets: dict[str, rf.Fleet], flights) -> list[list[str]]:
    out = []
    for name, tmap in (("clean", SPEED), ("clean", PWM), ("lag", SPEED)):
        what = "nothing" if name == "clean" else "motor lag only, seen through the measured motor speeds"
        d = rf.diagnose(flights(name, tmap), tmap)
        out.append([f"{what} ({tmap})", "diagnose", "-", "-", _verdict(d)])
        disc = rf.discover(flights(name, tmap), tmap)
        out.append([f"{what} ({tmap})", "discover", "-", "-", _kept(disc)])
    return out


def _rotor_drag_rows(rate: int, fleets: dict[str, rf.Fleet], flights) -> list[list[str]]:
    out = []
    for name in ("rotor_drag", "rotor_drag_xy"):
        fleet = fleets[name]
        truth, hover = rf.projected_truth(fleet, rate), rf.truth(fleet.physics)  # k: projected on T v
        what = "rotor drag k_d, k_z (rotorpy's default)" if name == "rotor_drag" else "rotor drag k_d alone (k_z = 0)"
        d = rf.diagnose(flights(name, SPEED), SPEED)
        for axis in "xyz":
            key = f"k_{axis}_s_per_m"
            out.append([what, f"rotor_drag.{key}", f"{truth['rotor_drag.' + key]:.4g} "
                        f"(hover {hover['rotor_drag.' + key]:.4g})", _fitted(d, "rotor_drag", key), _verdict(d)])
        d2 = rf.diagnose(flights(name, SPEED), SPEED, ("rotor_drag",))
        out.append([what, "with rotor_drag in the model", "-", "-", _verdict(d2)])
        disc = rf.discover(flights(name, SPEED), SPEED)
        for label, target, base in (("vertical drag", "f_res_b_z_N", "v_b_z_mps"),
                                    ("roll damping", "tau_res_b_x_Nm", "omega_b_x_radps"),
                                    ("yaw damping", "tau_res_b_z_Nm", "omega_b_z_radps")):
            t = _term(disc, target, base)
            if t is None:
                out.append([what, f"discover: {label}", "-", "-", "not kept"])
                continue
            value = rf.projection(fleet, rate, target, t.expression, rotor_drag_only=True)
            out.append([what, f"discover: {label}, {target} ~ c {t.expression}", f"{value:.4g}",
                        f"{t.coefficient:.4g} ± {t.std:.2g}", "kept"])
        out.append([what, "discover: every term", "-", "-", _kept(disc)])
    return out


def _parasitic_rows(rate: int, fleets: dict[str, rf.Fleet], flights) -> list[list[str]]:
    out = []
    fleet = fleets["parasitic"]
    hover = rf.truth(fleet.physics)
    d = rf.diagnose(flights("parasitic", SPEED), SPEED)
    for key in ("c_xy_kg_per_m", "c_z_kg_per_m"):
        out.append(["parasitic drag c_D", f"parasitic_drag.{key}", f"{hover['parasitic_drag.' + key]:.4g}",
                    _fitted(d, "parasitic_drag", key), _verdict(d)])
    d2 = rf.diagnose(flights("parasitic", SPEED), SPEED, ("parasitic_drag",))
    out.append(["parasitic drag c_D", "with parasitic_drag in the model", "-", "-", _verdict(d2)])
    out.append(["parasitic drag c_D", "discover", "-", "-", _kept(rf.discover(flights("parasitic", SPEED), SPEED))])
    return out


def _lag_rows(rate: int, fleets: dict[str, rf.Fleet], flights) -> list[list[str]]:
    out = []
    tau = rf.truth(fleets["lag"].physics)["motor_lag.tau_s"]
    lag = flights("lag", PWM)
    for label, subset in (("all six flights", lag), ("the three that start in hover", lag.only(("f2", "f4", "f5")))):
        d = rf.diagnose(subset, PWM)
        out.append([f"motor lag tau_m ({PWM})", f"motor_lag.tau_s, {label}", f"{tau:.4g}",
                    _fitted(d, "motor_lag", "tau_s"), _verdict(d)])
    d2 = rf.diagnose(lag, PWM, ("motor_lag",))
    out.append([f"motor lag tau_m ({PWM})", "with motor_lag in the model", "-", "-", _verdict(d2)])
    return out


# the table's sections, in its order: the fleets each simulates and its rows
SECTIONS = {"nothing": _nothing_rows, "rotor_drag": _rotor_drag_rows, "parasitic": _parasitic_rows, "lag": _lag_rows}
FLEETS_OF = {"nothing": ("clean", "lag"), "rotor_drag": ("rotor_drag", "rotor_drag_xy"), "parasitic": ("parasitic",),
             "lag": ("lag",)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rates", default="500,100", help="log rates in Hz (default 500,100)")
    parser.add_argument("--markdown", action="store_true", help="a Markdown table (as docs/validation.md holds)")
    parser.add_argument("--sections", default="", help=f"only these rows (comma-separated: {', '.join(SECTIONS)})")
    args = parser.parse_args()
    sections = tuple(s for s in args.sections.split(",") if s)
    unknown = sorted(set(sections) - set(SECTIONS))
    if unknown:
        parser.error(f"unknown section {unknown[0]!r}; one of {', '.join(SECTIONS)}")
    fleets = rf.fleets()
    t0 = time.perf_counter()
    rf.prepare([fleets[f] for f in dict.fromkeys(f for s in sections or SECTIONS for f in FLEETS_OF[s])])
    print(f"flights ready in {time.perf_counter() - t0:.1f} s (cache: {rf.cache_root()})", file=sys.stderr)
    header = ["rate", "rotorpy's effect", "what is checked", "rotorpy's value", "fitted ± σ", "verdict"]
    rows = [[f"{rate} Hz", *r] for rate in map(int, args.rates.split(",")) for r in rows_at(rate, fleets, sections)]
    if args.markdown:
        print("| " + " | ".join(header) + " |\n|" + "---|" * len(header))
        for r in rows:
            print("| " + " | ".join(c.replace("|", "\\|") for c in r) + " |")
    else:
        widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(len(header))]
        for r in [header, *rows]:
            print("  ".join(str(c).ljust(w) for c, w in zip(r, widths)))
    print(f"total {time.perf_counter() - t0:.1f} s", file=sys.stderr)


if __name__ == "__main__":
    main()
