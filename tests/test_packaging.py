"""The stage folders install as one `couch` namespace, and nothing generic lands at top level."""

from __future__ import annotations

import importlib
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CONFIG = tomllib.loads((ROOT / "pyproject.toml").read_text())
PACKAGE_DIR = CONFIG["tool"]["setuptools"]["package-dir"]


def _folder_packages() -> set[str]:
    found = set()
    for name, folder in PACKAGE_DIR.items():
        for init in (ROOT / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(ROOT / folder)
            found.add(".".join([name, *rel.parts]) if rel.parts else name)
    return found


def test_every_package_folder_is_listed():
    assert _folder_packages() == set(CONFIG["tool"]["setuptools"]["packages"])


@pytest.mark.parametrize("stage,folder", [(k, v) for k, v in PACKAGE_DIR.items()])
def test_stage_imports_from_its_folder(stage, folder):
    module = importlib.import_module(stage)
    assert Path(module.__file__).resolve().parent == (ROOT / folder).resolve()


def test_no_generic_top_level_modules_installed():
    site = [Path(p) for p in sys.path if p.endswith("site-packages")]
    assert site
    for folder in site:
        for generic in ("sync", "tools", "capture", "fitting", "augment", "synthesis"):
            assert not (folder / generic).exists(), f"{folder / generic} was installed"


def test_torch_is_pinned_exactly():
    deps = CONFIG["project"]["dependencies"]
    assert "torch==2.13.0" in deps
    assert not any(d.startswith("smplx") for d in deps)
