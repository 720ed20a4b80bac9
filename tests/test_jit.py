"""ssp.jit: where the compiled kernels are cached."""

from __future__ import annotations

import shutil
from pathlib import Path

import ssp.jit
from ssp.jit import KERNEL_MODULES, kernel_cache_dir

PKG = Path(ssp.jit.__file__).parent


def _copy(tmp_path: Path, name: str) -> Path:
    root = tmp_path / name
    for module in KERNEL_MODULES + ("parser.py",):
        (root / module).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(PKG / module, root / module)
    return root


def test_the_kernel_cache_changes_with_any_kernel_module_and_only_with_them(tmp_path, monkeypatch):
    monkeypatch.setenv("SSP_CACHE_DIR", str(tmp_path / "cache"))
    a, b = _copy(tmp_path, "a"), _copy(tmp_path, "b")
    same = kernel_cache_dir(a)
    assert same == kernel_cache_dir(b)  # the same sources elsewhere: the same folder
    assert same.parent == tmp_path / "cache" / "kernels"
    with (b / "parser.py").open("a") as f:
        f.write("\n# not a kernel module\n")
    kernel_cache_dir.cache_clear()
    assert kernel_cache_dir(b) == same
    with (b / "cells.py").open("a") as f:  # a callee of other modules' kernels
        f.write("\n# changed\n")
    kernel_cache_dir.cache_clear()
    assert kernel_cache_dir(b) != same


def test_the_kernels_are_cached_in_that_folder():
    from ssp.cells import cell_sort

    path = Path(cell_sort._cache._cache_path)
    assert path.parent == kernel_cache_dir()
