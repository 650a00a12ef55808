"""The generated C kernels from Python, through ctypes, without per-call overhead.

``load()`` opens ``libcochlea.so``: the file the environment variable ``COCHLEA_LIB`` names,
else the checkout's ``build/libcochlea.so`` (built by ``make lib`` from ``generated_c/``), else
the copy an installed wheel carries in ``cochlea/lib/``. ``library.kernel(name)`` binds one
kernel: it reads the kernel's signature from the library itself (``NAME_n_in``,
``NAME_sparsity_in``, ``NAME_work``, ...), allocates one numpy buffer per input and output (or
takes the caller's arrays, checked once here: dtype float64, shape, memory order, writeable), and
prepares the pointer arrays CasADi's calling convention needs. A call then is one ctypes call on
those prepared arrays -- no allocation, no argument conversion, no loop over elements::

    import numpy as np
    from cochlea.kernels import library

    lib = library.load()
    step = lib.kernel("serial_arm1_e_step")
    step["q"][:] = np.radians([73.0, 83.0, 110.0])   # write into the input buffers ...
    step["gains"][:] = [5, 4, 3, 0.05, 0.04, 0.003]
    step["Gamma"][:] = 1.0
    step["bound"][...] = 1.0
    step["h"][...] = 1e-3
    step()                                           # ... call ...
    tau = step["tau"]                                # ... and read the output buffers (views)

Buffers have the kernel's shapes: a column ``n x 1`` is a vector ``(n,)``, a scalar ``()``, a
matrix ``r x c`` an ``(r, c)`` array in Fortran (column-major) order, CasADi's layout.
``library.closed_loop(name)`` binds a generated closed-loop driver (N periods in C).

Every name the manifest lists binds, aliases included: a kernel (or driver) computing exactly
what an earlier one does has no C of its own, and its manifest entry's ``symbol`` names the C
function it runs; :meth:`Library.symbol` resolves it before any C symbol (``NAME``,
``NAME_n_in``, ...) is looked up, while the signature and source hash stay the alias's own.
"""

from __future__ import annotations

import ctypes
import functools
import json
import os
import stat
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import CochleaError
from ..resources import PACKAGED_LIBRARY, checkout
from .naming import MANIFEST_FORMAT

ENVIRONMENT = "COCHLEA_LIB"

_int = ctypes.c_longlong  # casadi_int: CasADi's default, long long int
_double_p = ctypes.POINTER(ctypes.c_double)
KERNEL_ARGTYPES = [ctypes.POINTER(ctypes.c_void_p), ctypes.POINTER(ctypes.c_void_p),
                    ctypes.POINTER(_int), _double_p, ctypes.c_int]


class LibraryError(CochleaError):
    """The C library is missing, stale or does not have what was asked for."""


class KernelError(CochleaError):
    """A kernel returned a nonzero code or was bound to unsuitable buffers."""


@dataclass(frozen=True)
class Argument:
    """One input or output of a kernel: its name and dense shape (rows x cols)."""

    name: str
    rows: int
    cols: int

    @property
    def shape(self) -> tuple[int, ...]:
        """The numpy shape of the buffer: ``()``, ``(rows,)`` or ``(rows, cols)``."""
        if self.cols == 1:
            return () if self.rows == 1 else (self.rows,)
        return (self.rows, self.cols)

    @property
    def size(self) -> int:
        return self.rows * self.cols


@dataclass(frozen=True)
class Signature:
    """A kernel's inputs, outputs and work-array sizes, as the library reports them."""

    name: str
    inputs: tuple[Argument, ...]
    outputs: tuple[Argument, ...]
    sz_arg: int
    sz_res: int
    sz_iw: int
    sz_w: int


def default_library() -> Path:
    """Run from a checkout: its ``build/libcochlea.so``; installed: the package's copy."""
    root = checkout()
    return root / "build" / "libcochlea.so" if root is not None else PACKAGED_LIBRARY


#: The library's file name in a folder ``cochlea-codegen --out DIR`` wrote and compiled.
LIBRARY_NAME = "libcochlea.so"


