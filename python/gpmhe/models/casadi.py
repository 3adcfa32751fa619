"""CasADi models behind `KnownModel.from_casadi`: checks of the functions' signatures, the stage
function (f, h and their Jacobians by CasADi's AD) and its evaluation at all window points in one
mapped call.

CasADi is optional: nothing here imports it at module level, `import_casadi` does when a CasADi
model is built or unpickled.

The user's f(x[, u]) and h(x[, u]) are wrapped into functions of one dense input d = [x; u]
(n + m values), expanded to SX (CasADi's fastest virtual machine) when CasADi can, optionally
compiled (``jit``), and mapped over k points with ``Function.map(k)`` (cached per k). CasADi's
buffer interface (``Function.buffer``) reads the numpy array of the points and writes the
results into one numpy array, without DM conversions. CasADi stores matrices column-major, so
the mapped input (n + m, k) is exactly the C-contiguous (k, n + m) array of the points, and an
output ``Jᵀ`` of shape (n + m, n) per point is, in k consecutive blocks, the row-major (k, n,
n + m) array the estimator's core reads.

The estimator's core does not call back into Python when it can avoid it: `CasadiModel.core_model`
compiles the same stage and prediction functions with CasADi's C code generation
(`gpmhe.models.compiled`) and hands the core the shared library, so that an update runs without
the GIL; where that fails (no C compiler) the core calls the functions above back, with one
warning.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import tempfile
import threading
import warnings

import numpy as np

from gpmhe import _core
from gpmhe._core import NumericalError
from gpmhe._validation import MAX_ABS, SettingsWarning, user_stacklevel, within_limits
from gpmhe.models import compiled
from gpmhe.models.base import ModelDomainError

__all__ = ["import_casadi", "CasadiModel"]

INSTALL_HINT = ('pip install casadi (without a network, from a wheelhouse made with --extras casadi: '
                'pip install --no-index --find-links wheelhouse "gpmhe[casadi]")')


def import_casadi(what):
    """The casadi module, or ImportError saying that ``what`` needs it and how to install it."""
    try:
        import casadi
    except ImportError as e:
        raise ImportError(f"{what} needs CasADi (>= 3.6), which is not installed: {INSTALL_HINT}") from e
    if not hasattr(casadi.Function, "buffer"):
        raise ImportError(f"{what} needs CasADi >= 3.6 (found {getattr(casadi, '__version__', '?')}): "
                          f"pip install --upgrade casadi")
    return casadi


def _vector_size(fn, name, kind, i):
    """The number of values of input or output i of fn, which must be a dense vector."""
    rows, cols = fn.size_in(i) if kind == "input" else fn.size_out(i)
    sparsity = fn.sparsity_in(i) if kind == "input" else fn.sparsity_out(i)
    label = fn.name_in(i) if kind == "input" else fn.name_out(i)
    if rows > 1 and cols > 1:
        raise ValueError(f"{name}: {kind} {i} ({label!r}) must be a vector, got shape {(rows, cols)} "
                         f"in {fn}")
    if kind == "input" and not sparsity.is_dense():
        raise ValueError(f"{name}: input {i} ({label!r}) must be dense, got {sparsity.nnz()} "
                         f"nonzeros of {rows * cols} in {fn}")
    return rows * cols


def check_no_free(ca, name, fn):
    """A CasADi Function must not depend on symbols that are not among its inputs (CasADi builds
    such a function with ``allow_free``, and only evaluating it fails)."""
    if not isinstance(fn, ca.Function):
        raise ValueError(f"{name}: must be a casadi.Function, got {type(fn).__name__}")
    if fn.has_free():
        free = ", ".join(str(v) for v in fn.get_free())
        raise ValueError(f"{name}: depends on symbols that are not its inputs ({free}) in {fn}; "
                         f"make them inputs or substitute values for them")


def signature(ca, name, fn):
    """(size of x, size of u or None without u, size of the output) of ``fn``, a CasADi Function
    fn(x) or fn(x, u) with one output, all dense vectors; ValueError naming ``name`` otherwise."""
    check_no_free(ca, name, fn)
    if fn.n_in() not in (1, 2):
        raise ValueError(f"{name}: must take x or (x, u) (or (x, u, p) for a model with "
                         f"parameters), got {fn.n_in()} inputs in {fn}")
    if fn.n_out() != 1:
        raise ValueError(f"{name}: must have one output, got {fn.n_out()} in {fn}")
    n = _vector_size(fn, name, "input", 0)
    m = _vector_size(fn, name, "input", 1) if fn.n_in() == 2 else None
    return n, m, _vector_size(fn, name, "output", 0)


def dimensions(ca, f, h):
    """(n, m, p) of the model f(x[, u]) -> x_next, h(x[, u]) -> y (h None: p = 0), after
    checking that the functions fit together."""
    n, m, n_out = signature(ca, "f", f)
    if n == 0:
        raise ValueError(f"f: the state x must have at least one value, got 0 in {f}")
    if n_out != n:
        raise ValueError(f"f: returns {n_out} values, expected one per state (dim_x = {n}) in {f}")
    m = 0 if m is None else m
    if h is None:
        return n, m, 0
    nh, mh, p = signature(ca, "h", h)
    if nh != n:
        raise ValueError(f"h: its input x has {nh} values, f's has {n} in {h}")
    if mh is not None and mh != m:
        raise ValueError(f"h: its input u has {mh} values, f's has {m} (dim_u) in {h}")
    return n, m, p


def _vec_call(ca, fn, x, u):
    """fn at the MX symbols x (and u) reshaped to fn's input shapes, as a column."""
    args = [ca.reshape(x, *fn.size_in(0))]
    if fn.n_in() == 2:
        args.append(ca.reshape(u, *fn.size_in(1)))
    return ca.vec(fn(*args))


