"""The config harness: hostile and careless vehicle files, model files and edited outputs, each
through the code a user's command runs, around a decoy tree of user files.

    python -m tests.fuzz.configs            (part of make fuzz)

Counts what issue 22's bar asks for:

- **tracebacks**: a file that ends in anything but the command's one-line user error naming
  the file (an exception the CLI does not report as a user error, a message over several lines
  or not naming the file);
- **implausible configurations accepted silently**: a case built to be refused (a mass of
  1e300 kg, 1,000 rotors, a plugin listed twice, ...) that loads;
- **valid configurations refused**: the other way round (the built-in vehicle, an octocopter,
  a 300 kg vehicle with its ``allow_unusual`` override, ...);
- **code run from a path an output names**: a fitted model's JSON or a learned model's manifest
  edited to name a module that would write a sentinel file, read by ``quadcore export-c``, the
  pipeline's current model and ``LearnedModel.physics_model()``;
- **files touched outside the project's own folders**: ``quadcore decode --out`` into a new
  folder, into an old-layout data root, into the decoy tree itself and into a foreign folder
  within it, and a sweep of each, with every decoy file's content hash compared before and after.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import hashlib
import io
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

from quadcore import cli, effects
from quadcore.identify import model
from quadcore.spec.model import ModelFileError, ModelSpec
from quadcore.store import ownership, safewrite, store

VEHICLE = (resources.files("quadcore") / "vehicles" / "crazyflie21.toml").read_text()
ROTOR = "[[rotors]]\narm_m = {arm}\nangle_deg = {angle}\nyaw_sign = {yaw}\n"
EXAMPLE_PLUGIN = Path(__file__).resolve().parents[2] / "examples" / "effects" / "linear_drag.py"


@dataclass(frozen=True)
class Case:
    name: str
    kind: str  # "vehicle" or "model"
    data: bytes
    valid: bool  # True: must load; False: must be refused with one line naming the file
    extra: tuple[tuple[str, bytes], ...] = ()  # other files beside it (plugins, vehicles)


def _replace(old: str, new: str, text: str = VEHICLE) -> bytes:
    assert old in text, old
    return text.replace(old, new, 1).encode()


def _rotors(n: int, arm: float = 0.046) -> str:
    body = VEHICLE.split("[[rotors]]")[0]
    tail = VEHICLE[VEHICLE.index("[thrust_map]"):]
    rotors = "".join(ROTOR.format(arm=arm, angle=360.0 * i / n + 45.0, yaw=1 if i % 2 else -1) for i in range(n))
    return body + rotors + tail


def _nested(depth: int, key: str = "mass_kg") -> bytes:
    return (VEHICLE.replace("mass_kg = 0.0347", f"{key} = " + "[" * depth + "]" * depth)).encode()


def _thrust_map(change: Callable[[float], float]) -> str:
    """The built-in vehicle with ``change`` applied to each coefficient of its PWM thrust map."""
    text = VEHICLE
    for line in ("c0 = 11.09", "cp = -39.08", "cb = -9.53", "cpp = 20.57", "cpb = 38.43"):
        name, value = line.split(" = ")
        text = text.replace(line, f"{name} = {change(float(value))}")
    return text


def vehicle_cases() -> list[Case]:
    v = []

    def add(name, data, valid=False):
        v.append(Case(name, "vehicle", data if isinstance(data, bytes) else data.encode(), valid))

    add("built-in", VEHICLE, True)
    add("octocopter", _rotors(8), True)
    add("hexacopter", _rotors(6), True)
    add("300 kg with override", _replace("mass_kg = 0.0347", 'allow_unusual = ["mass_kg", "thrust_map"]\n'
                                         "mass_kg = 300.0").decode(), True)
    # encodings and non-text
    add("utf-16 with BOM", VEHICLE.encode("utf-16"))
    add("utf-16-le without BOM", VEHICLE.encode("utf-16-le"))
    add("utf-16-be with BOM", b"\xfe\xff" + VEHICLE.encode("utf-16-be"))
    add("latin-1 comment", VEHICLE.replace("# Crazyflie", "# Crazyflie caf\xe9").encode("latin-1"))
    add("binary", bytes(range(256)) * 8)
    add("png header", b"\x89PNG\r\n\x1a\n" + bytes(64))
    add("nul bytes in text", VEHICLE.encode().replace(b"name =", b"na\x00me ="))
    add("empty", b"")
    add("only a comment", b"# nothing\n")
    add("2 MB of comments", VEHICLE.encode() + b"#" * (2 << 20))
    add("5000-deep array", _nested(5000))
    add("5000-deep inline table", VEHICLE.replace("mass_kg = 0.0347", "mass_kg = " + "{a = " * 5000 + "1"
                                                  + "}" * 5000).encode())
    add("300-deep array", _nested(300))
    add("not TOML", "mass_kg = = 1\n")
    # numbers
    for label, value in [("1e300", "1e300"), ("1e-300", "1e-300"), ("0", "0"), ("-1", "-1.0"), ("nan", "nan"),
                         ("inf", "inf"), ("string", '"heavy"'), ("true", "true"), ("int 10**400", str(10**400)),
                         ("int 10**30", str(10**30)), ("a list", "[1, 2]"), ("1 g", "0.001"), ("1 tonne", "1000.0")]:
        add(f"mass {label}", _replace("mass_kg = 0.0347", f"mass_kg = {value}"))
    big = "[[1e300, 0, 0], [0, 1e300, 0], [0, 0, 1e300]]"
    cond = "[[1e-6, 0, 0], [0, 1e-6, 0], [0, 0, 1e9]]"
    for label, value in [("1e300", big), ("condition 1e15", cond), ("zeros", "[[0,0,0],[0,0,0],[0,0,0]]"),
                         ("negative", "[[-1e-5,0,0],[0,-1e-5,0],[0,0,-1e-5]]"), ("2x2", "[[1e-5,0],[0,1e-5]]"),
                         ("strings", '[["a","b","c"],["a","b","c"],["a","b","c"]]'),
                         ("int 10**400", f"[[{10**400},0,0],[0,{10**400},0],[0,0,{10**400}]]"),
                         ("1e-300", "[[1e-300,0,0],[0,1e-300,0],[0,0,1e-300]]"), ("a number", "1e-5"),
                         ("not symmetric", "[[1e-5,1e-6,0],[0,1e-5,0],[0,0,2e-5]]")]:
        text = VEHICLE[:VEHICLE.index("inertia_kgm2 = [")] + f"inertia_kgm2 = {value}\n" + \
            VEHICLE[VEHICLE.index("torque_to_thrust_m"):]
        add(f"inertia {label}", text)
    add("1,000 rotors", _rotors(1000))
    add("20 rotors", _rotors(20))
    add("3 rotors", _rotors(3))
    add("no rotors", _rotors(0))
    add("arm 1e300", _rotors(4, 1e300))
    add("arm 1e-300", _rotors(4, 1e-300))
    add("arm 0", _rotors(4, 0.0))
    add("yaw_sign 5", _replace("angle_deg = 45.0\nyaw_sign = 1", "angle_deg = 45.0\nyaw_sign = 5"))
    add("rotors a string", _rotors(0) + 'rotors = "four"\n')
    add("all thrust coefficients zero", _thrust_map(lambda c: 0.0))
    add("negative thrust map", _thrust_map(lambda c: -c))
    add("thrust map 1e300", _replace("c0 = 11.09", "c0 = 1e300"))
    add("thrust map too weak to hover", _replace("cpb = 38.43", "cpb = 0.0"))
    add("falling thrust map", _replace("cpp = 20.57", "cpp = -40.0"))
    add("vbat_ref 0", _replace("vbat_ref_V = 4.2", "vbat_ref_V = 0"))
    add("vbat_ref 1e6", _replace("vbat_ref_V = 4.2", "vbat_ref_V = 1e6"))
    add("k_F 1e300", _replace("k_F_N_per_radps2 = 2.138e-08", "k_F_N_per_radps2 = 1e300"))
    add("k_F -1", _replace("k_F_N_per_radps2 = 2.138e-08", "k_F_N_per_radps2 = -1.0"))
    add("k_F 0 (not fitted yet)", _replace("k_F_N_per_radps2 = 2.138e-08", "k_F_N_per_radps2 = 0.0"), True)
    add("kind magic", _replace('kind = "pwm_vbat"', 'kind = "magic"'))
    add("missing c0", _replace("c0 = 11.09\n", ""))
    add("torque_to_thrust 1e300", _replace("torque_to_thrust_m = 0.006", "torque_to_thrust_m = 1e300"))
    add("rotor radius 1e300", _replace("rotor_radius_m = 0.0225", "rotor_radius_m = 1e300"))
    add("rotor radius 1e-300", _replace("rotor_radius_m = 0.0225", "rotor_radius_m = 1e-300"))
    add("typo key", _replace("mass_kg = 0.0347", "mas_kg = 0.0347"))
    add("name a number", _replace('name = "crazyflie21"', "name = 5"))
    add("allow_unusual unknown key", _replace("mass_kg = 0.0347", 'allow_unusual = ["everything"]\nmass_kg = 0.0347'))
    add("allow_unusual a string", _replace("mass_kg = 0.0347", 'allow_unusual = "mass_kg"\nmass_kg = 0.0347'))
    add("mass 1e300 without its override", _replace("mass_kg = 0.0347",
                                                    'allow_unusual = ["rotors"]\nmass_kg = 1e300'))
    return v


PLUGIN_EXIT = b"raise SystemExit(3)\n"
PLUGIN_RAISES = b"raise RuntimeError('boom')\n"
PLUGIN_BUILTIN = b"from quadcore.effects import rotor_drag\nEFFECT = rotor_drag.EFFECT\n"
PLUGIN_RECURSES = b"def f():\n    return f()\nf()\n"


def model_cases(bad_vehicle: bytes, deep: bytes) -> list[Case]:
    m = []

    def add(name, text, valid=False, extra=()):
        m.append(Case(name, "model", text if isinstance(text, bytes) else text.encode(), valid, tuple(extra)))

    plugin = (("linear_drag.py", EXAMPLE_PLUGIN.read_bytes()),)
    add("empty effects", "effects = []\n", True)
    add("rotor_drag", 'effects = ["rotor_drag"]\n', True)
    add("with plugin", 'effects = ["linear_drag"]\nplugins = ["linear_drag.py"]\n', True, plugin)
    add("fixed value within range", 'effects = ["rotor_drag"]\n[parameters.rotor_drag]\nk_x_s_per_m = 0.1\n', True)
    add("fixed value outside with override", 'effects = ["rotor_drag"]\nallow_unusual = ["rotor_drag.k_x_s_per_m"]\n'
        "[parameters.rotor_drag]\nk_x_s_per_m = 7.0\n", True)
    add("per-session scale", 'effects = ["thrust_scale"]\n[per_session]\nthrust_scale = ["scale"]\n', True)
    add("utf-16", 'effects = ["rotor_drag"]\n'.encode("utf-16"))
    add("utf-16-le", 'effects = ["rotor_drag"]\n'.encode("utf-16-le"))
    add("latin-1", '# mod\xe8le\neffects = []\n'.encode("latin-1"))
    add("binary", bytes(range(256)) * 4)
    add("nul bytes", b"effects = []\n\x00\x00")
    add("5000-deep", b"effects = " + b"[" * 5000 + b"]" * 5000 + b"\n")
    add("5000-deep table", b"x = " + b"{a = " * 5000 + b"1" + b"}" * 5000 + b"\n")
    add("not TOML", "effects = [\n")
    add("2 MB", b"effects = []\n" + b"#" * (2 << 20))
    add("unknown effect", 'effects = ["warp_drive"]\n')
    add("effect twice", 'effects = ["rotor_drag", "rotor_drag"]\n')
    add("effects a string", 'effects = "rotor_drag"\n')
    add("effects numbers", "effects = [1, 2]\n")
    add("unknown key", "effect = []\n")
    for label, value in [("1e300", "1e300"), ("-1e300", "-1e300"), ("int 10**400", str(10**400)), ("nan", "nan"),
                         ("string", '"fast"'), ("true", "true"), ("outside bounds", "7.0"), ("negative", "-0.5")]:
        add(f"fixed k_x {label}", f'effects = ["rotor_drag"]\n[parameters.rotor_drag]\nk_x_s_per_m = {value}\n')
    add("fixed parameter unknown", 'effects = ["rotor_drag"]\n[parameters.rotor_drag]\nk_q = 0.1\n')
    add("fixed effect not listed", 'effects = []\n[parameters.rotor_drag]\nk_x_s_per_m = 0.1\n')
    add("parameters = 5", "effects = []\nparameters = 5\n")
    add("fixed mass 1e300", 'effects = ["added_mass"]\n[parameters.added_mass]\nm_p_kg = 1e300\n')
    add("fixed scale 1e300", 'effects = ["thrust_scale"]\n[parameters.thrust_scale]\nscale = 1e300\n')
    add("per_session [1, scale]", 'effects = ["thrust_scale"]\n[per_session]\nthrust_scale = [1, "scale"]\n')
    add("per_session a string", 'effects = ["thrust_scale"]\n[per_session]\nthrust_scale = "scale"\n')
    add("per_session unknown effect", 'effects = []\n[per_session]\nthrust_scale = ["scale"]\n')
    add("per_session = 3", 'effects = []\nper_session = 3\n')
    add("sessions numbers", 'effects = []\n[sessions]\nearly = [1, 2]\n')
    add("session_thrust_map unknown session", 'effects = []\n[session_thrust_map]\nlate = "motor_speed"\n')
    add("session_thrust_map unknown kind", 'effects = []\n[sessions]\nlate = ["jana2*"]\n'
        '[session_thrust_map]\nlate = "magic"\n')
    add("thrust_map unknown", 'thrust_map = "x"\n')
    add("vehicle = 5", "vehicle = 5\n")
    add("vehicle missing file", 'vehicle = "nowhere.toml"\n')
    add("vehicle binary", 'vehicle = "v.bin"\n', extra=(("v.bin", bytes(range(256))),))
    add("vehicle 1e300 mass", 'vehicle = "v.toml"\n', extra=(("v.toml", bad_vehicle),))
    add("vehicle 5000-deep", 'vehicle = "v.toml"\n', extra=(("v.toml", deep),))
    add("vehicle a folder", 'vehicle = "sub"\n', extra=(("sub/x", b""),))
    add("the same plugin twice", 'effects = ["linear_drag"]\nplugins = ["linear_drag.py", "linear_drag.py"]\n',
        extra=plugin)
    add("the same plugin twice by two paths", 'effects = ["linear_drag"]\n'
        'plugins = ["linear_drag.py", "./linear_drag.py"]\n', extra=plugin)
    add("plugin missing", 'plugins = ["gone.py"]\n')
    add("plugin a folder", 'plugins = ["folder"]\n', extra=(("folder/x", b""),))
    add("plugin binary", 'plugins = ["p.py"]\n', extra=(("p.py", bytes(range(256))),))
    add("plugin utf-16", 'plugins = ["p.py"]\n', extra=(("p.py", "EFFECT = 1\n".encode("utf-16")),))
    add("plugin exits", 'plugins = ["p.py"]\n', extra=(("p.py", PLUGIN_EXIT),))
    add("plugin raises", 'plugins = ["p.py"]\n', extra=(("p.py", PLUGIN_RAISES),))
    add("plugin recurses", 'plugins = ["p.py"]\n', extra=(("p.py", PLUGIN_RECURSES),))
    add("plugin not an effect", 'plugins = ["p.py"]\n', extra=(("p.py", b"EFFECT = 42\n"),))
    add("plugin replaces a built-in", 'plugins = ["p.py"]\n', extra=(("p.py", PLUGIN_BUILTIN),))
    add("plugins a string", 'plugins = "p.py"\n')
    add("allow_unusual a number", "effects = []\nallow_unusual = 3\n")
    return m


# --- running one case as the CLI does ---------------------------------------------------------

@dataclass(frozen=True)
class Result:
    case: Case
    outcome: str  # "accepted", "refused", "traceback"
    message: str


def _load(case: Case, folder: Path) -> Path:
    """Write the case's files into a folder of its own; the path of its vehicle or model file."""
    folder.mkdir(parents=True, exist_ok=True)
    for name, data in case.extra:
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_bytes(data)
    path = folder / ("vehicle.toml" if case.kind == "vehicle" else "model.toml")
    path.write_bytes(case.data)
    return path


