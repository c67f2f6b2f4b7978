"""CuPy's user kernels for the CPU emulator (``tests/emulated_cupy.py``): the CUDA C++ bodies of
``ElementwiseKernel`` and ``ReductionKernel`` compiled by the host's C++ compiler.

The package's CUDA kernels (``pwf_dask.pwf.kernels._CUDA_KERNELS``, ``pwf_dask.tomo.tomography.
BACKPROJECT_KERNEL``) are plain C++ inside a loop over the output elements: here each body is
put inside that loop, one iteration where CUDA runs one thread, compiled once per signature into a
shared library and called through ctypes on the emulated arrays' NumPy buffers. Types follow
CuPy's: a placeholder (``T``) takes its argument's dtype, complex numbers are ``complex<float>``
(``std::complex`` here, with the same ``real()``, ``imag()`` and ``conj``), reductions run their
``map_expr``, ``reduce_expr`` and ``post_map_expr`` in order over the reduced axis (CuPy's order
is a tree: sums agree to rounding). What this does not check is CUDA's own: NVRTC's compilation,
launch sizes, CuPy's renaming of a reduction's single operand (``_CUDA_KERNELS``' note); a
device run still does. Available where a C++ compiler is (:func:`available`).
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path

import numpy as np

#: C++ types of the dtypes a kernel may name
CTYPES = {
    "bool": "bool",
    "int32": "int",
    "int64": "long long",
    "float32": "float",
    "float64": "double",
    "complex64": "complex<float>",
    "complex128": "complex<double>",
}

PREAMBLE = """#include <cmath>
#include <complex>
template <typename F> using complex = std::complex<F>;
using std::conj;
// one thread at a time here: CUDA's atomic addition is the plain one
template <typename T> inline T atomicAdd(T* address, T value) {
    const T old = *address;
    *address = old + value;
    return old;
}
"""

#: compiled kernels, shared by the processes of a test run (a library is written under a
#: name of its own and renamed into place, so two processes may build the same one at once)
_BUILD = Path(tempfile.gettempdir()) / f"pwf-emulated-kernels-{os.getuid()}"
_LIBRARIES: dict[str, ctypes.CDLL] = {}


def compiler() -> str | None:
    return shutil.which("g++") or shutil.which("c++") or shutil.which("clang++")


def available() -> bool:
    return compiler() is not None


def _params(spec: str) -> list[tuple[bool, str, str]]:
    """(raw, type, name) of each comma-separated parameter of a kernel's argument list."""
    out = []
    for part in spec.split(","):
        words = part.split()
        raw = words[0] == "raw"
        out.append((raw, words[-2], words[-1]))
    return out


def _compile(source: str) -> ctypes.CDLL:
    key = hashlib.sha1(source.encode()).hexdigest()[:16]
    if key not in _LIBRARIES:
        lib = _BUILD / f"{key}.so"
        if not lib.exists():
            _BUILD.mkdir(exist_ok=True)
            own = f"{key}.{os.getpid()}.{threading.get_ident()}"
            src, tmp = _BUILD / f"{own}.cpp", _BUILD / f"{own}.so"
            src.write_text(source)
            subprocess.run([compiler(), "-O2", "-std=c++14", "-shared", "-fPIC", str(src), "-o", str(tmp)], check=True)
            os.replace(tmp, lib)
            src.unlink()
        _LIBRARIES[key] = ctypes.CDLL(str(lib))
    return _LIBRARIES[key]


class _Call:
    """One call's operands: placeholders bound to dtypes, every operand a contiguous NumPy array
    (scalars as 0-d arrays of their parameter's type)."""

    def __init__(self, params, args, unwrap):
        self.types: dict[str, np.dtype] = {}
        values = [unwrap(a) for a in args]
        for (_, typ, _), value in zip(params, values):
            if typ not in CTYPES and isinstance(value, (np.ndarray, np.generic)):
                self.types.setdefault(typ, np.asarray(value).dtype)
        self.arrays = []
        for (_, typ, name), value in zip(params, values):
            dtype = self.dtype(typ)
            if isinstance(value, np.ndarray) and value.ndim > 0:
                if value.dtype != dtype:
                    raise TypeError(f"{name}: {value.dtype} where the kernel takes {dtype}")
                self.arrays.append(value)
            else:
                self.arrays.append(np.asarray(value, dtype=dtype))

    def dtype(self, typ: str) -> np.dtype:
        return np.dtype(typ) if typ in CTYPES else self.types[typ]

    def ctype(self, typ: str) -> str:
        return CTYPES[self.dtype(typ).name]

    def pointers(self):
        held = [np.ascontiguousarray(a) for a in self.arrays]
        return held, (ctypes.c_void_p * len(held))(*[a.ctypes.data for a in held])


def _declarations(params, call: _Call, size_name: str) -> tuple[str, str]:
    """(before the loop, at each element i) declarations of the parameters."""
    before, each = [], []
    for k, (raw, typ, name) in enumerate(params):
        ct = call.ctype(typ)
        array = call.arrays[k]
        if raw:
            before.append(f"{ct}* {name} = ({ct}*)_args[{k}];")
        elif array.ndim == 0:
            before.append(f"const {ct} {name} = *({ct}*)_args[{k}];")
        else:
            before.append(f"{ct}* _{name} = ({ct}*)_args[{k}];")
            each.append(f"{ct}& {name} = _{name}[{size_name}];")
    return "\n".join(before), "\n".join(each)


