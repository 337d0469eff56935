"""Where numba keeps coopmap's compiled kernels: one folder per state of their sources.

numba's on-disk cache (``@njit(cache=True)``) checks only the file of the function it compiled,
not the files of the kernels that function calls and inlines: after an update that changes a
callee in another file (``mapping.kernels.traversal._mark``, inlined into
``mapping.kernels.integrate``), the caller's cached machine code would still hold the old
callee, and nothing would say so. So the cache lives in a folder named after the contents of
every source file that uses numba (``~/.cache/coopmap/numba/<key>``, or under
``$XDG_CACHE_HOME``): a changed kernel anywhere starts a new folder, and every kernel is compiled
afresh once. The three most recently used folders are kept. ``NUMBA_CACHE_DIR``, when set,
is left as it is.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import sys
from pathlib import Path

__all__ = ["key_numba_cache", "source_key"]

_ROOT = Path(__file__).resolve().parent.parent
_PACKAGES = ("estimation", "mapping", "sensors")
#: The folders of this many source states are kept (the newest by use); older ones are removed.
_KEEP = 3
_KEY = re.compile(r"[0-9a-f]{16}")


def source_key(root: Path = _ROOT) -> str:
    """A hash of the path and contents of every ``.py`` file under the three packages that uses
    numba, in path order."""
    files = []
    for package in _PACKAGES:
        for folder, subfolders, names in os.walk(root / package):
            subfolders[:] = [d for d in subfolders if d != "__pycache__"]
            files += [os.path.join(folder, n) for n in names if n.endswith(".py")]
    digest = hashlib.sha256()
    for path in sorted(files):
        with open(path, "rb") as source:
            data = source.read()
        if b"numba" in data:
            digest.update(Path(path).relative_to(root).as_posix().encode())
            digest.update(len(data).to_bytes(8, "little"))
            digest.update(data)
    return digest.hexdigest()[:16]


def _cache_home() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "coopmap" / "numba"


def key_numba_cache(root: Path = _ROOT) -> Path | None:
    """Point numba's cache at the folder of the sources' state under ``root`` (made, and marked
    as just used), and remove the folders of older states beyond the newest ``_KEEP`` (only
    folders named as this names them); None (and nothing changed) when ``NUMBA_CACHE_DIR`` is
    set or no folder can be made."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return None
    home = _cache_home()
    folder = home / source_key(root)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        os.utime(folder)
    except OSError:
        return None  # numba's own default then (beside the sources)
    os.environ["NUMBA_CACHE_DIR"] = str(folder)
    config = sys.modules.get("numba.core.config")
    if config is not None:  # numba already imported: it read the variable then
        config.CACHE_DIR = str(folder)  # type: ignore[attr-defined]
    try:
        states = sorted(home.iterdir(), key=lambda p: p.stat().st_mtime, reverse=True)
    except OSError:
        return folder
    ours = [p for p in states if _KEY.fullmatch(p.name) and p.is_dir() and not p.is_symlink()]
    for old in ours[_KEEP:]:
        if old != folder:
            shutil.rmtree(old, ignore_errors=True)
    return folder