def run_case(case: Case, folder: Path, empty_logs: Path) -> Result:
    """``quadcore diagnose EMPTY --model F`` / ``--vehicle F``: the file is read before the logs,
    so a refused file is one line naming it, and an accepted one goes on to 'no logs'."""
    path = _load(case, folder)
    flag = "--vehicle" if case.kind == "vehicle" else "--model"
    err = io.StringIO()
    before = set(effects.registry())
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            code = cli.main(["diagnose", str(empty_logs), "--json", str(folder / "out.json"), flag, str(path)])
    except BaseException as exc:  # noqa: BLE001 (anything that escapes the CLI is a traceback for the user)
        return Result(case, "traceback", f"{type(exc).__name__}: {exc}"[:300])
    finally:
        for name in set(effects.registry()) - before:  # plugins of this case do not leak into the next
            effects.unregister(name)
    text = err.getvalue().strip()
    if code == 2 and str(path) in text:
        lines = text.splitlines()
        return Result(case, "refused" if len(lines) == 1 else "traceback", text[:300])
    # accepted: the command went on to the (empty) logs folder and stopped there
    return Result(case, "accepted" if code == 2 and str(empty_logs) in text else "traceback", text[:300])


# --- outputs that name code -------------------------------------------------------------------

SENTINEL = "from pathlib import Path\nPath({path!r}).write_text('ran')\n"