def _typedefs(call: _Call) -> str:
    return "\n".join(f"typedef {CTYPES[d.name]} {t};" for t, d in call.types.items())


class ElementwiseKernel:
    """``cupy.ElementwiseKernel`` for the emulator: ``operation`` in a loop over ``i``."""

    def __init__(self, in_params, out_params, operation, name="kernel", **kwargs):
        self.ins, self.outs = _params(in_params), _params(out_params)
        self.operation, self.name = operation, name

    def __call__(self, *args, wrap, unwrap):
        ins = args[: len(self.ins)]
        call = _Call(self.ins, ins, unwrap)
        shapes = [a.shape for (raw, _, _), a in zip(self.ins, call.arrays) if not raw and a.ndim > 0]
        outs = list(args[len(self.ins) :])
        if not outs:
            shape = np.broadcast_shapes(*shapes)
            outs = [wrap(np.empty(shape, call.dtype(typ))) for _, typ, _ in self.outs]
        out_arrays = [unwrap(o) for o in outs]
        # as CuPy: the loop runs over the non-raw operands, outputs first (a raw output, such as
        # a grid written by atomic additions, takes the size of the non-raw inputs)
        sized = [a for (raw, _, _), a in zip(self.outs, out_arrays) if not raw]
        size = sized[0].size if sized else int(np.prod(np.broadcast_shapes(*shapes)))
        for (raw, _, name), a in zip(self.ins, call.arrays):
            if not raw and a.ndim > 0 and a.size != size:
                raise ValueError(f"{name}: {a.shape} does not match the loop's {size} elements (no broadcasting here)")
        whole = _Call(self.ins + self.outs, [*ins, *outs], unwrap)
        before, each = _declarations(self.ins + self.outs, whole, "i")
        source = (
            f"{PREAMBLE}{_typedefs(whole)}\n"
            f'extern "C" void run(void** _args, long long _n) {{\n{before}\n'
            f"for (long long i = 0; i < _n; ++i) {{\n{each}\n{self.operation};\n}}\n}}\n"
        )
        held, pointers = whole.pointers()
        _compile(source).run(pointers, ctypes.c_longlong(size))
        for o, h in zip(out_arrays, held[len(self.ins) :]):
            if h is not o:
                o[...] = h
        return outs[0] if len(outs) == 1 else tuple(outs)


class ReductionKernel:
    """``cupy.ReductionKernel`` for the emulator: over all elements, or the last axis."""

    def __init__(
        self,
        in_params,
        out_params,
        map_expr,
        reduce_expr,
        post_map_expr,
        identity,
        name="reduce",
        reduce_type=None,
        **kwargs,
    ):
        self.ins, self.outs = _params(in_params), _params(out_params)
        self.map_expr, self.reduce_expr, self.post_map_expr = map_expr, reduce_expr, post_map_expr
        self.identity, self.name, self.reduce_type = identity, name, reduce_type

    def __call__(self, *args, axis=None, wrap, unwrap):
        call = _Call(self.ins, args, unwrap)
        shape = next(a.shape for a in call.arrays if a.ndim > 0)
        if axis is None:
            out_shape, n_reduce = (), int(np.prod(shape))
        elif axis in (-1, len(shape) - 1):
            out_shape, n_reduce = shape[:-1], shape[-1]
        else:
            raise NotImplementedError("the emulator reduces over all axes or the last one")
        out = np.empty(out_shape, call.dtype(self.outs[0][1]))
        whole = _Call(self.ins + self.outs, [*args, wrap(out)], unwrap)
        whole.arrays[-1] = out
        before, each = _declarations(self.ins, whole, "i")
        _, out_type, out_name = self.outs[0]
        reduce_type = CTYPES[np.dtype(self.reduce_type or out.dtype).name]
        source = (
            f"{PREAMBLE}{_typedefs(whole)}\n"
            f'extern "C" void run(void** _args, long long _n_out, long long _n_reduce) {{\n{before}\n'
            f"{whole.ctype(out_type)}* _{out_name} = ({whole.ctype(out_type)}*)_args[{len(self.ins)}];\n"
            f"for (long long _o = 0; _o < _n_out; ++_o) {{\n"
            f"{reduce_type} a = {reduce_type}({self.identity});\n"
            f"for (long long _j = 0; _j < _n_reduce; ++_j) {{\nconst long long i = _o * _n_reduce + _j;\n{each}\n"
            f"const {reduce_type} b = {reduce_type}({self.map_expr});\na = {self.reduce_expr};\n}}\n"
            f"{whole.ctype(out_type)}& {out_name} = _{out_name}[_o];\n{self.post_map_expr};\n}}\n}}\n"
        )
        held, pointers = whole.pointers()
        _compile(source).run(pointers, ctypes.c_longlong(max(out.size, 1)), ctypes.c_longlong(n_reduce))
        out[...] = held[-1].reshape(out.shape)
        return wrap(out)
