"""The C evaluator of a controller model (controller_evaluator.c / .h, shipped in this package):
the flat coefficient block it loads, and a ctypes binding that compiles it with the system C
compiler, with which the tests and benchmarks/bench_controller.py compare it with the numpy
reference evaluator (controller_evaluator.py) and time it.

The block is the controller JSON's contents as little-endian float64 in the order the C header
lists (``coefficient_block`` is that order's one definition); the exporter writes it beside the
JSON from the same contents, so the two cannot disagree.
"""
from __future__ import annotations

import ctypes
import shutil
import subprocess
from pathlib import Path

import numpy as np

from deltatwin.calibration.physics import controller_evaluator as ce

SOURCE = Path(__file__).with_name("controller_evaluator.c")
MAGIC = 1146373937.0            # "DTC1"; DTC_MAGIC in the header
LAYOUT_VERSION = 1.0
STEP_SIZE = 13                  # a step's kind and 12 values, zero-padded
STEP_KINDS = {"loop_drift": 1, "beam_misalignment": 2, "air_refraction": 3}
STATUSES = {0: "converged", 1: "not_converged", 2: "out_of_stroke", 3: "not_finite"}
ERRORS = {-1: "not a coefficient block of this layout", -2: "the rods cannot reach the platform",
          -3: "the kinematic loop did not close", -4: "the block file cannot be read"}


class ControllerCError(RuntimeError):
    """The C evaluator cannot be built or refuses its input."""


def _step_values(step: dict) -> list:
    kind = step["kind"]
    f = lambda k: np.ravel(np.asarray(step[k], dtype=np.float64)).tolist()
    if kind == "loop_drift":
        return [*f("reference_C"), *f("frame_height_m"), *f("frame_arm_m"), *f("table_cte_per_K"),
                *f("frame_cte_per_K"), *f("support_cte_per_K")]
    if kind == "beam_misalignment":
        return [*f("angle_rad"), *f("abbe_offset_m")]
    if kind == "air_refraction":
        return [*f("wavelength_m"), *f("beam_room_fraction"), *f("compensation_offset_C"),
                *f("assumed_pressure_Pa"), *f("vapour_pressure_Pa")]
    raise ControllerCError(f"optics step {kind!r} has no layout in the C evaluator")


def coefficient_block(doc: dict) -> np.ndarray:
    """The flat float64 block of a controller model (the JSON's contents, as written or as
    ``controller_evaluator.load`` reads them) in the C evaluator's layout."""
    g, th, load, o, st = (doc[k] for k in ("geometry", "thermal", "load", "optics", "statics"))
    a = lambda v: np.ravel(np.asarray(v, dtype=np.float64))
    mag = load.get("magnetic")
    parts = [a([th["reference_C"]]), a([th["cte_per_K"][k] for k in ("base", "arms", "rods",
                                                                     "platform")]),
             a(g["B_m"]), a(g["axis"]), a(g["arm_vec_m"]), a(g["P0_m"]), a(g["L_m"]),
             a(g["theta_zero_rad"]), a(g["cube_offset_m"]), a([g["cube_size_m"]]),
             a(g["stroke_rad"]),
             a([load.get("gravity_N") is not None]),
             a(load["gravity_N"]) if load.get("gravity_N") is not None else np.zeros(3),
             a([mag is not None])]
    if mag is None:
        parts.append(np.zeros(20))
    else:
        parts += [a([mag["magnet_moment_Am2"], mag["coil_moment_per_A"]]),
                  a(mag["magnets_platform_m"]), a(mag["coils_m"])]
    parts += [a([o["heads_m"][k] for k in ce.AXES]), a([o["directions"][k] for k in ce.AXES]),
              a(o["fold_m"]), a(o["fold_normal"]), a([len(o["steps"])])]
    for step in o["steps"]:
        v = _step_values(step)
        parts.append(a([STEP_KINDS[step["kind"]], *v, *[0.0] * (STEP_SIZE - 1 - len(v))]))
    m = np.asarray(st["preload_coef"]).shape[0]
    coef = np.concatenate([np.asarray(st["preload_coef"], dtype=np.float64),
                           np.asarray(st["compliance_coef"], dtype=np.float64).reshape(
                               (m, m, m, 36))], axis=-1)
    parts += [a([*st["q_range_rad"], st["degree"]]), a(coef)]
    body = np.concatenate(parts)
    return np.concatenate([[MAGIC, LAYOUT_VERSION, body.size + 3], body]).astype("<f8")


def block_path(json_path) -> Path:
    """Where the exporter writes the block of the controller file ``json_path``."""
    return Path(json_path).with_suffix(".bin")


# -- the ctypes binding ---------------------------------------------------------------------

class _Model(ctypes.Structure):
    _fields_ = [("_opaque", ctypes.c_double * 1024)]       # more than sizeof(dtc_model), 1.9 kB