def output_cases(base: Path) -> tuple[int, int, int]:
    """(cases, code run, cases not refused): fitted-model JSON and learned-model manifests that name
    a module writing a sentinel file, through export-c, the current model and physics_model()."""
    from quadcore.workflows import identify

    sentinel = base / "sentinel"
    evil = base / "elsewhere" / "evil.py"
    evil.parent.mkdir(parents=True, exist_ok=True)
    evil.write_text(SENTINEL.format(path=str(sentinel)))
    spec = ModelSpec(__import__("quadcore.physics.vehicle", fromlist=["load"]).load(), [])
    root = base / "root"
    path = model.save(model.PhysicsModel(spec.vehicle, []), store.physics_model_path(root), ["a", "b"], spec)
    saved = store.read_json(path)
    digest = hashlib.sha256(evil.read_bytes()).hexdigest()
    variants = [[str(evil)], [str(evil.relative_to(base))], ["../elsewhere/evil.py"],
                [{"effect": "evil", "module": str(evil), "sha256": digest}],
                [{"effect": "evil", "module": "evil.py", "sha256": digest}],
                [{"effect": "rotor_drag", "module": str(evil), "sha256": digest}], [{"path": str(evil)}], str(evil)]
    n = not_refused = 0
    for plugins in variants:
        doc = {**saved, "plugins": plugins, "effects": [{"name": "evil", "params": {}}]}
        store.write_json(doc, path)
        calls: list[Callable[[], object]] = [
            lambda: cli.main(["export-c", str(path), "--out", str(base / "c"), "--learned", "none"]),
            lambda: identify.current_model(root, spec),
            lambda: model.load_fitted(path, spec.vehicle),
            functools.partial(_manifest_physics, doc),
        ]
        for call in calls:
            n += 1
            try:
                with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
                    got = call()
                not_refused += got != 2
            except (ModelFileError, cli.UserError):
                pass
            except BaseException:  # noqa: BLE001 (a traceback: counted as not refused)
                not_refused += 1
    return n, int(sentinel.exists()), not_refused


