"""A CPU stand-in for CuPy, as strict as CuPy where mixing host and device arrays is concerned.

No GPU has been lent to most sessions of this project, so the CuPy branches of the numerics
(``xp is not np``, ``cupy.fft``, ``.get()``) would otherwise never run before a user's GPU
does. This module lets the GPU tests run on any machine: installed as ``sys.modules["cupy"]``,
it hands out :class:`ndarray` objects that hold a NumPy array but behave towards NumPy as a
CuPy array does (cupy/_core/core.pyx):

- implicit conversion to NumPy raises ``TypeError`` (``np.asarray(a)``, ``np.exp(a)``,
  ``scipy.ndimage.*(a)``): a host routine called on a device array is a bug on a GPU;
- arithmetic with a NumPy array of one or more dimensions raises ``TypeError``, and so does
  assigning one into a slice (CuPy's default, without ``CUPY_EXPERIMENTAL_SLICE_COPY``);
- reductions and scalar indexing return 0-d arrays, which convert with ``float()``;
- ``fft`` keeps single precision (cupy.fft does, numpy.fft does not): it is ``scipy.fft``.
- ``cupyx.scipy.ndimage`` (:data:`NDIMAGE`) is SciPy's on the wrapped arrays;
- ``ElementwiseKernel`` and ``ReductionKernel`` compile their CUDA bodies as C++ with the host's
  compiler (``tests/emulated_kernels.py``), so the package's CUDA kernels run here too.

Functions are NumPy's with arrays unwrapped and results wrapped; only the names CuPy also
has are offered (:data:`FUNCTIONS`), so code that needs a NumPy-only routine fails here as
it would on a GPU. Numbers are NumPy's, so results equal the NumPy path's up to rounding.
"""

from __future__ import annotations

import operator
import sys
import threading
import types
from contextlib import contextmanager

import numpy as np
import scipy.fft

_MIXING = "Unsupported type <class 'numpy.ndarray'>"

#: device-to-host transfers so far: every ``get()``, ``item()``, ``tolist()``, ``float()``,
#: ``complex()``, ``int()``, ``bool()`` or format of a device array (a CUDA synchronisation
#: and a copy each on a GPU); tests of the solver's round trips per iteration read it
transfers = 0


def _fetched(a: np.ndarray) -> np.ndarray:
    global transfers
    transfers += 1
    return a


#: NumPy functions CuPy provides under the same name (those the package may reach for)
FUNCTIONS = (
    "abs absolute all allclose amax amin angle any arange arccos arcsin arctan arctan2 argmax argmin "
    "argsort around array_equal asarray ascontiguousarray atleast_1d atleast_2d broadcast_to ceil "
    "clip concatenate conj conjugate copy cos cosh count_nonzero cumsum deg2rad diag diff divide dot "
    "einsum empty empty_like exp expand_dims eye flip floor full full_like gradient hypot imag "
    "indices isfinite isnan linspace log log10 log1p logical_and logical_not logical_or matmul "
    "max maximum mean median meshgrid min minimum moveaxis multiply nanmean nanmedian nonzero ones "
    "ones_like outer pad percentile power prod ptp quantile rad2deg repeat ravel real reshape rint roll round sign "
    "sin sinh sort sqrt square squeeze stack std subtract sum swapaxes take tan tanh tensordot tile "
    "trace transpose tril triu unique var vdot vstack hstack where zeros zeros_like"
).split()

#: dtypes and constants CuPy re-exports from NumPy
CONSTANTS = (
    "bool_ float16 float32 float64 complex64 complex128 int8 int16 int32 int64 uint8 uint16 "
    "uint32 uint64 intp dtype finfo iinfo pi e inf nan newaxis"
).split()


def _unwrap(x, allow_host: bool = False):
    if isinstance(x, ndarray):
        return x._a
    if isinstance(x, np.ndarray) and x.ndim > 0 and not allow_host:
        raise TypeError(_MIXING)
    if isinstance(x, (list, tuple)):
        return type(x)(_unwrap(v, allow_host) for v in x)
    if isinstance(x, dict):
        return {k: _unwrap(v, allow_host) for k, v in x.items()}
    return x


