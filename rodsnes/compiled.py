"""The compiled kernels' shared libraries: built by setup.py as extension modules (plain C, no
Python API) and opened with ctypes (model/elastic_compiled.py, contact/potential_compiled.py).
"""
import ctypes
import functools
import importlib.util
import os

import numpy as np

F64 = np.dtype(np.float64)
I64 = np.dtype(np.int64)
I32 = np.dtype(np.int32)
I8 = np.dtype(np.int8)


def library_path(module):
    """Path of the built extension ``module`` (a dotted name), or None when it is not built."""
    try:
        spec = importlib.util.find_spec(module)
    except (ImportError, ValueError):
        spec = None
    if spec is None or not spec.origin or not os.path.isfile(spec.origin):
        return None
    return spec.origin


def open_library(module):
    """ctypes.CDLL of the built extension ``module``, or None when it is not built or does not
    load (the caller then uses its numpy path)."""
    path = library_path(module)
    if path is None:
        return None
    try:
        return ctypes.CDLL(path)
    except OSError:
        return None


def load(module, declare):
    """declare(lib): the ctypes functions, with their argument types, of the built extension
    ``module``; False when it is not built, does not load or lacks a declared function (built
    from an older source; the caller then uses its numpy path).  The kernels' modules load it
    once, through ``loader``."""
    lib = open_library(module)
    if lib is None:
        return False
    try:
        return declare(lib)
    except AttributeError:          # a library built from an older source: rebuild (make install)
        return False


def loader(module, declare):
    """A function of no arguments that returns load(module, declare), made on its first call
    and kept (each kernel's module holds one as its _load)."""
    return functools.lru_cache(maxsize=None)(functools.partial(load, module, declare))


def address(a, dtype):
    """The address of ``a``, a C-contiguous array of ``dtype`` (None: NULL), checked in Python
    before the foreign call."""
    if a is None:
        return None
    if not isinstance(a, np.ndarray) or a.dtype != dtype or not a.flags.c_contiguous:
        raise TypeError(f"a C-contiguous {dtype} array is needed, not "
                        f"{type(a).__name__} {getattr(a, 'dtype', '')}")
    return a.__array_interface__["data"][0]


class Foreign:
    """A C function of a built library with its signature: ``spec`` holds ctypes scalar types,
    or F64 / I64 for C-contiguous arrays of that dtype, passed by address.  The arrays are
    checked and turned into addresses here, in Python, before the call: with numpy's ndpointer
    argtypes that work runs inside ctypes' argument conversion, and an exception raised there
    (the Interrupted of a SIGINT or SIGTERM arriving at that moment) reached the caller as
    ctypes.ArgumentError, a traceback instead of the interrupted run's exit."""

    def __init__(self, fn, spec, restype):
        self.fn, self.spec = fn, tuple(spec)
        fn.argtypes = [ctypes.c_void_p if isinstance(t, np.dtype) else t for t in self.spec]
        fn.restype = restype

    def __call__(self, *args):
        if len(args) != len(self.spec):
            raise TypeError(f"{len(self.spec)} arguments expected, {len(args)} given")
        return self.fn(*[address(a, t) if isinstance(t, np.dtype) else a
                         for a, t in zip(args, self.spec)])