class _Manifest:
    def __init__(self, manifest: dict):
        self.manifest = manifest


def _manifest_physics(doc: dict):
    """``LearnedModel.physics_model()`` of a learned model whose manifest holds ``doc``."""
    from quadcore.learn import artefacts

    learned: Any = _Manifest({"physics_model": doc})
    return artefacts.LearnedModel.physics_model(learned)


# --- the decoy tree around the output folders ------------------------------------------------------

def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def decoy_tree(base: Path) -> Path:
    """A user's folder with what a sweep by pattern would take: old backups, temp files named as
    the project's writers name theirs (with a dead pid), a git index backup, a ``.features-``."""
    dead, old = _dead_pid(), time.time() - 3 * safewrite.STALE_AFTER_S
    files = {".bashrc": "a", ".bashrc.old": "b", ".config.old/app/settings": "c", "project/.git/.index.old": "d",
             "docs/.chapter3.tmp": "e", f".notes.{dead}.abc123.tmp": "f", f"docs/.draft.{dead}.x1.staging/a": "g",
             ".features-abc123/x": "h", f"decoded/.data.parquet.{dead}.abc.tmp": "i", "thesis.tex": "j",
             f"foreign/.cache.{dead}.zz.old/y": "k", "foreign/notes.md": "l"}
    for name, text in files.items():
        (base / name).parent.mkdir(parents=True, exist_ok=True)
        (base / name).write_text(text)
    for p in base.rglob("*"):
        os.utime(p, (old, old))
    return base