class _Conditions(ctypes.Structure):
    _fields_ = [("T_C", ctypes.c_double * len(ce.CONDITIONS)), ("pressure_Pa", ctypes.c_double),
                ("currents_A", ctypes.c_double * 3)]


class _Pose(ctypes.Structure):
    _fields_ = [("valid", ctypes.c_int), ("p", ctypes.c_double * 3),
                ("R", ctypes.c_double * 9)]


class _Session(ctypes.Structure):
    _fields_ = [("model", ctypes.c_void_p), ("paths_zero", ctypes.c_double * 3)]


def compile_library(out_dir, compiler: str | None = None) -> Path:
    """The C evaluator compiled into a shared library in ``out_dir`` (C99, -O2, libm)."""
    cc = compiler or shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        raise ControllerCError("no C compiler (cc or gcc) on PATH")
    lib = Path(out_dir) / "libdeltatwin_controller.so"
    cmd = [cc, "-std=c99", "-O2", "-Wall", "-Wextra", "-pedantic", "-Werror", "-fPIC",
           "-shared", "-o", str(lib), str(SOURCE), "-lm"]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise ControllerCError(f"{' '.join(cmd)} failed:\n{r.stderr}")
    return lib


class CSession:
    """One session of the C evaluator loaded through ctypes: the model block read by its
    ``dtc_read_block``, the zero's conditions; ``forward`` and ``inverse`` one point at a time
    with the numpy Session's conditions (dicts of scalars)."""

    def __init__(self, library, block_file, zero_conditions: dict):
        self.lib = ctypes.CDLL(str(library))
        self.lib.dtc_inverse.argtypes = [ctypes.c_void_p] * 5 + [
            ctypes.c_double, ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p]
        n = Path(block_file).stat().st_size // 8
        self._block = (ctypes.c_double * n)()
        got = ctypes.c_size_t()
        self._check(self.lib.dtc_read_block(str(block_file).encode(), self._block,
                                            ctypes.c_size_t(n), ctypes.byref(got)))
        self._model = _Model()
        self._check(self.lib.dtc_model_init(ctypes.byref(self._model), self._block, got))
        self._ref = _Conditions()
        self.lib.dtc_conditions_reference(ctypes.byref(self._model), ctypes.byref(self._ref))
        self._session = _Session()
        self._check(self.lib.dtc_session_init(ctypes.byref(self._session),
                                              ctypes.byref(self._model),
                                              ctypes.byref(self.conditions(zero_conditions))))
        self._q = (ctypes.c_double * 3)()
        self._out = (ctypes.c_double * 3)()
        self._resid = ctypes.c_double()
        self._iters = ctypes.c_int()

    @staticmethod
    def _check(rc):
        if rc < 0:
            raise ControllerCError(f"C evaluator: {ERRORS.get(rc, rc)}")
        return rc

    def conditions(self, values: dict) -> _Conditions:
        """The C conditions of one point (missing values as in the numpy evaluator)."""
        c = _Conditions.from_buffer_copy(self._ref)
        one = lambda k, size: np.broadcast_to(np.asarray(values[k], float).reshape(-1), (size,))
        for k, name in enumerate(ce.CONDITIONS):
            if name in values:
                c.T_C[k] = one(name, 1)[0]
        if "pressure_Pa" in values:
            c.pressure_Pa = one("pressure_Pa", 1)[0]
        if "currents_A" in values:
            c.currents_A[:] = one("currents_A", 3)
        return c

    def forward(self, q, cond, pose: _Pose | None = None) -> np.ndarray:
        self._q[:] = np.asarray(q, dtype=np.float64)
        self._check(self.lib.dtc_forward(ctypes.byref(self._session), self._q,
                                         ctypes.byref(cond), None if pose is None else ctypes.byref(pose),
                                         self._out))
        return np.array(self._out[:])

    def inverse(self, target, cond, q0=None, pose: _Pose | None = None, tol_m: float = 1e-12,
                max_iter: int = 20) -> dict:
        """As the numpy Session.inverse for one point: q, status, residual_m, iterations; the
        ``pose`` (a ``new_pose()``) is the warm start in and the solution's pose out."""
        t = (ctypes.c_double * 3)(*np.asarray(target, dtype=np.float64))
        start = None if q0 is None else (ctypes.c_double * 3)(*np.asarray(q0, dtype=np.float64))
        rc = self._check(self.lib.dtc_inverse(
            ctypes.byref(self._session), t, ctypes.byref(cond), start,
            None if pose is None else ctypes.byref(pose), tol_m, max_iter, self._q,
            ctypes.byref(self._resid), ctypes.byref(self._iters)))
        return {"q": np.array(self._q[:]), "status": STATUSES[rc],
                "residual_m": self._resid.value, "iterations": self._iters.value}

    @staticmethod
    def new_pose(like: _Pose | None = None) -> _Pose:
        """A pose for ``inverse``: empty (the closed-form start), or a copy of ``like``."""
        return _Pose() if like is None else _Pose.from_buffer_copy(like)