def library_path(path: str | Path | None = None) -> Path:
    """The library to load: ``path``, else ``$COCHLEA_LIB``, else :func:`default_library`.
    A folder (what ``cochlea-codegen --scenario ... --out DIR`` wrote) means its
    ``libcochlea.so``."""
    if path is None:
        path = os.environ.get(ENVIRONMENT) or default_library()
    path = Path(path)
    return path / LIBRARY_NAME if path.is_dir() else path


@functools.cache
def _load(path: str) -> Library:
    return Library(path)


#: What :func:`load` found for each way of naming a library (the argument, ``$COCHLEA_LIB``
#: and, for a relative name, the working directory): the file's path as named, the file
#: itself (device and inode) and its real path. A sweep's worker asks for the library every
#: sample; resolving the checkout's folder and the real path each time cost 0.1-0.2 ms.
_FOUND: dict[tuple, tuple[str, tuple[int, int], str]] = {}


def _file_id(path: str) -> tuple[int, int] | None:
    """The regular file ``path`` names (symbolic links followed): ``(device, inode)``, or
    None when there is none."""
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return (st.st_dev, st.st_ino) if stat.S_ISREG(st.st_mode) else None


def load(path: str | Path | None = None) -> Library:
    """The library (opened once per path and process).

    Found again in one ``stat`` when asked for the same way as before: the name it was
    found by must still name the same file (device and inode), else it is looked up anew
    (a moved link or a rebuilt file at the link's target gets its own real path)."""
    env = os.environ.get(ENVIRONMENT) if path is None else None
    named = path if path is not None else env
    key = (None if path is None else os.fspath(path), env,
           None if named is not None and os.path.isabs(named) else os.getcwd())
    hit = _FOUND.get(key)
    if hit is not None and _file_id(hit[0]) == hit[1]:
        return _load(hit[2])
    resolved = library_path(path)
    if not resolved.is_file():
        raise LibraryError(f"the C kernels' library {resolved} does not exist: build it with "
                           "`make lib` (it compiles generated_c/; no Python needed)")
    real = str(resolved.resolve())
    found = _file_id(str(resolved))
    if found is not None and found == _file_id(real):
        _FOUND[key] = (str(resolved), found, real)
    return _load(real)