def tree_digest(folder: Path, skip: tuple[str, ...] = ()) -> dict[str, str]:
    out = {}
    for dirpath, dirnames, filenames in os.walk(folder):
        rel_dir = os.path.relpath(dirpath, folder)
        if rel_dir.split(os.sep)[0] in skip:
            continue
        for f in filenames:
            p = os.path.join(dirpath, f)
            out[os.path.relpath(p, folder)] = hashlib.sha256(Path(p).read_bytes()).hexdigest()
        out.update({os.path.relpath(os.path.join(dirpath, d), folder): "dir" for d in dirnames})
    return {k: v for k, v in out.items() if k.split(os.sep)[0] not in skip}


def decoy_runs(base: Path, log_file: Path) -> tuple[int, int]:
    """(runs, decoy files changed or removed): decode --out into the decoy tree and around it."""
    decoy = decoy_tree(base / "decoy")
    old_layout = decoy / "old_root"
    (old_layout / "decoded").mkdir(parents=True)
    (old_layout / "model.toml").write_text("effects = []\n")
    targets = [decoy / "new_out", old_layout, decoy, decoy / "foreign", decoy / "docs"]
    before = tree_digest(decoy, skip=("new_out", "old_root"))
    runs = 0
    for out in targets:
        with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
            cli.main(["decode", str(log_file), "--out", str(out)])
        safewrite.sweep_stale(out)
        runs += 1
    safewrite.sweep_stale(decoy)
    after = tree_digest(decoy, skip=("new_out", "old_root"))
    changed = sum(1 for k, v in before.items() if after.get(k) != v)
    return runs, changed + int(not ownership.is_marked(decoy / "new_out"))


