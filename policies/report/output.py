"""What a report writes: ``results.md`` beside its figures, each file atomically
(:func:`write_report_files`), and what the caller is told (:class:`ReportFiles`). Shared by the
single-vehicle, fleet and sweep reports.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from sim.errors import InputError

REPORT_FILE = "results.md"
"""The report's tables and headlines (markdown)."""


@dataclass(frozen=True)
class ReportFiles:
    """What a report wrote: the files, and one headline line per compared policy."""

    written: tuple[Path, ...]
    headlines: tuple[str, ...]


def write_report_files(out_dir: Path, files: dict[str, bytes | str]) -> list[Path]:
    """Write a report's files into ``out_dir`` (created if missing), each atomically (figures
    as bytes, text as UTF-8); InputError naming ``--out`` if it cannot be written."""
    from sim.atomic import atomic_write_bytes, atomic_write_text

    written = []
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        for name, data in files.items():
            if isinstance(data, str):
                atomic_write_text(out_dir / name, data)
            else:
                atomic_write_bytes(out_dir / name, data)
            written.append(out_dir / name)
    except OSError as exc:
        raise InputError(f"--out: {out_dir}: cannot write: {exc.strerror or exc}") from None
    return written
