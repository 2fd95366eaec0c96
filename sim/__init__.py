"""The network model, the world and the environments (docs/architecture.md).

Numba caches each compiled kernel beside its source and re-checks only that file's own time
stamp, so a kernel that calls a function from another module (``sim.network`` calls
``sim.queues``, ``sim.mac``, ``sim.phy`` ...) would keep running the old callee after that module
changed. The cache therefore lives in a directory named by a hash of this package's sources,
subpackages included: any change to any module compiles afresh. ``NUMBA_CACHE_DIR`` set by the
caller wins.
"""

from __future__ import annotations

import hashlib
import os
import sys
import tempfile
from pathlib import Path


def _numba_cache_dir() -> None:
    if "NUMBA_CACHE_DIR" in os.environ:
        return
    here = Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for source in sorted(here.rglob("*.py")):
        digest.update(source.relative_to(here).as_posix().encode())
        digest.update(source.read_bytes())
    name = f"numba-{digest.hexdigest()[:16]}"
    # Beside the sources as numba would, or (read-only install) in the user's temp directory.
    for place in (here / "__pycache__" / name, Path(tempfile.gettempdir()) / f"tupa-{name}"):
        try:
            place.mkdir(parents=True, exist_ok=True)
        except OSError:
            continue
        if os.access(place, os.W_OK):
            break
    else:
        return  # nowhere writable: numba's own choice (it may not cache)
    path = str(place)
    os.environ["NUMBA_CACHE_DIR"] = path
    if "numba" in sys.modules:  # imported before us: its configuration is already read
        sys.modules["numba"].config.CACHE_DIR = path


_numba_cache_dir()
