"""Digests of the source code a result comes from, for cache keys.

A cache keyed on the release number serves stale results whenever a default or a fix changes
inside one release. :func:`source_digest` hashes instead the files of the modules a computation
can run: its entry modules and, transitively, every module of the same top-level package they
import (read statically from the ``import`` statements anywhere in each file, lazy imports inside
functions included), plus the ``data/`` folder beside each such module (the body model's
arrays). A change to a module the computation does not import leaves its digest alone, as
``make`` leaves a target whose prerequisites did not change.
"""

from __future__ import annotations

import ast
import functools
import hashlib
import importlib.util
from collections.abc import Iterable
from pathlib import Path


def _module_file(name: str) -> Path | None:
    """The source file of module ``name`` (a package's ``__init__.py``); None when it is not a
    module of source code (a name imported from a module, a built-in)."""
    try:
        spec = importlib.util.find_spec(name)
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.origin or not spec.origin.endswith(".py"):
        return None
    return Path(spec.origin)


def _imports(path: Path, module: str) -> set[str]:
    """Module names of ``module``'s top-level package that its file ``path`` imports:
    ``import a.b`` gives ``a.b``; ``from a.b import c`` gives ``a.b.c`` when that is a module,
    else ``a.b``; relative imports are resolved against ``module``'s package."""
    here = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_bytes(), filename=str(path))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = here.rsplit(".", node.level - 1)[0] if node.level > 1 else here
                source = f"{base}.{node.module}" if node.module else base
            else:
                source = node.module or ""
            for a in node.names:
                sub = f"{source}.{a.name}"
                out.add(sub if _module_file(sub) is not None else source)
    top = module.split(".")[0]
    return {m for m in out if m == top or m.startswith(top + ".")}


def module_closure(entries: Iterable[str]) -> dict[str, Path]:
    """Source files of the modules ``entries`` name and of every module of their top-level
    package they import, transitively: ``{module name: file}``.

    Raises:
        ModuleNotFoundError: an entry is not a module of source code.
    """
    todo = list(entries)
    found: dict[str, Path] = {}
    while todo:
        name = todo.pop()
        if name in found:
            continue
        path = _module_file(name)
        if path is None:
            raise ModuleNotFoundError(f"{name} is not a Python source module")
        found[name] = path
        todo.extend(_imports(path, name))
    return found


@functools.cache
def source_digest(entries: tuple[str, ...]) -> str:
    """Hex sha256 of :func:`module_closure` ``(entries)``'s files (by module name and content)
    and of the files in a ``data/`` folder beside any of them; computed once per process."""
    h = hashlib.sha256()
    files = module_closure(entries)
    data: dict[str, Path] = {}
    for name, path in files.items():
        folder = path.parent / "data"
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        if folder.is_dir():
            for f in folder.rglob("*"):
                if f.is_file() and "__pycache__" not in f.parts:
                    data[f"{package}/data/{f.relative_to(folder).as_posix()}"] = f
    for key, path in sorted({**files, **data}.items()):
        h.update(f"{key}\0".encode())
        h.update(hashlib.sha256(path.read_bytes()).digest())
    return h.hexdigest()