def _wrap(x):
    if isinstance(x, np.ndarray):
        return ndarray(x)
    if isinstance(x, np.generic):
        return ndarray(np.asarray(x))
    if isinstance(x, tuple):
        return tuple(_wrap(v) for v in x)
    if isinstance(x, list):
        return [_wrap(v) for v in x]
    return x


def _device(fn, allow_host: bool = False):
    """``fn`` on unwrapped arguments, its arrays wrapped back as device arrays."""

    def call(*args, **kwargs):
        return _wrap(fn(*_unwrap(args, allow_host), **_unwrap(kwargs, allow_host)))

    call.__name__ = getattr(fn, "__name__", "function")
    return call


class ndarray:  # noqa: N801 (CuPy's name)
    """A device array: a NumPy array that refuses to be treated as one."""

    __slots__ = ("_a",)
    __module__ = "cupy"  # what pwf_dask.backend.get_array_module recognises    __array_priority__ = 100
    #: numpy ufuncs and array functions on this type raise (as with a CUDA pointer)
    __array_ufunc__ = None

    def __init__(self, a: np.ndarray):
        object.__setattr__(self, "_a", a)

    def __array__(self, *args, **kwargs):
        raise TypeError(
            "Implicit conversion to a NumPy array is not allowed. "
            "Please use `.get()` to construct a NumPy array explicitly."
        )

    def __array_function__(self, func, types, args, kwargs):
        raise TypeError(f"numpy.{func.__name__} on a device array: use the cupy function")

    # conversion
    def get(self):
        return _fetched(self._a).copy()

    def item(self):
        return _fetched(self._a).item()

    def tolist(self):
        return _fetched(self._a).tolist()

    def __float__(self):
        return float(_fetched(self._a))

    def __int__(self):
        return int(_fetched(self._a))

    def __complex__(self):
        return complex(_fetched(self._a))

    def __bool__(self):
        return bool(_fetched(self._a))

    def __index__(self):
        return operator.index(_fetched(self._a).item())

    def __format__(self, spec):
        return format(_fetched(self._a).item() if self._a.ndim == 0 else self._a, spec)

    def __repr__(self):
        return f"emulated_cupy.{self._a!r}"

    def __len__(self):
        return len(self._a)

    def __iter__(self):
        return (self[i] for i in range(len(self)))

    # attributes
    shape = property(lambda self: self._a.shape)
    dtype = property(lambda self: self._a.dtype)
    ndim = property(lambda self: self._a.ndim)
    size = property(lambda self: self._a.size)
    nbytes = property(lambda self: self._a.nbytes)
    itemsize = property(lambda self: self._a.itemsize)
    strides = property(lambda self: self._a.strides)
    flags = property(lambda self: self._a.flags)
    T = property(lambda self: ndarray(self._a.T))

    @property
    def real(self):
        return ndarray(self._a.real)

    @real.setter
    def real(self, value):
        self._a.real = _unwrap(value)

    @property
    def imag(self):
        return ndarray(self._a.imag)

    @imag.setter
    def imag(self, value):
        self._a.imag = _unwrap(value)

    def __getattr__(self, name):
        if name == "_a" or name.startswith("__"):
            # no __array_interface__ and the like: NumPy must not see the host buffer
            raise AttributeError(name)
        # methods (astype, copy, reshape, sum, conj, ...), NumPy's with arrays kept on device
        return _device(getattr(self._a, name))

    def __getitem__(self, key):
        return _wrap(self._a[_unwrap(key, allow_host=True)])

    def __setitem__(self, key, value):
        self._a[_unwrap(key, allow_host=True)] = _unwrap(value)

    def __copy__(self):
        return ndarray(self._a.copy())

    def __deepcopy__(self, memo):
        return ndarray(self._a.copy())

    def __reduce__(self):
        return (_from_host, (self._a,))


def _from_host(a):
    return ndarray(np.array(a))