class Library:
    """``libcochlea.so``: its manifest, and kernels bound to buffers on request."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        try:
            self._cdll = ctypes.CDLL(str(self.path))
        except OSError as exc:
            raise LibraryError(f"cannot load {self.path}: {exc}; rebuild it with `make lib`") \
                from exc
        try:
            manifest = self._cdll.cochlea_manifest
        except AttributeError as exc:
            raise LibraryError(f"{self.path} has no cochlea_manifest(): not a cochlea kernel "
                               "library") from exc
        manifest.argtypes, manifest.restype = [], ctypes.c_char_p
        self.manifest = json.loads(manifest().decode())
        if self.manifest.get("format") != MANIFEST_FORMAT:
            raise LibraryError(f"{self.path}: manifest format {self.manifest.get('format')!r},"
                               f" expected {MANIFEST_FORMAT!r}: rebuild with `make lib`")
        self._signatures: dict[str, Signature] = {}
        self._functions: dict[str, ctypes._CFuncPtr] = {}
        self._closed_loops: dict[str, ClosedLoop] = {}

    @property
    def names(self) -> tuple[str, ...]:
        """Every kernel in the library, aliases included."""
        return tuple(self.manifest["kernels"])

    @property
    def closed_loops(self) -> tuple[str, ...]:
        return tuple(self.manifest["closed_loops"])

    def source_hash(self, name: str) -> str:
        """SHA-256 of the CasADi Function ``name`` was generated from (see codegen)."""
        return self._entry(name)["sha256"]

    def _entry(self, name: str) -> dict:
        try:
            return self.manifest["kernels"][name]
        except KeyError:
            raise LibraryError(f"{self.path} has no kernel {name!r}; it has "
                               + ", ".join(self.names)) from None

    def symbol(self, name: str) -> str:
        """The C function kernel ``name`` runs: its own, or, for an alias (a kernel computing
        exactly what an earlier one does), that kernel's."""
        return self._entry(name).get("symbol", name)

    def _symbol(self, name: str, restype, argtypes):
        try:
            f = getattr(self._cdll, name)
        except AttributeError:
            raise LibraryError(f"{self.path} has no symbol {name!r}: rebuild with "
                               "`make lib`") from None
        f.restype, f.argtypes = restype, argtypes
        return f

    def function(self, name: str):
        """The raw ctypes function of kernel ``name``, its argtypes and restype declared."""
        if name not in self._functions:
            self._functions[name] = self._symbol(self.symbol(name), ctypes.c_int,
                                                 KERNEL_ARGTYPES)
        return self._functions[name]

    def signature(self, name: str) -> Signature:
        """The kernel's signature, read from the library's CasADi metadata functions."""
        if name in self._signatures:
            return self._signatures[name]
        c = self.symbol(name)
        n_in = self._symbol(f"{c}_n_in", _int, [])()
        n_out = self._symbol(f"{c}_n_out", _int, [])()
        name_in = self._symbol(f"{c}_name_in", ctypes.c_char_p, [_int])
        name_out = self._symbol(f"{c}_name_out", ctypes.c_char_p, [_int])
        sp_in = self._symbol(f"{c}_sparsity_in", ctypes.POINTER(_int), [_int])
        sp_out = self._symbol(f"{c}_sparsity_out", ctypes.POINTER(_int), [_int])
        work = self._symbol(f"{c}_work", ctypes.c_int, [ctypes.POINTER(_int)] * 4)

        def argument(label, sparsity, i) -> Argument:
            sp = sparsity(i)
            rows, cols = sp[0], sp[1]
            dense = sp[2] == 1 or sp[2 + cols] == rows * cols  # compact dense, or full CCS
            if not dense:
                raise LibraryError(f"{name}: argument {label(i).decode()} is sparse; cochlea's "
                                   "kernels are dense: regenerate with cochlea-codegen")
            return Argument(label(i).decode(), rows, cols)

        sizes = [_int() for _ in range(4)]
        if work(*[ctypes.byref(s) for s in sizes]):
            raise LibraryError(f"{name}_work failed")
        sig = Signature(name, tuple(argument(name_in, sp_in, i) for i in range(n_in)),
                        tuple(argument(name_out, sp_out, i) for i in range(n_out)),
                        *(s.value for s in sizes))
        expected = self._entry(name)
        for key, args in (("inputs", sig.inputs), ("outputs", sig.outputs)):
            listed = [(a["name"], a["rows"], a["cols"]) for a in expected[key]]
            if listed != [(a.name, a.rows, a.cols) for a in args]:
                raise LibraryError(f"{name}: the library's {key} disagree with its manifest: "
                                   "rebuild with `make lib`")
        self._signatures[name] = sig
        return sig

    def kernel(self, name: str, **buffers: np.ndarray) -> Kernel:
        """Bind kernel ``name``; keyword arguments supply the caller's own buffers by
        argument name (checked here, then used in place), the rest are allocated."""
        return Kernel(self.function(name), self.signature(name), buffers)

    def closed_loop(self, name: str) -> ClosedLoop:
        """Bind the generated closed-loop driver ``name`` (see generated_c/README.md): once
        per library and name (a driver keeps nothing of a run; a sweep runs one every
        sample)."""
        loop = self._closed_loops.get(name)
        if loop is None:
            loop = self._closed_loops[name] = self._bind_closed_loop(name)
        return loop

    def _bind_closed_loop(self, name: str) -> ClosedLoop:
        try:
            meta = self.manifest["closed_loops"][name]
        except KeyError:
            raise LibraryError(f"{self.path} has no closed loop {name!r}; it has "
                               + ", ".join(self.closed_loops)) from None
        pointer = ctypes.c_void_p
        argtypes = ([_int, _int] + [pointer] * 11 + [ctypes.c_double, ctypes.c_double]
                    + [pointer] * 10 + [_int, pointer, pointer] + [pointer] * 5
                    + [ctypes.POINTER(_int), pointer])
        # An alias runs the driver that makes the same kernel calls.
        return ClosedLoop(name, meta, self._symbol(meta.get("symbol", name), ctypes.c_int,
                                                   argtypes))


