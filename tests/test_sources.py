"""couch.sources: the code digests the pipeline's cache keys hash instead of the version."""

from __future__ import annotations

import sys

import pytest

from couch.fitting.pipeline import STAGE_CODE
from couch.sources import module_closure, source_digest


@pytest.fixture
def pkg(tmp_path, monkeypatch):
    """A package ``toy``: ``toy.a`` imports ``toy.b`` lazily, inside a function, ``toy.d`` in an
    exception handler of a method, and a name from ``toy.sub``; ``toy.sub.rel`` imports both
    relatively; ``toy.c`` is imported by nothing; ``toy/sub/data/`` holds a data file."""
    root = tmp_path / "toy"
    (root / "sub" / "data").mkdir(parents=True)
    (root / "__init__.py").write_text("")
    (root / "a.py").write_text("import os\nfrom toy.sub import K\n\n"
                               "def f():\n    import toy.b\n    return toy.b.Y + K\n\n"
                               "class G:\n    def m(self, x):\n        match x:\n"
                               "            case 1:\n                try:\n"
                               "                    pass\n"
                               "                except ValueError:\n"
                               "                    from toy import d\n")
    (root / "b.py").write_text("Y = 2\n")
    (root / "d.py").write_text("W = 5\n")
    (root / "c.py").write_text("Z = 3\n")
    (root / "sub" / "__init__.py").write_text("K = 1\n")
    (root / "sub" / "rel.py").write_text("from . import K\nfrom ..b import Y\n")
    (root / "sub" / "data" / "weights.txt").write_text("0.5\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    yield root
    # find_spec imports the parent packages; the next test's toy lives in another folder
    for name in [m for m in sys.modules if m == "toy" or m.startswith("toy.")]:
        del sys.modules[name]


def _digest(*entries: str) -> str:
    source_digest.cache_clear()  # the files change between calls here, not within a process
    return source_digest(entries)


def test_closure_follows_imports_within_the_package(pkg):
    assert sorted(module_closure(["toy.a"])) == ["toy.a", "toy.b", "toy.d", "toy.sub"]
    # relative imports, one and two levels up
    assert sorted(module_closure(["toy.sub.rel"])) == ["toy.b", "toy.sub", "toy.sub.rel"]
    with pytest.raises(ModuleNotFoundError, match=r"toy\.nothing"):
        module_closure(["toy.nothing"])
    # a file's imports are read again when it changes (parsed once per content, not per path)
    (pkg / "a.py").write_text("import toy.c\n")
    assert sorted(module_closure(["toy.a"])) == ["toy.a", "toy.c"]


def test_digest_changes_with_the_code_it_runs_and_only_that(pkg):
    first = _digest("toy.a")
    (pkg / "c.py").write_text("Z = 4\n")  # not imported by toy.a
    (pkg / "__pycache__").mkdir(exist_ok=True)
    (pkg / "__pycache__" / "b.cpython-311.pyc").write_bytes(b"\0" * 16)
    assert _digest("toy.a") == first
    (pkg / "b.py").write_text("Y = 3\n")  # a changed default, imported lazily
    second = _digest("toy.a")
    assert second != first
    (pkg / "sub" / "data" / "weights.txt").write_text("0.6\n")  # data beside an imported module
    assert _digest("toy.a") not in (first, second)
    (pkg / "b.py").write_text("Y = 2\n")
    (pkg / "sub" / "data" / "weights.txt").write_text("0.5\n")
    assert _digest("toy.a") == first


def test_each_stage_hashes_the_modules_that_compute_it():
    closures = {stage: module_closure(entries) for stage, entries in STAGE_CODE.items()}
    assert "couch.capture.calibration" in closures["calibrate"]
    assert not any(m.startswith("couch.fitting") for m in closures["calibrate"])
    assert {"couch.capture.segmentation", "couch.fitting.chair"} <= set(closures["chair"])
    assert "couch.fitting.fusion" not in closures["chair"]
    assert {"couch.fitting.fusion", "couch.capture.segmentation", "couch.sync.imu",
            "couch.body.model"} <= set(closures["body"])
    assert "couch.fitting.contacts" in closures["contacts"]
