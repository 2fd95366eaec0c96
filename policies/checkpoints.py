"""Checkpoints: an SB3 zip with a sidecar metadata JSON, written atomically, loaded with checks.

A checkpoint ``NAME.zip`` has ``NAME.json`` beside it::

    {"format": "tupa-checkpoint/1", "algorithm": "ddqn", "strategy": "gen10k", "preset": {...},
     "episodes": 10000, "timesteps": ..., "seed": 1, "n_users": 3, "observation_shape": [6,20,20],
     "area": {...}, "scenario_set_hash": "...", "git_commit": "...", "wall_time_s": ...,
     "evaluation": {...}}

Loading checks the metadata against the zip and against the area it will serve, so a file of the
wrong algorithm or built for another observation shape fails with one line naming the mismatch.
"""

from __future__ import annotations

import json
import os
import subprocess
import tempfile
import zipfile
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from sim.config import AreaConfig
from sim.errors import InputError
from sim.files import atomic_write_json, replacement_mode
from sim.observation import observation_shape

CHECKPOINT_FORMAT = "tupa-checkpoint/1"


def metadata_path(checkpoint: Path) -> Path:
    return checkpoint.with_suffix(".json")


def resolve_checkpoint(path: Path) -> Path:
    """``path`` itself if it is a zip, ``path/model.zip`` if it is a training output directory."""
    path = Path(path)
    try:
        if path.is_dir():
            path = path / "model.zip"
        if not path.is_file():
            raise InputError(f"{path}: no such checkpoint")
    except OSError as exc:  # e.g. a name too long for the file system
        raise InputError(f"{path}: cannot open ({exc.strerror or exc})") from None
    return path


def git_commit() -> str | None:
    """The repository's current commit, or None outside a git checkout."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            timeout=5,
            check=True,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None


def save_checkpoint(model: Any, path: Path, metadata: dict[str, Any]) -> None:
    """Write ``model`` (an SB3 algorithm) to ``path`` and its metadata beside it, atomically.

    The zip goes to a temporary file first and is renamed into place; the JSON follows. A crash
    in between leaves the previous checkpoint's zip and JSON intact.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".zip", dir=path.parent)
    os.close(fd)
    try:
        model.save(tmp_name)
        os.chmod(tmp_name, replacement_mode(path))
        os.replace(tmp_name, path)
    except BaseException:
        Path(tmp_name).unlink(missing_ok=True)
        raise
    atomic_write_json(metadata_path(path), {"format": CHECKPOINT_FORMAT, **metadata})


def read_metadata(path: Path) -> dict[str, Any]:
    """The metadata of checkpoint ``path`` (a zip or a training directory), checked."""
    zip_path = resolve_checkpoint(path)
    meta_path = metadata_path(zip_path)
    try:
        meta = json.loads(meta_path.read_text())
    except FileNotFoundError:
        raise InputError(f"{zip_path}: metadata file {meta_path.name} is missing") from None
    except (OSError, ValueError, RecursionError) as exc:  # ValueError: bad JSON, UTF-8, digits
        message = "nested too deeply" if isinstance(exc, RecursionError) else str(exc)
        raise InputError(f"{meta_path}: not a readable JSON file ({message})") from None
    if not isinstance(meta, dict) or meta.get("format") != CHECKPOINT_FORMAT:
        raise InputError(f"{meta_path}: format: expected {CHECKPOINT_FORMAT!r}")
    if meta.get("algorithm") not in ("ddqn", "ddpg"):
        raise InputError(
            f"{meta_path}: algorithm: expected 'ddqn' or 'ddpg', got {meta.get('algorithm')!r}"
        )
    return meta


def load_checkpoint(
    path: Path,
    area: AreaConfig = AreaConfig(),
    algorithm: str | None = None,
    device: str = "auto",
) -> tuple[Any, dict[str, Any]]:
    """Load a checkpoint for serving or evaluation: (SB3 model, metadata).

    Raises ``InputError`` (one line: the file and the mismatch) for a missing or corrupt file,
    the wrong algorithm, or an observation shape other than ``area``'s.
    """
    zip_path = resolve_checkpoint(path)
    meta = read_metadata(zip_path)
    if algorithm is not None and meta["algorithm"] != algorithm:
        raise InputError(
            f"{zip_path}: algorithm: expected {algorithm}, the file holds {meta['algorithm']}"
        )
    expected_shape = list(observation_shape(area))
    if meta.get("observation_shape") != expected_shape:
        raise InputError(
            f"{zip_path}: observation_shape: built for {meta.get('observation_shape')!r}, "
            f"this area needs {expected_shape}"
        )
    if not zipfile.is_zipfile(zip_path):
        raise InputError(f"{zip_path}: not a valid checkpoint zip (corrupt or truncated)")
    model_class = algorithm_class(meta["algorithm"])
    try:
        model = model_class.load(zip_path, device=device)
    except Exception as exc:  # SB3 raises many kinds on a damaged file
        raise InputError(
            f"{zip_path}: cannot load the model ({type(exc).__name__}: {exc})"
        ) from None
    if list(model.observation_space.shape) != expected_shape:
        raise InputError(
            f"{zip_path}: observation_shape: the network takes "
            f"{list(model.observation_space.shape)}, this area needs {expected_shape}"
        )
    return model, meta


def export_checkpoint(
    source: Path, dest: Path, area: AreaConfig = AreaConfig(), **extra_metadata: Any
) -> dict[str, Any]:
    """Write a serving copy of checkpoint ``source`` to ``dest`` (zip + metadata JSON).

    Same network weights (online and target), so it acts exactly as ``source`` does; without
    the optimizer's running statistics (RMSprop's squared-gradient averages: as large as the
    network itself and only needed to continue training; a copy resumed anyway starts them
    afresh) and without a replay buffer (never in the zip); members deflate-compressed. The
    metadata is ``source``'s plus ``extra_metadata`` and an ``exported_from`` note.
    """
    model, meta = load_checkpoint(source, area, device="cpu")
    for name in model._get_torch_save_params()[0]:
        if name.endswith("optimizer"):
            obj = model
            for part in name.split("."):
                obj = getattr(obj, part)
            obj.state.clear()
    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{dest.stem}.", suffix=".zip", dir=dest.parent)
    os.close(fd)
    plain = Path(tmp_name).with_suffix(".plain.zip")
    try:
        model.save(plain)
        with (
            zipfile.ZipFile(plain) as src,
            zipfile.ZipFile(tmp_name, "w", compression=zipfile.ZIP_DEFLATED) as out,
        ):
            for item in src.infolist():
                out.writestr(item.filename, src.read(item.filename))
        os.chmod(tmp_name, replacement_mode(dest))
        os.replace(tmp_name, dest)
    except BaseException:
        Path(tmp_name).unlink(missing_ok=True)
        raise
    finally:
        plain.unlink(missing_ok=True)
    metadata = {
        **{k: v for k, v in meta.items() if k != "format"},
        **extra_metadata,
        "exported_from": {
            "path": str(source),
            "at": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
            "dropped": ["optimizer state"],
        },
    }
    atomic_write_json(metadata_path(dest), {"format": CHECKPOINT_FORMAT, **metadata})
    return metadata


def algorithm_class(algorithm: str) -> type:
    if algorithm == "ddqn":
        from policies.ddqn import MaskedDoubleDQN

        return MaskedDoubleDQN
    if algorithm == "ddpg":
        from policies.ddpg import IntervalTargetDDPG

        return IntervalTargetDDPG
    raise ValueError(f"algorithm: expected 'ddqn' or 'ddpg', got {algorithm!r}")