def _check_buffer(kernel: str, arg: Argument, array: np.ndarray, output: bool) -> None:
    what = f"{kernel}: buffer for {'output' if output else 'input'} {arg.name!r}"
    if not isinstance(array, np.ndarray):
        raise KernelError(f"{what} must be a numpy array, got {type(array).__name__}")
    if array.dtype != np.float64:
        raise KernelError(f"{what} must have dtype float64, got {array.dtype}")
    if array.shape != arg.shape:
        raise KernelError(f"{what} must have shape {arg.shape}, got {array.shape}")
    if not array.flags.f_contiguous or not array.flags.aligned:
        raise KernelError(f"{what} must be contiguous in column-major (Fortran) order")
    if output and not array.flags.writeable:
        raise KernelError(f"{what} must be writeable")


class Kernel:
    """One kernel bound to its buffers. ``kernel()`` runs it on the buffers' current values.

    ``kernel[name]`` is the buffer of input or output ``name`` (a numpy array the C code reads
    or writes in place); ``kernel.inputs`` and ``kernel.outputs`` map names to buffers in order.
    """

    def __init__(self, function, signature: Signature, buffers: dict[str, np.ndarray]):
        self.signature = signature
        self.name = signature.name
        known = {a.name for a in signature.inputs + signature.outputs}
        unknown = sorted(set(buffers) - known)
        if unknown:
            raise KernelError(f"{self.name} has no argument {', '.join(unknown)}; its arguments "
                              f"are {', '.join(a.name for a in signature.inputs)} -> "
                              f"{', '.join(a.name for a in signature.outputs)}")

        def bind(args, output):
            bound = {}
            for a in args:
                array = buffers.get(a.name)
                if array is None:
                    array = np.zeros(a.shape, order="F")
                _check_buffer(self.name, a, array, output)
                bound[a.name] = array
            return bound

        self.inputs = bind(signature.inputs, False)
        self.outputs = bind(signature.outputs, True)
        self._arg = (ctypes.c_void_p * max(signature.sz_arg, len(self.inputs)))(
            *[a.ctypes.data for a in self.inputs.values()])
        self._res = (ctypes.c_void_p * max(signature.sz_res, len(self.outputs)))(
            *[a.ctypes.data for a in self.outputs.values()])
        self._iw = (_int * signature.sz_iw)() if signature.sz_iw else None
        self._w = (ctypes.c_double * signature.sz_w)() if signature.sz_w else None
        #: The bare call: returns the kernel's code (0 on success), checks nothing.
        self.call = functools.partial(function, self._arg, self._res, self._iw, self._w, 0)

    def __call__(self) -> None:
        if self.call():
            raise KernelError(f"{self.name} returned a nonzero code")

    def __getitem__(self, name: str) -> np.ndarray:
        if name in self.inputs:
            return self.inputs[name]
        try:
            return self.outputs[name]
        except KeyError:
            raise KeyError(f"{self.name} has no argument {name!r}") from None

    def evaluate(self, *args, **kwargs) -> tuple[np.ndarray, ...]:
        """Convenience for tests and one-off calls (it copies): set the inputs from ``args``
        (in order) and ``kwargs`` (by name), run, return copies of the outputs."""
        for a, value in zip(self.signature.inputs, args):
            self.inputs[a.name][...] = np.reshape(value, a.shape, order="F")
        for name, value in kwargs.items():
            a = next(x for x in self.signature.inputs if x.name == name)
            self.inputs[name][...] = np.reshape(value, a.shape, order="F")
        self()
        return tuple(out.copy() for out in self.outputs.values())

    def __repr__(self) -> str:
        def fmt(args):
            return ", ".join(f"{a.name}[{a.rows}x{a.cols}]" for a in args)

        return f"<Kernel {self.name}({fmt(self.signature.inputs)}) -> " \
               f"({fmt(self.signature.outputs)})>"