def _padded_transpose(ca, J, m):
    """[J, 0]ᵀ, dense: the rows' Jacobian in d = [x; u] (u-columns zero), transposed so that
    CasADi's column-major storage is numpy's row-major (rows, n + m)."""
    return ca.densify(ca.vertcat(J.T, ca.MX(m, J.shape[0])))


def _run(trigger):
    """Evaluate through a buffer's trigger. CasADi reports a failed evaluation as a RuntimeError
    with its own text; a rootfinder that did not converge (an implicit integration step of
    `gpmhe.discretize`) becomes a `gpmhe.NumericalError` naming the step and what to change. Both
    are RuntimeErrors: at a trial point of the window solver they only reject the step."""
    try:
        trigger()
    except RuntimeError as e:
        text = str(e)
        found = re.search(r"for '([^']+)' \[Newton\]", text)
        if found is None or "rootfinder process failed" not in text:
            raise
        raise NumericalError(f"{found.group(1)}: the implicit step's Newton iteration did not converge "
                             f"within newton_max_iter iterations to newton_tol (CasADi rootfinder); "
                             f"try more substeps or a larger newton_max_iter") from None


@contextlib.contextmanager
def _jit_directory():
    """A fresh directory for CasADi's generated C file and compiled library, removed afterwards
    (the library is loaded by then; nothing is left in the working directory)."""
    directory = tempfile.mkdtemp(prefix="gpmhe-jit-")
    try:
        yield directory
    finally:
        shutil.rmtree(directory, ignore_errors=True)


def _jit_options(directory):
    # cleanup False (both levels): the directory goes as a whole once the library is loaded;
    # CasADi would otherwise try to delete its files again when the function is freed
    return {"jit": True, "compiler": "shell", "jit_cleanup": False,
            "jit_options": {"flags": ["-O2"], "verbose": False, "cleanup": False,
                            "directory": directory + os.sep}}


def check_compiler(ca):
    """``jit=True`` needs a C compiler that CasADi's shell compiler can run: compile a tiny
    function now, so that its absence is an error at construction, not at the first update."""
    x = ca.SX.sym("x")
    with _jit_directory() as directory:
        try:
            ca.Function("gpmhe_jit_probe", [x], [2 * x], _jit_options(directory))
        except RuntimeError as e:
            last = str(e).strip().splitlines()[-1] if str(e).strip() else ""
            raise ValueError(f"jit: CasADi could not compile a test function with its shell compiler "
                             f"(is a C compiler such as gcc installed and on PATH?): {last}") from None