# --- the report ---------------------------------------------------------------------------------

@dataclass(frozen=True)
class Report:
    configs: int
    tracebacks: list[Result]
    accepted_implausible: list[Result]
    refused_valid: list[Result]
    output_cases: int
    code_run: int
    outputs_not_refused: int
    decoy_runs: int
    decoy_touched: int
    seconds: float

    @property
    def ok(self) -> bool:
        return not (self.tracebacks or self.accepted_implausible or self.refused_valid or self.code_run
                    or self.outputs_not_refused or self.decoy_touched)

    def lines(self) -> list[str]:
        out = [f"config files (vehicle and model): {self.configs}",
               f"  tracebacks: {len(self.tracebacks)}",
               f"  implausible configurations accepted silently: {len(self.accepted_implausible)}",
               f"  valid configurations refused: {len(self.refused_valid)}",
               f"edited outputs naming code ({self.output_cases} reads): code run {self.code_run}, "
               f"not refused {self.outputs_not_refused}",
               f"decode --out into and around a decoy tree ({self.decoy_runs} runs and sweeps): decoy files touched "
               f"{self.decoy_touched}",
               f"({self.seconds:.1f} s)"]
        for label, results in (("traceback", self.tracebacks), ("accepted", self.accepted_implausible),
                               ("refused", self.refused_valid)):
            out += [f"  {label}: {r.case.kind} {r.case.name}: {r.message}" for r in results]
        return out


def run(base: Path) -> Report:
    t0 = time.perf_counter()
    from quadcore.sim import simulation

    logs = base / "logs"
    simulation.simulate_set(logs, [simulation.SimConfig(kind="hover", duration_s=2.0, seed=1)], {})
    empty = base / "empty_logs"
    empty.mkdir()
    vehicles = vehicle_cases()
    bad_vehicle = next(c.data for c in vehicles if c.name == "mass 1e300")
    deep = next(c.data for c in vehicles if c.name == "5000-deep array")
    cases = vehicles + model_cases(bad_vehicle, deep)
    results = [run_case(c, base / "cases" / f"{i:03d}", empty) for i, c in enumerate(cases)]
    n_out, code_run, not_refused = output_cases(base / "outputs")
    runs, touched = decoy_runs(base, logs / "sim000")
    return Report(len(cases), [r for r in results if r.outcome == "traceback"],
                  [r for r in results if r.outcome == "accepted" and not r.case.valid],
                  [r for r in results if r.outcome == "refused" and r.case.valid],
                  n_out, code_run, not_refused, runs, touched, time.perf_counter() - t0)


def main(argv: list[str] | None = None) -> int:
    argparse.ArgumentParser(prog="python -m tests.fuzz.configs", description=__doc__.splitlines()[0]).parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="quadcore-configs-") as tmp:
        report = run(Path(tmp))
    print("\n".join(report.lines()))
    return 0 if report.ok else 1


if __name__ == "__main__":
    sys.exit(main())
