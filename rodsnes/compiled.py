"""The compiled kernels' shared libraries: built by setup.py as extension modules (plain C, no
Python API) and opened with ctypes (model/elastic_compiled.py, contact/potential_compiled.py).
"""
import ctypes
import importlib.util
import os


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
    from an older source; the caller then uses its numpy path).  The kernels' modules cache it (functools.cache on their _load)."""
    lib = open_library(module)
    if lib is None:
        return False
    try:
        return declare(lib)
    except AttributeError:          # a library built from an older source: rebuild (make install)
        return False
