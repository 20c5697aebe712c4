"""Compile the generated C: the strict check, the footprint, and a host library to run it on a
flight's rows (tests, benchmark).

The footprint is measured by compiling for the Cortex-M4 when ``arm-none-eabi-gcc`` is
installed (``-Os -mcpu=cortex-m4 -mfpu=fpv4-sp-d16 -mfloat-abi=hard``), else for the host
(labelled so): flash = ``.text`` + ``.rodata`` + ``.data``, static RAM = ``.data`` + ``.bss``,
stack = the sum of every function's frame from ``-fstack-usage`` (an upper bound: the deepest
call chain is shorter), plus the caller's three structs.
"""

from __future__ import annotations

import ctypes
import hashlib
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from quadcore.effects.c_inputs import ExportError
from quadcore.export.c.generate import HEADER, OUTPUTS, SOURCE, Generated

# The flags, plus what a float-only firmware build cares about (no silent double, no shadowing)
STRICT = ["-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-Wdouble-promotion", "-Wshadow"]
CORTEX_M4 = ["-mcpu=cortex-m4", "-mthumb", "-mfpu=fpv4-sp-d16", "-mfloat-abi=hard"]
STM32F405_FLASH_BYTES = 1024 * 1024
STM32F405_RAM_BYTES = 192 * 1024


class CompileError(ExportError):
    """The C compiler is missing or rejected the generated code."""


def host_compiler() -> str:
    for name in ("cc", "gcc", "clang"):
        path = shutil.which(name)
        if path:
            return path
    raise CompileError("no C compiler found (cc, gcc or clang): install gcc")


def _run(cmd: list[str], cwd: Path) -> None:
    done = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True)
    if done.returncode != 0:
        raise CompileError(f"{' '.join(cmd)} failed:\n{done.stderr.strip()}")


def check_strict(gen: Generated, defines: tuple[str, ...] = ()) -> None:
    """Compile the generated source with :data:`STRICT` (``-std=c99 -Wall -Wextra -Werror`` and
    more), in a scratch folder (the files may be written to an object store)."""
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        (folder / HEADER).write_text(gen.header)
        (folder / SOURCE).write_text(gen.source)
        _run([host_compiler(), *STRICT, *defines, "-c", SOURCE, "-o", "m.o"], folder)


@dataclass(frozen=True)
class Footprint:
    """Bytes of flash and RAM the model takes, and how they were measured."""

    target: str
    flash_bytes: int
    static_ram_bytes: int
    stack_bytes: int
    struct_bytes: int  # input + memory + output, owned by the caller

    @property
    def ram_bytes(self) -> int:
        return self.static_ram_bytes + self.stack_bytes + self.struct_bytes

    def comment(self) -> str:
        flash_share = self.flash_bytes / STM32F405_FLASH_BYTES
        return (f"Footprint ({self.target}): flash {self.flash_bytes} B ({flash_share:.2%} "
                f"of the STM32F405's 1 MB), RAM {self.ram_bytes} B ({self.ram_bytes / STM32F405_RAM_BYTES:.2%} of "
                f"192 KB):\nstatic {self.static_ram_bytes} B, stack at most {self.stack_bytes} B, the caller's "
                f"input/memory/output structs {self.struct_bytes} B.")

    def to_dict(self) -> dict:
        return {"target": self.target, "flash_bytes": self.flash_bytes, "ram_bytes": self.ram_bytes,
                "static_ram_bytes": self.static_ram_bytes, "stack_bytes": self.stack_bytes,
                "struct_bytes": self.struct_bytes, "flash_budget_bytes": STM32F405_FLASH_BYTES,
                "ram_budget_bytes": STM32F405_RAM_BYTES}


