"""The parser of every verb, built without importing the command groups (``quadcore --help`` and
``quadcore VERB --help`` load the standard library and :mod:`quadcore.learn.learners` only). Each verb's
parser names its command: ``group``, the module of :mod:`quadcore.cli` that runs it, and ``command``, the
function there (:func:`quadcore.cli.main` loads the module when the command runs)."""

from __future__ import annotations

import argparse

from quadcore.learn import learners


def build_parser() -> argparse.ArgumentParser:
    # one flat table of the verbs and their options, read top to bottom: long, not deep (issue #15)
    parser = argparse.ArgumentParser(prog="quadcore",
                                     description="Quadrotor flight logs -> SI Parquet -> dynamics models.")
    sub = parser.add_subparsers(dest="verb", required=True)
    p = sub.add_parser("decode", help="decode uSD logs into SI Parquet")
    p.add_argument("paths", nargs="+", metavar="LOG_OR_FOLDER")
    p.add_argument("--out", required=True, metavar="DIR", help="output data root")
    p.set_defaults(group="decode", command="cmd_decode")

    def vehicle_args(p):
        p.add_argument("--vehicle", default=None, metavar="FILE", help="vehicle TOML (default: built-in Crazyflie 2.1)")
        p.add_argument("--thrust-map", default=None, metavar="KIND",
                       help="override the vehicle file's thrust map (pwm_vbat or motor_speed)")

    def model_and_flights_args(p, json_help: str):
        # what diagnose, discover and plan start from (quadcore.cli.common.model_and_flights), one definition each
        p.add_argument("data", metavar="DATA", help="a folder of raw uSD logs")
        p.add_argument("--json", required=True, metavar="OUT.json", help=json_help)
        p.add_argument("--model", default=None, metavar="MODEL.toml",
                       help="a model file (vehicle, effects, plugins) to start from")
        p.add_argument("--effects", default="", metavar="e1,e2,...",
                       help="effects in the model, instead of the model file's (default: the file's, else none)")
        p.add_argument("--holdout", default="", metavar="FLIGHT,...", help="score on these flights (default: "
                       "cross-validation over flights)")
        p.add_argument("--sessions", default=None, metavar="SESSIONS.toml", help="groups of flights ([sessions] "
                       "NAME = [\"flight\", \"pattern*\"]) whose parameters may differ (default: the model file's, "
                       "else groups found from the data)")
        p.add_argument("--quiet", action="store_true", help="no progress on stderr")
        vehicle_args(p)

    p = sub.add_parser("vehicle", help="a vehicle file of your own: write one from the commented template, or "
                       "check one")
    p.add_argument("action", choices=["new", "check"], help="new: write a template; check: load and summarise FILE")
    p.add_argument("name", metavar="NAME_OR_FILE", help="new: the vehicle's name; check: the vehicle file")
    p.add_argument("--out", default=None, metavar="FILE", help="new: where to write it (default NAME.toml)")
    p.set_defaults(group="physics", command="cmd_vehicle")

    p = sub.add_parser("residuals", help="residual force and torque statistics per flight")
    p.add_argument("paths", nargs="+", metavar="LOG_OR_FOLDER")
    p.add_argument("--out", default=None, metavar="DIR", help="also write residual Parquet under DIR/residuals")
    vehicle_args(p)
    p.set_defaults(group="physics", command="cmd_residuals")

    p = sub.add_parser("fit-thrust", help="fit k_F of the motor-speed thrust map f = k_F omega^2")
    p.add_argument("paths", nargs="+", metavar="LOG_OR_FOLDER")
    p.add_argument("--write", default=None, metavar="OUT.toml", help="write a vehicle file with the fitted k_F")
    vehicle_args(p)
    p.set_defaults(group="physics", command="cmd_fit_thrust")

    p = sub.add_parser("simulate", help="simulate flights with known effects as uSD logs + ground truth JSON")
    p.add_argument("--out", required=True, metavar="DIR", help="folder for the logs (sim000, ...) and <log>.truth.json")
    p.add_argument("--kind", default="default-set",
                   choices=["figure8", "circle0", "yaw0", "random", "hover", "low_pass", "default-set"],
                   help="what to fly (default: the default set of 6 varied flights)")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="flight length in seconds")
    p.add_argument("--flights", type=int, default=None, metavar="N", help="number of flights (seeds SEED, SEED+1, ...)")
    p.add_argument("--effect", action="extend", nargs="+", default=None, metavar="NAME:param=value,...",
                   help="an effect to switch on, e.g. rotor_drag:k_x_s_per_m=0.4,k_y_s_per_m=0.4 (repeatable)")
    p.add_argument("--seed", type=int, default=0, metavar="N", help="random seed (default 0)")
    p.add_argument("--vehicle", default=None, metavar="FILE", help="vehicle TOML (default: built-in Crazyflie 2.1)")
    p.set_defaults(group="sim", command="cmd_simulate", thrust_map=None)

    p = sub.add_parser("export", help="flights as MCAP for Foxglove (pose, IMU, motors, model vs measured)")
    p.add_argument("paths", nargs="+", metavar="LOG_OR_FOLDER")
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--start", metavar="ISO_TIME", help="the flight's start (UTC, e.g. 2024-05-01T12:00:00Z); default: "
                   "the flights file's start_utc, else the log file's modification time taken as the end of the flight")
    p.add_argument("--flights", metavar="FLIGHTS.csv", help="flights file with a start_utc column "
                   "(default: flights.csv beside or above the logs)")
    vehicle_args(p)
    p.set_defaults(group="export", command="cmd_export")

    p = sub.add_parser("export-c", help="the model as C99 for a flight controller (header + source), checked")
    p.add_argument("model", metavar="MODEL_DIR_OR_FILE",
                   help="a learned model folder, a physics_model.json, or a data root (its best learned model)")
    p.add_argument("--out", required=True, metavar="DIR", help="folder for quadcore_model.h and quadcore_model.c")
    p.add_argument("--learned", default="xgboost", choices=["xgboost", "mlp", "none"],
                   help="from a data root: the best model of this kind (default xgboost), or none (physics only)")
    p.add_argument("--model-file", default=None, metavar="MODEL.toml",
                   help="the model file whose plugins the model's plugin effects come from (a saved model never "
                        "names code to run: its plugins are checked against these by name and SHA-256)")
    p.set_defaults(group="export", command="cmd_export_c")

    p = sub.add_parser("diagnose", help="where the model fails and which effect is missing (JSON report)")
    model_and_flights_args(p, "the diagnosis")
    p.add_argument("--report", default=None, metavar="DIR", help="also write diagnosis.md and diagnosis.html")
    p.set_defaults(group="diagnose", command="cmd_diagnose")

    p = sub.add_parser("discover", help="terms the effect library lacks: sparse regression on the residual (JSON)")
    model_and_flights_args(p, "the terms found, on top of the model's effects")
    p.add_argument("--write-effect", default=None, metavar="DIR/NAME.py",
                   help="write the kept terms as a linear effect plugin module NAME")
    p.set_defaults(group="discover", command="cmd_discover")

    p = sub.add_parser("plan", help="the next flight: a trajectory that separates what the data cannot tell apart")
    model_and_flights_args(p, "the plan (and OUT.png, its picture)")
    p.add_argument("--trajectory", required=True, metavar="OUT.csv", help="the trajectory in the lab's format")
    p.add_argument("--between", default="", metavar="A,B", help="separate these two candidates")
    p.add_argument("--parameter", default="", metavar="EFFECT.NAME", help="pin down this parameter")
    p.add_argument("--arena", default="", metavar="XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX",
                   help="the room the flight must stay in, m (default -1,-1,0.2,1,1,1.5)")
    p.add_argument("--duration", type=float, default=20.0, metavar="S", help="manoeuvre time, s (default 20)")
    p.add_argument("--max-speed", type=float, default=1.5, metavar="MPS", help="default 1.5 m/s")
    p.add_argument("--max-tilt", type=float, default=25.0, metavar="DEG", help="default 25 degrees")
    p.add_argument("--no-proof", action="store_true", help="skip flying the plan in the simulator")
    p.add_argument("--seed", type=int, default=0, metavar="N", help="the proof's simulator seed")
    p.set_defaults(group="plan", command="cmd_plan")

    p = sub.add_parser("train", help="learn the residual the physics model leaves (XGBoost, MLP) and report")
    p.add_argument("data", metavar="DATA", help="a folder of raw uSD logs")
    p.add_argument("--holdout", default=None, metavar="FLIGHT",
                   help="the held-out flight (default jana02, or the last flight when there is no jana02)")
    p.add_argument("--loo", action="store_true", help="also leave-one-flight-out cross-validation over all flights")
    p.add_argument("--models", default="xgboost,mlp", metavar="KIND,...", help="model kinds (default xgboost,mlp)")
    p.add_argument("--xgboost", default="", metavar="OPTS", help="XGBoost options, e.g. depth=4,trees=300,eta=0.1")
    p.add_argument("--mlp", default="", metavar="OPTS", help="MLP options, e.g. hidden=64x64,epochs=100,lr=0.001")
    p.add_argument("--feature-sets", default="", metavar="SET,...",
                   help="feature sets (default: all built-in; define one as name=col1+col2+...)")
    p.add_argument("--effects", default="", metavar="e1,e2,...",
                   help="effects in the physics model, fitted on the training flights (default: none)")
    p.add_argument("--model", default=None, metavar="MODEL.toml",
                   help="a model file (vehicle, effects, plugins) for the physics model under the learned ones")
    p.add_argument("--out", default="data", metavar="DIR",
                   help="data root for learned/, reports/, history/ (default: data)")
    p.add_argument("--flights-csv", default=None, metavar="FILE",
                   help="flight kinds (flight,kind; default: flights.csv beside or above DATA)")
    p.add_argument("--no-compare", action="store_true", help="skip the training-size and complexity comparisons")
    p.add_argument("--stride", type=int, default=5, metavar="N", help="fit on every N-th sample (default 5)")
    p.add_argument("--max-rows", type=int, default=learners.DEFAULT_ROW_BUDGET, metavar="N",
                   help=f"the row budget: the most usable training rows one model holds; above it they are drawn "
                        f"evenly per flight (default {learners.DEFAULT_ROW_BUDGET})")
    p.add_argument("--seed", type=int, default=0, metavar="N")
    p.add_argument("--threads", type=int, default=1, metavar="N",
                   help="XGBoost threads (default 1, measured faster here)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    vehicle_args(p)
    p.set_defaults(group="learn", command="cmd_train")
    return parser
