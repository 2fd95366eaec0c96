"""Files written atomically: a reader sees the old file or the new one, never a half-written
one (:func:`atomic_write_bytes`, :func:`atomic_write_text`, :func:`atomic_write_json`). Used for
every file the project writes that someone may read meanwhile (results, checkpoints, state
files, site data).
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any

__all__ = ["atomic_write_bytes", "atomic_write_json", "atomic_write_text", "replacement_mode"]


def replacement_mode(path: Path) -> int:
    """The permission bits a file written to ``path`` should get: those of the file it
    replaces, else the usual 0o666 minus the umask (``tempfile.mkstemp`` makes files 0o600)."""
    try:
        return Path(path).stat().st_mode & 0o7777
    except FileNotFoundError:
        # os.umask can only be read by setting it; the window is a few instructions.
        mask = os.umask(0o022)
        os.umask(mask)
        return 0o666 & ~mask


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that readers see the old file or the new one, never a
    half-written one.

    Writes a temporary file in the same directory, fsyncs it, renames it over ``path`` with
    ``os.replace`` and fsyncs the directory. Creates missing parent directories. The new file
    keeps the mode of the file it replaces, or gets the usual 0o666 minus umask. On any error
    the temporary file is removed and ``path`` is left as it was.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    mode = replacement_mode(path)
    fd, tmp_name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fchmod(handle.fileno(), mode)
            os.fsync(handle.fileno())
        os.replace(tmp_name, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp_name)
        raise
    try:
        dir_fd = os.open(path.parent, os.O_RDONLY)
    except OSError:  # some platforms cannot open directories; the rename is done anyway
        return
    try:
        os.fsync(dir_fd)
    except OSError:
        pass
    finally:
        os.close(dir_fd)


def atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` as UTF-8 atomically, see :func:`atomic_write_bytes`. The text is encoded
    before any file is touched."""
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: Path, obj: Any) -> None:
    """Write ``obj`` as JSON (2-space indent, trailing newline) atomically, see
    :func:`atomic_write_text`.

    The object is serialised before any file is touched, so an object json cannot encode
    (``TypeError``) or a NaN/infinity (``ValueError``: not valid JSON) leaves no trace.
    """
    text = json.dumps(obj, indent=2, allow_nan=False) + "\n"
    atomic_write_text(path, text)
