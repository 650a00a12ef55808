"""One calling convention for a kernel, whether CasADi or generated C runs it.

``inputs[i]`` and ``outputs[j]`` are flat float64 arrays bound once; fill the inputs in place,
call, read the outputs in place: nothing is allocated or converted per call, which is what the
1 kHz loop and the simulation's Python loop need.
"""

from __future__ import annotations

import casadi as ca
import numpy as np


class BufferedFunction:
    """A CasADi Function called through preallocated numpy buffers (no allocation per call)."""

    def __init__(self, f: ca.Function):
        self.function = f
        self.inputs = [np.zeros(f.nnz_in(i)) for i in range(f.n_in())]
        self.outputs = [np.zeros(f.nnz_out(i)) for i in range(f.n_out())]
        self._buffer, self._trigger = f.buffer()
        for i, a in enumerate(self.inputs):
            self._buffer.set_arg(i, memoryview(a))
        for i, a in enumerate(self.outputs):
            self._buffer.set_res(i, memoryview(a))

    def __call__(self) -> None:
        self._trigger()


class BufferedKernel:
    """A generated C kernel (:meth:`cochlea.kernels.library.Library.kernel`) behind the same
    interface: ``inputs`` and ``outputs`` lists of the kernel's own buffers, in order, and a
    call. SX kernels cannot fail, so the call's return code is not checked in the period."""

    def __init__(self, kernel):
        self.kernel = kernel
        self.inputs = list(kernel.inputs.values())
        self.outputs = list(kernel.outputs.values())
        self._trigger = kernel.call

    def __call__(self) -> None:
        self._trigger()
