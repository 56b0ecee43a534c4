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


def _statements(nodes: list[ast.AST]) -> Iterable[ast.AST]:
    """Every statement of ``nodes`` and of the blocks nested in them (function and class
    bodies, branches, handlers, match cases), without descending into expressions: an import
    is a statement, and the expressions are most of a file's nodes."""
    todo = list(nodes)
    while todo:
        node = todo.pop()
        yield node
        for _, value in ast.iter_fields(node):
            if isinstance(value, list):
                todo.extend(v for v in value
                            if isinstance(v, ast.stmt | ast.excepthandler | ast.match_case))


@functools.cache
def _parsed_imports(source: bytes, filename: str) -> tuple[tuple[int, str, str], ...]:
    """(level, module, name) of every ``import`` / ``from ... import`` name of ``source``:
    parsed once per content in a process (the stages' closures share most files)."""
    out = []
    for node in _statements(ast.parse(source, filename=filename).body):
        if isinstance(node, ast.Import):
            out += [(-1, a.name, "") for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            out += [(node.level, node.module or "", a.name) for a in node.names]
    return tuple(out)


def _imports(path: Path, module: str) -> set[str]:
    """Module names of ``module``'s top-level package that its file ``path`` imports:
    ``import a.b`` gives ``a.b``; ``from a.b import c`` gives ``a.b.c`` when that is a module,
    else ``a.b``; relative imports are resolved against ``module``'s package."""
    here = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out: set[str] = set()
    for level, name, attr in _parsed_imports(path.read_bytes(), str(path)):
        if level < 0:
            out.add(name)
            continue
        if level:
            base = here.rsplit(".", level - 1)[0] if level > 1 else here
            source = f"{base}.{name}" if name else base
        else:
            source = name
        sub = f"{source}.{attr}"
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
