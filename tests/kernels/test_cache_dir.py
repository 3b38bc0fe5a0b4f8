"""The numba cache folder follows the kernels' sources (numba alone checks only each kernel's
own file, so a kernel could keep an inlined helper's old code)."""

import shutil
from pathlib import Path

import numba.core.config

import evchain.kernels as kernels


def test_numba_caches_the_kernels_in_the_folder_of_their_sources_hash():
    assert numba.core.config.CACHE_DIR == str(kernels.cache_dir())
    assert kernels.cache_dir().name == f"evchain-{kernels.sources_hash()}"


def test_the_folder_is_inside_numba_cache_dir_when_that_is_set(monkeypatch, tmp_path):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    assert kernels.cache_dir() == tmp_path / f"evchain-{kernels.sources_hash()}"


def test_the_hash_changes_with_any_kernel_module(tmp_path):
    src = tmp_path / "k"
    shutil.copytree(Path(kernels.__file__).parent, src,
                    ignore=shutil.ignore_patterns("__pycache__"))
    before = kernels.sources_hash(src)
    assert before == kernels.sources_hash()
    helper = src / "fit.py"
    helper.write_text(helper.read_text() + "\n# changed\n")
    assert kernels.sources_hash(src) != before