def _sections(size_tool: str, obj: Path) -> dict[str, int]:
    out = subprocess.run([size_tool, "-A", str(obj)], capture_output=True, text=True, check=True).stdout
    sizes: dict[str, int] = {}
    for line in out.splitlines():
        parts = line.split()
        if len(parts) >= 2 and parts[0].startswith(".") and parts[1].isdigit():
            sizes[parts[0]] = sizes.get(parts[0], 0) + int(parts[1])
    return sizes


# A zero-filled array as large as the caller's three structs: its .bss size is their sizeof.
STRUCT_SIZES = """#include "quadcore_model.h"
char qc_struct_bytes[sizeof(quadcore_input_t) + sizeof(quadcore_memory_t) + sizeof(quadcore_wrench_t)];
"""


# The cross compiler here comes without a C library: declarations are all the footprint needs.
ARM_MATH_H = """float sqrtf(float); float expf(float); float fabsf(float);
double sqrt(double); double exp(double); double fabs(double);
#define isnan(x) __builtin_isnan(x)
#define INFINITY (__builtin_inff())
"""


def measure_footprint(gen: Generated) -> Footprint | None:
    """Compile ``gen`` for the Cortex-M4 (or, without a cross compiler, the host) and read the
    sections and stack frames; ``None`` when no compiler is installed."""
    arm = shutil.which("arm-none-eabi-gcc")
    try:
        cc = arm or host_compiler()
    except CompileError:
        return None
    flags = [*CORTEX_M4, "-Os", "-fno-math-errno", "-Iinclude"] if arm else ["-Os"]
    size_tool = shutil.which("arm-none-eabi-size" if arm else "size")
    if size_tool is None:
        return None
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        (folder / HEADER).write_text(gen.header)
        (folder / SOURCE).write_text(gen.source)
        (folder / "include").mkdir()
        (folder / "include" / "math.h").write_text(ARM_MATH_H)
        _run([cc, "-std=c99", *flags, "-fstack-usage", "-c", SOURCE, "-o", "m.o"], folder)
        sections = _sections(size_tool, folder / "m.o")
        stack = sum(int(line.split("\t")[1]) for line in (folder / "m.su").read_text().splitlines() if "\t" in line)
        (folder / "s.c").write_text(STRUCT_SIZES)
        _run([cc, "-std=c99", *flags, "-fno-common", "-c", "s.c", "-o", "s.o"], folder)
        struct_bytes = _sections(size_tool, folder / "s.o").get(".bss", 0)
    flash = sum(v for k, v in sections.items() if k.startswith((".text", ".rodata", ".data")))
    ram = sum(v for k, v in sections.items() if k.startswith((".data", ".bss")))
    target = ("Cortex-M4, arm-none-eabi-gcc -Os -fno-math-errno; libm's expf, where used, not counted" if arm else
              "measured for the host with cc -Os, no ARM compiler installed: Thumb-2 code is usually smaller")
    return Footprint(target, flash, ram, stack, struct_bytes)


# ---------------------------------------------------------------------------------------
# A host library to run the exported model on a flight's rows
# ---------------------------------------------------------------------------------------

def _harness(gen: Generated) -> str:
    copy, offset = [], 0
    for f in gen.fields:
        if f.length:
            copy.append(f"for (k = 0; k < {f.length}; ++k) in.{f.name}[k] = row[{offset} + k];")
        else:
            copy.append(f"in.{f.name} = row[{offset}];")
        offset += f.size
    outs = "\n            ".join(f"for (k = 0; k < 3; ++k) o[{3 * i} + k] = w.{name}[k];"
                                  for i, name in enumerate(OUTPUTS))
    features = """
void qc_harness_features(long n, const float *x, float *out)
{
    long r;
    for (r = 0; r < n; ++r) quadcore_learned_from_features(x + r * QUADCORE_N_FEATURES, out + 6 * r, out + 6 * r + 3);
}
""" if gen.feature_columns else ""
    return f"""#include "{HEADER}"
/* Runs the model over n rows of inputs (the struct's fields, flattened), `repeats` times from a reset
   memory; writes {3 * len(OUTPUTS)} floats per row ({', '.join(OUTPUTS)}) when out is not NULL. */
void qc_harness_run(long n, const float *rows, float *out, int repeats)
{{
    quadcore_input_t in;
    quadcore_memory_t mem;
    quadcore_wrench_t w;
    long r;
    int k, rep;
    (void)k;
    for (rep = 0; rep < repeats; ++rep) {{
        quadcore_reset(&mem);
        for (r = 0; r < n; ++r) {{
            const float *row = rows + r * {max(offset, 1)};
            (void)row;
            {chr(10).join('            ' + c for c in copy).strip()}
            quadcore_residual(&in, &mem, &w);
            if (out) {{
            float *o = out + r * {3 * len(OUTPUTS)};
            {outs}
            }}
        }}
    }}
}}
{features}"""