class CasadiModel:
    """The CasADi functions of a `KnownModel` and their evaluation at k points d (k, n + m).

    `stage` is what the estimator's core calls back (no input checks: the core passes a
    C-contiguous float64 array); `part` evaluates one of ``"f"``, ``"h"``, ``"f_jacobian"``,
    ``"h_jacobian"``. Pickles as the user's two functions and the options (the derived functions
    are rebuilt, compiled again with ``jit``, when first used).
    """

    _PARTS = ("stage", "f", "h", "f_jacobian", "h_jacobian")
    #: The generated functions' names in the compiled library (its C symbols).
    _NATIVE = {"stage": "gpmhe_stage", "f": "gpmhe_f"}

    def __init__(self, f, h, jit=False, native=True):
        ca = import_casadi("KnownModel.from_casadi")
        self.dims = dimensions(ca, f, h)
        self.f, self.h, self.jit, self.native = f, h, bool(jit), bool(native)
        if self.jit:
            check_compiler(ca)
        self._setup()

    # ---- pickling: the user's functions (CasADi pickles them serialised) ---------------------
    def __getstate__(self):
        ca = import_casadi("Pickling a KnownModel.from_casadi model")
        for name, fn in (("f", self.f), ("h", self.h)):
            if fn is None:
                continue
            try:  # e.g. a Python casadi.Callback serialises, but cannot be read back
                ca.Function.deserialize(fn.serialize())
            except Exception as e:
                import pickle

                raise pickle.PicklingError(f"the CasADi function {name} cannot be serialised by "
                                           f"CasADi ({str(e).strip().splitlines()[-1]})") from None
        return {"f": self.f, "h": self.h, "jit": self.jit, "native": self.native, "dims": self.dims}

    def __setstate__(self, state):
        import_casadi("Unpickling a KnownModel.from_casadi model")
        self.f, self.h, self.jit, self.dims = state["f"], state["h"], state["jit"], tuple(state["dims"])
        self.native = state.get("native", True)
        self._setup()

    def _setup(self):
        n, m, p = self.dims
        nd = n + m
        self._lock = threading.Lock()
        self._functions = {}  # part -> Function of d (built on first use)
        self._maps = {}       # (part, k) -> (mapped function, buffer, trigger)
        # The core's callbacks hand back views of result buffers, read by the core after the
        # callback returned; each thread has buffers of its own, so another thread's call can
        # never overwrite them in between (the lock guards building them and `_evaluate`).
        self._callback = {}   # (thread, k) -> (buffer, trigger, results, the 8 arrays)
        self._predictor = {}  # thread -> (buffer, trigger, point, result)
        self._core_model = None  # the compiled model for the core (`core_model`), once built
        self._not_native = None  # why it could not be built (then the core calls back)
        # the values each part writes per point, in the order of its outputs
        self._sizes = {"stage": (n, n * nd, p, p * nd), "f": (n,), "h": (p,),
                       "f_jacobian": (n * n,), "h_jacobian": (p * n,)}
        self._per_point = {part: sum(s) for part, s in self._sizes.items()}

    def __repr__(self):
        n, m, p = self.dims
        return f"<CasADi model: f {self.f.name()!r}, h {None if self.h is None else self.h.name()!r}, " \
               f"dim_x={n}, dim_u={m}, dim_y={p}>"

    # ---- building ------------------------------------------------------------------------------
    def _build(self, part, name=None, jit=None):
        """The Function of d for ``part`` (named ``name``, default ``part``): from MX symbols x,
        u; expanded to SX when possible (an MX-only node such as a rootfinder keeps MX); compiled
        with ``jit`` (default: the model's)."""
        ca = import_casadi("KnownModel.from_casadi")
        name = part if name is None else name
        jit = self.jit if jit is None else jit
        n, m, p = self.dims
        x, u, d = ca.MX.sym("x", n), ca.MX.sym("u", m), ca.MX.sym("d", n + m)
        fx = _vec_call(ca, self.f, x, u)
        hx = ca.MX(0, 1) if self.h is None else _vec_call(ca, self.h, x, u)
        if part == "stage":
            outs = [fx, _padded_transpose(ca, ca.jacobian(fx, x), m),
                    hx, _padded_transpose(ca, ca.jacobian(hx, x), m)]
        elif part == "f":
            outs = [fx]
        elif part == "h":
            outs = [hx]
        else:  # ∂/∂x transposed: row-major (rows, n) per point
            outs = [ca.densify(ca.jacobian(fx if part == "f_jacobian" else hx, x).T)]
        inner = ca.Function(name, [x, u], [ca.densify(out) for out in outs])
        xd, ud = (ca.vertsplit(d, [0, n, n + m]) if m else (d, ca.MX(0, 1)))
        outer = ca.Function(name, [d], inner.call([xd, ud]))
        opts = {"cse": True}  # common subexpressions once (about 20% fewer operations for RK4)
        if not jit:
            try:
                return outer.expand(name, opts)
            except RuntimeError:  # not expandable (an MX-only operation inside): MX
                return outer
        with _jit_directory() as directory:
            opts.update(_jit_options(directory))
            try:
                return outer.expand(name, opts)
            except RuntimeError:
                return ca.Function(name, [d], outer.call([d]), opts)

    def _map(self, part, k):
        entry = self._maps.get((part, k))
        if entry is None:
            fn = self._functions.get(part)
            if fn is None:
                fn = self._functions[part] = self._build(part)
            mapped = fn.map(k) if k > 1 else fn
            buf, trigger = mapped.buffer()
            entry = self._maps[(part, k)] = (mapped, buf, trigger)
        return entry

    # ---- the core's model: compiled, else callbacks ------------------------------------------
    def core_model(self):
        """The `gpmhe._core.StageModel` an estimator runs: the compiled stage and prediction
        functions (built once per model, the library from gpmhe's cache when it holds it), or,
        with ``native=False`` or when compiling fails (one `gpmhe.SettingsWarning` per model),
        this object's callbacks."""
        if self.native and self._not_native is None:
            with self._lock:
                if self._core_model is None and self._not_native is None:
                    self._core_model = self._compile()
            if self._core_model is not None:
                return self._core_model
        n, m, p = self.dims
        return _core.StageModel.callback(self.stage_callback, n, m, p, predict=self.predict_callback)

    def _compile(self):
        """The compiled model, or None (with the warning) if it cannot be built."""
        ca = import_casadi("KnownModel.from_casadi")
        n, m, p = self.dims
        functions = [self._build(part, name, jit=False) for part, name in self._NATIVE.items()]
        for rebuild in (False, True):  # a library that does not load is compiled once more
            try:
                path = compiled.library(ca, functions, rebuild=rebuild)
                return _core.StageModel.compiled(path, self._NATIVE["stage"], self._NATIVE["f"],
                                                 n, m, p, self.core_model)
            except compiled.CompileError as e:
                reason = str(e)
                break
            except ValueError as e:
                reason = str(e)
        self._not_native = reason
        warnings.warn(f"the CasADi model {self.f.name()!r} runs as Python callbacks (the GIL held "
                      f"during updates, banks of it serial): it could not be compiled for the "
                      f"estimator's core: {reason}", SettingsWarning, stacklevel=user_stacklevel())
        return None

    # ---- evaluation ----------------------------------------------------------------------------
    def _evaluate(self, part, d):
        """All outputs of ``part`` at the k points d (C-contiguous float64 (k, n + m)), as one
        flat array (output by output, point by point within an output)."""
        k = d.shape[0]
        _, buf, trigger = self._map(part, k)
        out = np.empty(k * self._per_point[part])
        with self._lock:  # one buffer per (part, k): one evaluation at a time
            buf.set_arg(0, memoryview(d))
            start = 0
            for i, size in enumerate(self._sizes[part]):
                if size:
                    buf.set_res(i, memoryview(out[start:start + k * size]))
                start += k * size
            _run(trigger)
        return out

    def _check(self, part, out):
        if not within_limits(out):
            raise ModelDomainError(f"{part}: returned NaN or inf or a value of magnitude > {MAX_ABS:g} "
                             f"(CasADi model)")

    def part(self, name, d):
        """One part at the k points d: f (k, n), h (k, p), f_jacobian (k, n, n) or h_jacobian
        (k, p, n)."""
        n, _, p = self.dims
        d = np.ascontiguousarray(d, dtype=np.float64)
        out = self._evaluate(name, d)
        self._check(name, out)
        rows = {"f": n, "h": p, "f_jacobian": n, "h_jacobian": p}[name]
        k = d.shape[0]
        return out.reshape((k, rows) if name in ("f", "h") else (k, rows, n))

    def _callback_entry(self, key):
        """For the core's stage callback of one thread at k points (``key`` = (thread, k)): a
        buffer of its own whose results are bound once to one array, and the 8 arrays (views of
        it, the variances zeros) returned by every call."""
        n, m, p = self.dims
        nd = n + m
        k = key[1]
        with self._lock:
            mapped = self._map("stage", k)[0]
        buf, trigger = mapped.buffer()
        out = np.empty(k * self._per_point["stage"])
        a, b, c = k * n, k * n * (1 + nd), k * (n + n * nd + p)
        for i, (start, end) in enumerate(((0, a), (a, b), (b, c), (c, out.size))):
            if end > start:
                buf.set_res(i, memoryview(out[start:end]))
        zeros = [np.zeros(shape) for shape in ((k, n), (k, n, nd), (k, p), (k, p, nd))]
        arrays = (out[:a].reshape(k, n), zeros[0], out[a:b].reshape(k, n, nd), zeros[1],
                  out[b:c].reshape(k, p), zeros[2], out[c:].reshape(k, p, nd), zeros[3])
        for arr in arrays:
            arr.flags.writeable = False
        entry = self._callback[key] = (buf, trigger, out, arrays)
        return entry

    def _stage(self, d):
        key = (threading.get_ident(), d.shape[0])
        entry = self._callback.get(key)
        if entry is None:
            entry = self._callback_entry(key)
        buf, trigger, out, arrays = entry
        buf.set_arg(0, memoryview(d))
        _run(trigger)
        if not within_limits(out):
            self._raise_bad(out, d.shape[0])
        return arrays

    def stage_callback(self, d):
        """The 8 arrays of `KnownModel.stage_eval` at the points d (C-contiguous float64
        (k, n + m)): the estimator core's callback. The arrays are read-only and belong to the
        calling thread: its next call overwrites them, another thread's never does."""
        return self._stage(d)

    def stage(self, d):
        """`stage_callback` with fresh, writable arrays: `KnownModel.stage_eval`."""
        return tuple(np.array(a) for a in self._stage(d))

    def _raise_bad(self, out, k):
        n, m, p = self.dims
        nd = n + m
        ends = np.cumsum([k * n, k * n * nd, k * p, k * p * nd])
        for name, start, end in zip(("f", "f_jacobian", "h", "h_jacobian"), [0, *ends[:-1]], ends):
            if not within_limits(out[start:end]):
                raise ModelDomainError(f"{name}: returned NaN or inf or a value of magnitude > "
                                 f"{MAX_ABS:g} (CasADi model)")

    def predict_callback(self, x, u):
        """f(x, u) at one point (contiguous float64 vectors): the estimator core's prediction
        callback. The result belongs to the calling thread: its next call overwrites it."""
        me = threading.get_ident()
        entry = self._predictor.get(me)
        if entry is None:
            with self._lock:
                mapped = self._map("f", 1)[0]
            buf, trigger = mapped.buffer()
            point, result = np.empty(sum(self.dims[:2])), np.empty(self.dims[0])
            buf.set_arg(0, memoryview(point))
            buf.set_res(0, memoryview(result))
            entry = self._predictor[me] = (buf, trigger, point, result)
        _, trigger, point, result = entry
        n = self.dims[0]
        point[:n] = x
        point[n:] = u
        _run(trigger)
        self._check("f", result)
        return result


class CasadiPart:
    """One of a CasADi model's functions as `KnownModel` calls it with ``vectorized=True``:
    ``part(X, U)`` for X (k, n) and U (k, m) (or None when m = 0)."""

    def __init__(self, model, name):
        self.model, self.name = model, name

    def __call__(self, X, U=None):
        X = np.asarray(X, dtype=np.float64)
        k = X.shape[0] if X.ndim == 2 else 1
        U = np.zeros((k, 0)) if U is None else np.asarray(U, dtype=np.float64)
        d = np.concatenate((X.reshape(k, -1), U.reshape(k, -1)), axis=1)
        if d.shape[1] != sum(self.model.dims[:2]):
            raise ValueError(f"{self.name}: X and U must have dim_x + dim_u = "
                             f"{sum(self.model.dims[:2])} columns together, got {d.shape[1]}")
        return self.model.part(self.name, d)

    def __repr__(self):
        fn = self.model.h if self.name.startswith("h") else self.model.f
        what = self.name.replace("_jacobian", "'s Jacobian")
        return f"<{what} of the CasADi function {fn.name()!r}, vectorised>"