@dataclass
class ClosedLoopLog:
    """What a closed-loop run writes: one row per period (row-major), ``rows`` filled."""

    rows: int
    x: np.ndarray  # (N, 2 nq) true state [q, qd] at the start of each period
    p_hat: np.ndarray  # (N, np) estimate used in the period
    tau: np.ndarray  # (N, nq)
    errors: np.ndarray  # (N, ne)
    pose: np.ndarray  # (N, npose)
    #: Rows in front of ``x`` in its buffer ``padded`` (``ClosedLoop.run``'s ``lead``; ``x``
    #: is ``padded[lead:]``), each a copy of its first row once the run logged one:
    #: :meth:`delayed` reads them.
    lead: int = 0
    padded: np.ndarray | None = None
    #: What the driver gathered of the ``rows`` written (``ClosedLoop.run``'s ``reductions``;
    #: None when not asked for): :class:`LoopReductions`.
    reductions: LoopReductions | None = None

    def delayed(self, delay: int, rows: int) -> np.ndarray | None:
        """The first ``rows`` logged states each ``delay`` periods earlier (the first state
        before the first period): ``x[max(k - delay, 0)]`` for row k, the same values as that
        gather, as a read-only view of the log's buffer without a copy; None when the buffer
        has fewer than ``delay`` rows in front."""
        if not 0 <= delay <= self.lead or not 0 < rows <= len(self.x) or self.padded is None:
            return None
        view = self.padded[self.lead - delay:self.lead - delay + rows]
        view.flags.writeable = False
        return view


@dataclass(frozen=True)
class LoopReductions:
    """What a closed-loop driver gathers of the rows it writes, while each value is at hand
    (generated_c/README.md): the verdict's and the summary's reads of the logs without a
    second pass over them. A NaN in a column makes both its extremes NaN."""

    rows: int  # the rows these describe
    state_low: np.ndarray  # (2 nq,) each measured state column's minimum ([q, qd], SI)
    state_high: np.ndarray  # and maximum
    tau_low: np.ndarray  # (nq,) each applied effort column's minimum
    tau_high: np.ndarray  # and maximum
    #: The largest sum of squares of a logged estimate row, its columns added in order: over
    #: every row, and over the rows after the first (the first alone when it is the only one).
    square_all: float
    square_later: float
    #: The smallest squared distance (m^2) of a keep-out tool point to its centre over the
    #: rows' logged poses (the true state's); +inf without a tool point.
    keep_out_nearest: float

    @classmethod
    def unpack(cls, values: np.ndarray, nq: int, rows: int) -> LoopReductions:
        nx = 2 * nq
        return cls(rows, values[:nx], values[nx:2 * nx], values[2 * nx:2 * nx + nq],
                   values[2 * nx + nq:2 * nx + 2 * nq], float(values[-3]), float(values[-2]),
                   float(values[-1]))