def _binary(op, iop=None):
    def forward(self, other):
        return _wrap(op(self._a, _unwrap(other)))

    def backward(self, other):
        return _wrap(op(_unwrap(other), self._a))

    def inplace(self, other):
        # in place with NumPy's casting rules (a complex value into a float array fails)
        iop(self._a, _unwrap(other))
        return self

    return forward, backward, inplace


for _name, _op in {
    "add": operator.add,
    "sub": operator.sub,
    "mul": operator.mul,
    "truediv": operator.truediv,
    "floordiv": operator.floordiv,
    "mod": operator.mod,
    "pow": operator.pow,
    "matmul": operator.matmul,
    "and": operator.and_,
    "or": operator.or_,
    "xor": operator.xor,
}.items():
    _f, _b, _i = _binary(_op, getattr(operator, f"i{_name}"))
    setattr(ndarray, f"__{_name}__", _f)
    setattr(ndarray, f"__r{_name}__", _b)
    setattr(ndarray, f"__i{_name}__", _i)

for _name, _op in {
    "lt": operator.lt,
    "le": operator.le,
    "eq": operator.eq,
    "ne": operator.ne,
    "gt": operator.gt,
    "ge": operator.ge,
}.items():
    setattr(ndarray, f"__{_name}__", _binary(_op)[0])

ndarray.__neg__ = lambda self: ndarray(-self._a)
ndarray.__pos__ = lambda self: self
ndarray.__abs__ = lambda self: ndarray(np.abs(self._a))
ndarray.__invert__ = lambda self: ndarray(~self._a)
ndarray.__hash__ = None


def _module() -> types.ModuleType:
    cp = types.ModuleType("cupy", __doc__)
    cp.ndarray = ndarray
    for name in FUNCTIONS:
        if hasattr(np, name):
            setattr(cp, name, _device(getattr(np, name)))
    for name in CONSTANTS:
        setattr(cp, name, getattr(np, name))

    # creation from host data is the one place a NumPy array may go in; it is copied, as a
    # transfer to the device is, so that device code cannot write into the caller's array
    def asarray(a, dtype=None, order=None):
        if isinstance(a, ndarray):
            return ndarray(np.asarray(a._a, dtype=dtype, order=order))
        return ndarray(np.array(a, dtype=dtype, order=order, copy=True))

    cp.asarray = asarray
    cp.array = _device(np.array, allow_host=True)
    cp.asnumpy = lambda a: a.get() if isinstance(a, ndarray) else np.asarray(a)
    cp.get_array_module = lambda *arrays: cp if any(isinstance(a, ndarray) for a in arrays) else np

    fft = types.ModuleType("cupy.fft")
    for name in "fft ifft fft2 ifft2 fftn ifftn rfft irfft rfft2 irfft2 rfftn irfftn".split():
        setattr(fft, name, _device(getattr(scipy.fft, name)))
    for name in ("fftfreq", "rfftfreq", "fftshift", "ifftshift"):
        setattr(fft, name, _device(getattr(np.fft, name)))
    cp.fft = fft

    linalg = types.ModuleType("cupy.linalg")
    for name in ("norm", "solve", "lstsq", "inv", "eigh", "svd", "det"):
        setattr(linalg, name, _device(getattr(np.linalg, name)))
    cp.linalg = linalg

    class _Stream:
        """A stream is a context (the current stream of its thread) with a synchronize."""

        def __init__(self, non_blocking: bool = False):
            self.non_blocking = non_blocking

        def __enter__(self):
            _current.stack = [*getattr(_current, "stack", []), self]
            return self

        def __exit__(self, *exc):
            _current.stack = _current.stack[:-1]
            return False

        def synchronize(self):
            pass

    _current = threading.local()
    null = _Stream()

    class _Device:
        #: (free, total) bytes: a 16 GB card; tests set their own
        mem_info = (16 * 2**30, 16 * 2**30)

        def __init__(self, device_id: int = 0):
            self.id = device_id

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def use(self):
            pass

    cuda = types.ModuleType("cupy.cuda")
    cuda.runtime = types.SimpleNamespace(
        getDeviceCount=lambda: 1,
        getDeviceProperties=lambda device_id: {"name": b"emulated CuPy (NumPy on the CPU)"},
    )
    cuda.Device = _Device
    _Stream.null = null

    class _MemoryPool:
        """CuPy's pool of device memory: the host allocator holds nothing back."""

        def free_bytes(self):
            return 0

        def used_bytes(self):
            return 0

        def total_bytes(self):
            return 0

        def free_all_blocks(self):
            pass

    pool = _MemoryPool()
    cp.get_default_memory_pool = lambda: pool
    _user_kernels(cp)
    cuda.Stream = _Stream
    cuda.get_current_stream = lambda: (getattr(_current, "stack", None) or [null])[-1]
    cp.cuda = cuda
    return cp