class HostModel:
    """The exported model compiled for this machine (``-O2``) and loaded with ctypes."""

    def __init__(self, folder: Path, gen: Generated, workdir: Path, defines: tuple[str, ...] = ()):
        self.gen = gen
        self.width = max(sum(f.size for f in gen.fields), 1)
        workdir.mkdir(parents=True, exist_ok=True)
        (workdir / "harness.c").write_text(_harness(gen))
        # named after what it holds: the loader hands back an already loaded library for a known path
        digest = hashlib.sha256("\0".join([gen.source, gen.header, *defines]).encode()).hexdigest()[:16]
        lib = workdir / f"libquadcore_model_{digest}.so"
        strict = [f for f in STRICT if f != "-Wdouble-promotion" or "-DQUADCORE_DOUBLE_INPUTS" not in defines]
        _run([host_compiler(), *strict, "-O2", "-fPIC", "-shared", *defines, f"-I{folder}", str(Path(folder) / SOURCE),
              "harness.c", "-o", lib.name, "-lm"], workdir)
        self.lib = ctypes.CDLL(str(lib))
        f32 = np.ctypeslib.ndpointer(np.float32, flags="C_CONTIGUOUS")
        self.lib.qc_harness_run.argtypes = [ctypes.c_long, f32, ctypes.c_void_p, ctypes.c_int]
        if gen.feature_columns:
            self.lib.qc_harness_features.argtypes = [ctypes.c_long, f32, f32]

    def run(self, rows: np.ndarray) -> dict[str, np.ndarray]:
        """(n, width) float32 inputs -> {output name: (n, 3)}, in call order from a reset."""
        rows = np.ascontiguousarray(rows, np.float32).reshape(len(rows), self.width)
        out = np.zeros((len(rows), 3 * len(OUTPUTS)), np.float32)
        self.lib.qc_harness_run(len(rows), rows, out.ctypes.data, 1)
        return {name: out[:, 3 * i: 3 * i + 3].astype(np.float64) for i, name in enumerate(OUTPUTS)}

    def learned_from_features(self, X: np.ndarray) -> np.ndarray:
        X = np.ascontiguousarray(X, np.float32)
        out = np.zeros((len(X), 6), np.float32)
        self.lib.qc_harness_features(len(X), X, out)
        return out.astype(np.float64)

    def seconds_per_call(self, rows: np.ndarray, chunk: int = 500, tries: int = 200) -> float:
        """Per call: the best of ``tries`` timed passes over ``chunk`` consecutive rows (a few ms
        each, so that some run without being preempted on a shared machine; outputs not copied)."""
        rows = np.ascontiguousarray(rows, np.float32).reshape(len(rows), self.width)
        starts = np.arange(0, max(len(rows) - chunk, 0) + 1, chunk)
        best = float("inf")
        for k in range(tries):
            block = np.ascontiguousarray(rows[starts[k % len(starts)]:][:chunk])
            t0 = time.perf_counter()
            self.lib.qc_harness_run(len(block), block, None, 1)
            best = min(best, (time.perf_counter() - t0) / len(block))
        return best