class ClosedLoop:
    """A generated closed-loop driver: N periods of controller, update and plant in C."""

    def __init__(self, name: str, meta: dict, function):
        self.name, self.meta, self._fn = name, meta, function
        self.nq, self.n_params = meta["nq"], meta["n_params"]
        self.n_desired, self.n_errors, self.n_pose = (meta["n_desired"], meta["n_errors"],
                                                      meta["n_pose"])
        self.n_plant_params, self.n_gains = meta["n_plant_params"], meta["n_gains"]
        #: The plant's state size (``2 nq``, or ``4 nq`` on the geared plant) and the size of
        #: its 6th input (``drive``).
        self.nx = meta.get("nx", 2 * self.nq)
        self.n_drive = meta.get("n_drive", self.nq)
        self.n_reductions = meta["n_reductions"]

    def _array(self, label: str, value, shape: tuple[int, ...]) -> np.ndarray:
        array = np.ascontiguousarray(value, dtype=np.float64)
        if array.shape != shape:
            raise KernelError(f"{self.name}: {label} must have shape {shape}, got "
                              f"{array.shape}")
        return array

    def _keep_out(self, points) -> tuple[np.ndarray, np.ndarray]:
        """``run``'s ``keep_out`` as the driver reads it, each index checked: the driver
        reads the pose and state rows at them."""
        index, centre = [], []
        for point in points:
            try:
                u, v, joint, cu, cv = point
            except (TypeError, ValueError):
                raise KernelError(f"{self.name}: a keep-out point is (u, v, joint, centre_u, "
                                  f"centre_v), got {point!r}") from None
            for label, value, low, size in (("u", u, 0, self.n_pose), ("v", v, 0, self.n_pose),
                                            ("joint", -1 if joint is None else joint, -1,
                                             self.nq)):
                if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or \
                        not low <= value < size:
                    raise KernelError(f"{self.name}: a keep-out point's {label} must be a "
                                      f"whole index below {size}, got {value!r}")
            index += [int(u), int(v), -1 if joint is None else int(joint)]
            centre += [float(cu), float(cv)]
        return (np.array(index, dtype=np.int64).reshape(-1, 3),
                np.array(centre, dtype=np.float64).reshape(-1, 2))

    def run(self, n: int, *, x0, p_hat0, xd, xd_dot, xd_ddot, gains, Gamma, bound: float,
            h: float, plant_p, friction, noise=None, delay: int = 0, quantum=None,
            offset=None, effort_limit=None, coulomb=None, effort_quantum=None,
            effort_bound=None, effort_offset=None, effort_ramp=None,
            robust=None, delays=None, torque_scale=None, lead: int = 0,
            reductions: bool = False, keep_out=()) -> ClosedLoopLog:
        """Run ``n`` periods; every array is checked and converted once, before the call.
        ``x0`` is the plant's initial state (``nx``); ``coulomb`` its 6th input (``n_drive``
        values: the dry friction's rows, or the gear plant's drive). ``effort_quantum`` and
        ``effort_bound`` (nq each; the bound defaults to no bound) put the applied efforts on
        the drives' grid, ``effort_offset`` and ``effort_ramp`` (nq each) add the bridge's
        offset before it (see generated_c/README.md). The log holds ``[q, qd]``. ``robust``:
        the controller's robust options (:data:`cochlea.control.controllers.ROBUST_INPUTS`, in
        that order; default: the neutral ones). ``delays`` (n whole periods, each >= 0): each
        period's own delay, instead of ``delay`` (the jittering delay). ``torque_scale`` (nq):
        the plant gets the applied efforts times it (the motors' torque-constant error); the
        log keeps the applied efforts. ``lead``: rows the state log's buffer holds in front of
        it, each the first logged state after the run (:meth:`ClosedLoopLog.delayed`).
        ``reductions``: the log also holds what the driver gathered of its rows
        (:class:`LoopReductions`), the nearest approach of the ``keep_out`` tool points among
        them: each ``(u, v, joint, centre_u, centre_v)``, the pose columns of the point, the
        joint whose position is its centre's v (None: the centre is fixed, at ``(centre_u,
        centre_v)``)."""
        nq, nd = self.nq, self.n_desired
        if robust is None:
            robust = (np.zeros(nq), np.full(self.n_params, -np.inf),
                      np.full(self.n_params, np.inf), np.zeros(nq), np.ones(nq))
        robust = self._array("robust", np.concatenate([np.ravel(r) for r in robust]),
                             (3 * nq + 2 * self.n_params,))
        ins = {
            "x0": self._array("x0", x0, (self.nx,)),
            "p_hat0": self._array("p_hat0", p_hat0, (self.n_params,)),
            "xd": self._array("xd", xd, (n, nd)),
            "xd_dot": self._array("xd_dot", xd_dot, (n, nd)),
            "xd_ddot": self._array("xd_ddot", xd_ddot, (n, nd)),
            "gains": self._array("gains", gains, (self.n_gains,)),
            "Gamma": self._array("Gamma", Gamma, (self.n_params,)),
            "plant_p": self._array("plant_p", plant_p, (self.n_plant_params,)),
            "friction": self._array("friction", friction, (nq,)),
        }
        noise = None if noise is None else self._array("noise", noise, (n, 2 * nq))
        if quantum is not None:  # the measurement grid; the offset defaults to zero
            quantum = self._array("quantum", quantum, (2 * nq,))
            offset = self._array("offset", np.zeros(2 * nq) if offset is None else offset,
                                 (2 * nq,))
        if effort_limit is not None:
            effort_limit = self._array("effort_limit", effort_limit, (nq,))
        if coulomb is not None:  # read by a driver whose plant has a 6th input
            coulomb = self._array("coulomb", coulomb, (self.n_drive,))
        if effort_quantum is not None:
            effort_quantum = self._array("effort_quantum", effort_quantum, (nq,))
            effort_bound = self._array("effort_bound", np.full(nq, np.inf) if effort_bound
                                       is None else effort_bound, (nq,))
        if effort_offset is not None:
            effort_offset = self._array("effort_offset", effort_offset, (nq,))
            effort_ramp = self._array("effort_ramp", effort_ramp, (nq,))
        if torque_scale is not None:
            torque_scale = self._array("torque_scale", torque_scale, (nq,))
        if delay < 0:
            raise KernelError(f"{self.name}: the delay must be >= 0 periods, got {delay}")
        if delays is not None:
            delays = np.ascontiguousarray(delays, dtype=np.int64)
            if delays.shape != (n,) or (n and delays.min() < 0):
                raise KernelError(f"{self.name}: delays must be {n} whole periods, each >= 0")
        if not isinstance(lead, int) or isinstance(lead, bool) or lead < 0:
            raise KernelError(f"{self.name}: lead must be whole rows, >= 0, got {lead!r}")
        states = np.empty((n + lead, 2 * nq))
        log = ClosedLoopLog(0, states[lead:] if lead else states, np.empty((n, self.n_params)),
                            np.empty((n, nq)), np.empty((n, self.n_errors)),
                            np.empty((n, self.n_pose)), lead, states)
        index, centre = self._keep_out(keep_out)
        rows = _int(0)
        gathered = np.empty(self.n_reductions) if reductions else None
        flag = self._fn(n, delay, None if delays is None else delays.ctypes.data,
                        ins["x0"].ctypes.data, ins["p_hat0"].ctypes.data,
                        ins["xd"].ctypes.data, ins["xd_dot"].ctypes.data,
                        ins["xd_ddot"].ctypes.data, None if noise is None else noise.ctypes.data,
                        None if quantum is None else quantum.ctypes.data,
                        None if quantum is None else offset.ctypes.data,
                        ins["gains"].ctypes.data, ins["Gamma"].ctypes.data, float(bound),
                        float(h), robust.ctypes.data, ins["plant_p"].ctypes.data,
                        ins["friction"].ctypes.data,
                        None if coulomb is None else coulomb.ctypes.data,
                        None if effort_limit is None else effort_limit.ctypes.data,
                        None if effort_quantum is None else effort_quantum.ctypes.data,
                        None if effort_quantum is None else effort_bound.ctypes.data,
                        None if effort_offset is None else effort_offset.ctypes.data,
                        None if effort_offset is None else effort_ramp.ctypes.data,
                        None if torque_scale is None else torque_scale.ctypes.data,
                        len(centre), index.ctypes.data, centre.ctypes.data,
                        log.x.ctypes.data, log.p_hat.ctypes.data, log.tau.ctypes.data,
                        log.errors.ctypes.data, log.pose.ctypes.data, ctypes.byref(rows),
                        None if gathered is None else gathered.ctypes.data)
        if flag:
            raise KernelError(f"{self.name}: a kernel returned code {flag}")
        log.rows = rows.value
        if gathered is not None:
            log.reductions = LoopReductions.unpack(gathered, nq, log.rows)
        if lead and log.rows:
            states[:lead] = log.x[0]
        return log