def _kernel_operand(x):
    """A user kernel's operand as NumPy: a device array's buffer; a host array is refused, as
    CuPy refuses it."""
    if isinstance(x, ndarray):
        return x._a
    if isinstance(x, np.ndarray) and x.ndim > 0:
        raise TypeError(_MIXING)
    return x


def _user_kernels(cp) -> None:
    """``ElementwiseKernel`` and ``ReductionKernel``, their CUDA bodies compiled by the host's
    C++ compiler (``tests/emulated_kernels.py``), where one is found; without one the module has
    none, and the package's kernel paths (``backend.cuda_kernels``) stay off here."""
    import emulated_kernels

    if not emulated_kernels.available():
        return

    class ElementwiseKernel(emulated_kernels.ElementwiseKernel):
        def __call__(self, *args, **kwargs):
            return super().__call__(*args, wrap=_wrap, unwrap=_kernel_operand, **kwargs)

    class ReductionKernel(emulated_kernels.ReductionKernel):
        def __call__(self, *args, **kwargs):
            return super().__call__(*args, wrap=_wrap, unwrap=_kernel_operand, **kwargs)

    cp.ElementwiseKernel, cp.ReductionKernel = ElementwiseKernel, ReductionKernel


#: ``cupyx.scipy.ndimage`` routines the package calls (the same names and modes as SciPy's)
NDIMAGE = ("gaussian_filter", "binary_dilation", "distance_transform_edt")


def _cupyx() -> dict[str, types.ModuleType]:
    """``cupyx``, ``cupyx.scipy`` and ``cupyx.scipy.ndimage``: SciPy's filters on device arrays."""
    import scipy.ndimage

    cupyx = types.ModuleType("cupyx")
    cupyx.scipy = types.ModuleType("cupyx.scipy")
    cupyx.scipy.ndimage = types.ModuleType("cupyx.scipy.ndimage")
    for name in NDIMAGE:
        setattr(cupyx.scipy.ndimage, name, _device(getattr(scipy.ndimage, name)))
    dilation = cupyx.scipy.ndimage.binary_dilation

    def binary_dilation(input, structure=None, iterations=1, *args, brute_force=False, **kwargs):
        # cupyx/scipy/ndimage/_morphology.py: more than one iteration only by brute force
        if iterations != 1 and not brute_force:
            raise NotImplementedError("only brute_force iteration has been implemented")
        return dilation(input, structure, iterations, *args, brute_force=brute_force, **kwargs)

    cupyx.scipy.ndimage.binary_dilation = binary_dilation
    return {"cupyx": cupyx, "cupyx.scipy": cupyx.scipy, "cupyx.scipy.ndimage": cupyx.scipy.ndimage}


@contextmanager
def installed():
    """``import cupy`` gives the emulator inside the block; the previous module after it."""
    cp = _module()
    modules = {"cupy": cp, "cupy.fft": cp.fft, "cupy.linalg": cp.linalg, "cupy.cuda": cp.cuda, **_cupyx()}
    before = {k: sys.modules.get(k) for k in modules}
    sys.modules.update(modules)
    try:
        yield cp
    finally:
        for k, v in before.items():
            if v is None:
                sys.modules.pop(k, None)
            else:
                sys.modules[k] = v
