"""A restricted unpickler for third-party pickles (official SMPL ``.pkl``, BEHAVE fits).

``pickle.load`` on a file from elsewhere runs whatever callable the file names. This loader only
rebuilds numpy arrays, plain containers, scipy sparse matrices and chumpy arrays (as numpy,
without chumpy, which cannot be installed on Python 3.11); any other global makes it stop with
:class:`UnsafePickleError` naming the file and the global. Python 2 pickles (the official SMPL
files) are read with ``encoding="latin1"``.
"""

from __future__ import annotations

import builtins
import importlib
import os
import pickle
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse


class UnsafePickleError(pickle.UnpicklingError):
    """The pickle asked for a global this loader does not allow."""


class _StandIn:
    """Records the state a pickled object would have received, without running its code."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.args = args
        self.state: Any = None

    def __setstate__(self, state: Any) -> None:
        self.state = state


class _Chumpy(_StandIn):
    cls_name = "chumpy"


class _Sparse(_StandIn):
    fmt = "csc"


_NUMPY_GLOBALS = {
    ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"),
    ("numpy", "ndarray"), ("numpy", "dtype"),
    ("numpy.core.numeric", "_frombuffer"), ("numpy._core.numeric", "_frombuffer"),
}
_PLAIN_BUILTINS = {"set", "frozenset", "complex", "bytearray", "slice", "object"}
_SPARSE_FORMATS = {"csc_matrix": "csc", "csr_matrix": "csr", "coo_matrix": "coo",
                   "csc_array": "csc", "csr_array": "csr", "coo_array": "coo"}


def _safe_reconstructor(cls: Any, base: Any, state: Any) -> Any:
    # copyreg._reconstructor builds protocol 0/1 objects; only our stand-ins may be built this way.
    if isinstance(cls, type) and issubclass(cls, _StandIn) and base is object:
        return cls.__new__(cls)
    raise UnsafePickleError(f"copyreg._reconstructor for {cls!r} is not allowed")


def _numpy_global(module: str, name: str) -> Any:
    if module.startswith(("numpy.core", "numpy._core")):
        sub = module.split(".")[-1]
        try:
            return getattr(importlib.import_module(f"numpy._core.{sub}"), name)
        except ImportError:  # numpy < 2
            return getattr(importlib.import_module(f"numpy.core.{sub}"), name)
    return getattr(np, name)


def _latin1_encode(text: str, encoding: str = "utf-8") -> bytes:
    # Python 3 writes bytes into protocol 0-2 pickles as _codecs.encode(str, "latin1").
    if not isinstance(text, str) or encoding not in ("latin1", "latin-1"):
        raise UnsafePickleError(f"_codecs.encode({type(text).__name__}, {encoding!r}) is not "
                                "allowed")
    return text.encode("latin1")


class _RestrictedUnpickler(pickle.Unpickler):
    def __init__(self, file: Any, source: str) -> None:
        super().__init__(file, encoding="latin1")
        self.source = source

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in _NUMPY_GLOBALS:
            return _numpy_global(module, name)
        if module == "_codecs" and name == "encode":
            return _latin1_encode
        if module in ("copy_reg", "copyreg") and name == "_reconstructor":
            return _safe_reconstructor
        if module in ("__builtin__", "builtins") and name in _PLAIN_BUILTINS:
            return getattr(builtins, name)
        if module.startswith("scipy.sparse") and name in _SPARSE_FORMATS:
            return type(name, (_Sparse,), {"fmt": _SPARSE_FORMATS[name]})
        if module == "chumpy" or module.startswith("chumpy."):
            return type(name, (_Chumpy,), {"cls_name": f"{module}.{name}"})
        raise UnsafePickleError(
            f"{self.source}: refusing to load global '{module}.{name}' (only numpy arrays, "
            "plain containers, scipy sparse matrices and chumpy arrays are allowed)")


def _to_plain(obj: Any, source: str) -> Any:
    if isinstance(obj, _Chumpy):
        state = obj.state if isinstance(obj.state, dict) else {}
        if "x" not in state:
            raise UnsafePickleError(
                f"{source}: chumpy object {obj.cls_name} holds an expression, not an array; "
                "convert the file with chumpy installed (x.r) first")
        return np.asarray(_to_plain(state["x"], source))
    if isinstance(obj, _Sparse):
        s = obj.state if isinstance(obj.state, dict) else {}
        shape = tuple(s.get("_shape", s.get("shape", ())))
        if obj.fmt == "coo":
            return scipy.sparse.coo_matrix((s["data"], (s["row"], s["col"])), shape=shape)
        build = scipy.sparse.csc_matrix if obj.fmt == "csc" else scipy.sparse.csr_matrix
        return build((s["data"], s["indices"], s["indptr"]), shape=shape)
    if isinstance(obj, dict):
        return {(k.decode("latin1") if isinstance(k, bytes) else k): _to_plain(v, source)
                for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return type(obj)(_to_plain(v, source) for v in obj)
    return obj


def safe_load_pickle(path: str | os.PathLike) -> Any:
    """Load a third-party pickle without executing code; chumpy arrays become numpy arrays.

    Raises:
        UnsafePickleError: the file names a global outside the allowed set (the message names
            the file and the global).
        pickle.UnpicklingError / EOFError: the file is not a (complete) pickle.
    """
    path = Path(path)
    with path.open("rb") as f:
        try:
            return _to_plain(_RestrictedUnpickler(f, str(path)).load(), str(path))
        except UnsafePickleError:
            raise
        except (pickle.UnpicklingError, EOFError, KeyError, TypeError, ValueError) as e:
            raise pickle.UnpicklingError(f"{path}: not a readable pickle ({e})") from e


__all__ = ["UnsafePickleError", "safe_load_pickle"]
