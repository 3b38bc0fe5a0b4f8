"""The numba kernels, one module per stage (see the README's layout).

Every kernel is compiled with ``cache=True``. numba checks a cached kernel against its own file
only, not against the kernels it calls in other modules: after an update, a cached kernel would
keep an old copy of a helper it inlined and compute with it silently. So the cache lives in a
folder named after a hash of this package's sources, ``evchain-<hash>`` inside
``$NUMBA_CACHE_DIR`` when that is set, else inside the user cache folder
(``platformdirs.user_cache_dir("evchain")/numba``); a changed kernel anywhere compiles afresh.
Old folders are left to the user (``evchain-*``; each holds a few MB).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path


def sources_hash(folder: Path = Path(__file__).parent) -> str:
    """Short hash of the names and bytes of the ``.py`` files in ``folder``."""
    h = hashlib.sha256()
    for path in sorted(folder.glob("*.py")):
        h.update(path.name.encode() + b"\0" + path.read_bytes())
    return h.hexdigest()[:12]


def cache_dir() -> Path:
    """The folder numba caches evchain's compiled kernels in (see the module docstring)."""
    base = os.environ.get("NUMBA_CACHE_DIR")
    if not base:
        import platformdirs

        base = str(Path(platformdirs.user_cache_dir("evchain")) / "numba")
    return Path(base) / f"evchain-{sources_hash()}"


def _use_cache_dir() -> None:
    import numba.core.config

    numba.core.config.CACHE_DIR = str(cache_dir())


_use_cache_dir()
