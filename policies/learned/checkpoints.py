"""Checkpoints: an SB3 zip with a sidecar metadata JSON, written atomically, loaded with checks.

A checkpoint ``NAME.zip`` has ``NAME.json`` beside it::

    {"format": "tupa-checkpoint/1", "algorithm": "ddqn", "strategy": "gen10k", "preset": {...},
     "episodes": 10000, "timesteps": ..., "seed": 1, "n_users": 3, "observation_shape": [6,20,20],
     "area": {...}, "scenario_set_hash": "...", "git_commit": "...", "wall_time_s": ...,
     "evaluation": {...}}

Loading checks the metadata against the zip and against the area it will serve, so a file of the
wrong algorithm or built for another observation shape fails with one line naming the mismatch.

A checkpoint is a pickle (SB3 unpickles parts of ``data``): loading one runs code. So the files
are read once, through descriptors that are checked as opened (optionally: inside given
directories, never a FIFO or device, bounded in size), and the model is loaded from those bytes
(:func:`read_checkpoint`, :func:`load_checkpoint`); the service adds the directories it trusts.

Those pickles name classes by module path: the CNN in ``policy_kwargs``, a DDQN's replay buffer
class. A checkpoint saved before ``policies/`` went into folders names them at their old paths
(``policies.networks.ZoneMapsCNN``, ``policies.ddqn.MaskedReplayBuffer``); loading and resuming
look those up at their current paths (:data:`MOVED_MODULES`, :func:`moved_objects`,
:func:`load_replay_buffer`), so every such file loads and decides as it did.
"""

from __future__ import annotations

import base64
import io
import json
import os
import pickle
import stat
import subprocess
import zipfile
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from sim.atomic import atomic_write_bytes, atomic_write_json
from sim.config import AreaConfig
from sim.errors import InputError
from sim.observation import observation_shape as area_observation_shape

CHECKPOINT_FORMAT = "tupa-checkpoint/1"
RUN_FILE = "run.json"
"""A training run's state in its directory: its configuration and the episodes done."""
LATEST_CHECKPOINT = Path("checkpoints") / "latest.zip"
"""A training run's latest checkpoint, relative to its directory (periodic, and on an
interruption)."""
REPLAY_BUFFER = "latest_replay.pkl"
"""The replay buffer saved beside the latest checkpoint, when the run was asked to."""
MOVED_MODULES: dict[str, str] = {
    "policies.networks": "policies.learned.networks",
    "policies.ddqn": "policies.learned.ddqn",
    "policies.ddpg": "policies.learned.ddpg",
}
"""The modules a checkpoint's pickles may name at a path that no longer exists → where they
are now (``policies/`` in folders by job)."""


def metadata_path(checkpoint: Path) -> Path:
    return checkpoint.with_suffix(".json")


@dataclass(frozen=True)
class TrainingRun:
    """What a ``tupa train`` output directory holds, read without loading any model."""

    directory: Path
    finished: bool
    """Whether ``model.zip`` is there (the run ended and was evaluated)."""
    latest: Path | None
    """``checkpoints/latest.zip``, when there is one."""
    episodes_done: int | None
    episodes: int | None
    """The episodes the run was to train (its target)."""
    test_scenarios: str | None

    @property
    def interrupted(self) -> bool:
        """Stopped before the end (Ctrl-C, SIGTERM, a crash) with a checkpoint to show for it."""
        return not self.finished and self.latest is not None

    def progress(self) -> str:
        """``35 of 2000 episodes`` (or less, when ``run.json`` does not say)."""
        if self.episodes_done is None:
            return "episodes unknown"
        target = f" of {self.episodes}" if self.episodes is not None else ""
        return f"{self.episodes_done}{target} episodes"


def training_run(directory: Path | str, read_state: bool = True) -> TrainingRun | None:
    """The training run in ``directory``, or None when it holds none (no ``run.json``,
    ``model.zip`` or ``checkpoints/latest.zip``). With ``read_state`` the counts and the test
    set come from ``run.json`` (unknown when it cannot be read); without, no file is read, only
    looked at (for a directory a client named)."""
    directory = Path(directory)
    if not directory.is_dir():
        return None
    finished = (directory / "model.zip").is_file()
    latest = directory / LATEST_CHECKPOINT
    has_latest = latest.is_file()
    state_file = directory / RUN_FILE
    if not (finished or has_latest or state_file.is_file()):
        return None
    state: Any = {}
    if read_state and state_file.is_file():
        try:
            state = json.loads(state_file.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            state = {}
    state = state if isinstance(state, dict) else {}
    config = state.get("config")
    config = config if isinstance(config, dict) else {}
    done, target = state.get("episodes_done"), config.get("episodes")
    return TrainingRun(
        directory=directory,
        finished=finished,
        latest=latest if has_latest else None,
        episodes_done=done if isinstance(done, int) else None,
        episodes=target if isinstance(target, int) else None,
        test_scenarios=str(config["test_scenarios"]) if config.get("test_scenarios") else None,
    )


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

    The zip is built in memory and written with :func:`sim.atomic.atomic_write_bytes`; the JSON
    follows. A crash in between leaves the previous checkpoint's zip and JSON intact.
    """
    path = Path(path)
    buffer = io.BytesIO()
    model.save(buffer)
    atomic_write_bytes(path, buffer.getvalue())
    atomic_write_json(metadata_path(path), {"format": CHECKPOINT_FORMAT, **metadata})


class CheckpointError(InputError):
    """A checkpoint that cannot be used.

    ``str(error)`` names the file and gives every detail, for the command line and the
    service's log; :attr:`problem` says what is wrong without any path, file content or library
    text: what the service may tell an HTTP client.
    """

    def __init__(self, shown: Path | str, problem: str, detail: str | None = None) -> None:
        self.path = str(shown)
        self.problem = problem
        self.detail = detail
        super().__init__(f"{shown}: {problem}" + (f" ({detail})" if detail else ""))


class CheckpointTooLargeError(CheckpointError):
    """The checkpoint file, or what its zip expands to, is over the size limit."""


NO_SUCH_CHECKPOINT = "no such checkpoint"
OUTSIDE_ALLOWED = "outside the checkpoint directories this service loads from"
METADATA_MAX_BYTES = 1024 * 1024
"""A metadata file is a few kB; a larger one is refused unread."""
MAX_MEMBERS = 64
"""An SB3 zip has about seven members."""


@dataclass(frozen=True)
class CheckpointFiles:
    """A checkpoint read from disk once: the zip's bytes and the metadata beside it."""

    shown: Path
    """The zip as the caller named it (``DIR/model.zip`` for a training directory)."""
    real_path: Path
    """The file the bytes were read from (links resolved)."""
    zip_bytes: bytes
    metadata: dict[str, Any]


def read_checkpoint(
    path: Path | str,
    allowed_dirs: Sequence[Path] | None = None,
    max_bytes: int | None = None,
) -> CheckpointFiles:
    """Read checkpoint ``path`` (a zip, or a training directory holding ``model.zip``) and its
    metadata JSON, each opened once and checked as opened; ``CheckpointError`` otherwise (for
    an interrupted run's directory, which has no ``model.zip``, naming its latest checkpoint).

    With ``allowed_dirs`` both files must lie inside one of those directories. The path is
    resolved once (links and ``..``), checked, and the resolved file is opened without
    following a final link; the *open* file is then checked again (by the real path of the
    descriptor) and read through that descriptor, so a link flipped between the check and the
    read cannot substitute another file. The metadata file is the one beside the real
    checkpoint, read the same way. Only regular files are read, never waited on: a FIFO or a
    device is refused. ``max_bytes`` bounds the zip file (the metadata file has its own, small
    bound, :data:`METADATA_MAX_BYTES`).
    """
    shown = Path(path)
    roots = _roots(allowed_dirs)
    run = None
    try:
        resolved = _resolve_inside(shown, shown, roots)
        if resolved.is_dir():
            run = training_run(resolved, read_state=False)
            shown = shown / "model.zip"
            resolved = _resolve_inside(resolved / "model.zip", shown, roots)
    except CheckpointError:
        raise
    except (OSError, RuntimeError, ValueError) as exc:  # too long a name, a loop of links, NUL
        raise CheckpointError(shown, "cannot open the checkpoint", _reason(exc)) from None
    try:
        zip_bytes, real_path = _read_checked(
            resolved, shown, roots, max_bytes, missing=NO_SUCH_CHECKPOINT, what="checkpoint"
        )
    except CheckpointError as exc:
        if run is None or not run.interrupted or exc.problem != NO_SUCH_CHECKPOINT:
            raise
        raise CheckpointError(
            shown,
            NO_SUCH_CHECKPOINT,
            f"an interrupted run: its latest checkpoint is {shown.parent / LATEST_CHECKPOINT}",
        ) from None
    meta_shown = metadata_path(shown)
    try:
        meta_resolved = _resolve_inside(metadata_path(real_path), meta_shown, roots)
    except CheckpointError:
        raise
    except (OSError, RuntimeError, ValueError) as exc:
        raise CheckpointError(meta_shown, "cannot open the metadata file", _reason(exc)) from None
    meta_bytes, _ = _read_checked(
        meta_resolved,
        meta_shown,
        roots,
        METADATA_MAX_BYTES,
        missing=f"metadata file {meta_shown.name} is missing",
        what="metadata file",
    )
    return CheckpointFiles(shown, real_path, zip_bytes, _parse_metadata(meta_bytes, meta_shown))


def read_metadata(path: Path) -> dict[str, Any]:
    """The metadata of checkpoint ``path`` (a zip or a training directory), checked."""
    return read_checkpoint(path).metadata


def _roots(allowed_dirs: Sequence[Path] | None) -> list[Path] | None:
    if allowed_dirs is None:
        return None
    return [Path(d).resolve() for d in allowed_dirs]


def _inside(path: Path, roots: list[Path] | None) -> bool:
    return roots is None or any(path.is_relative_to(root) for root in roots)


def _resolve_inside(path: Path, shown: Path, roots: list[Path] | None) -> Path:
    """``path`` with links and ``..`` resolved (it need not exist), refused outside ``roots``."""
    resolved = path.resolve()
    if not _inside(resolved, roots):
        raise CheckpointError(shown, OUTSIDE_ALLOWED, f"it resolves to {resolved}")
    return resolved


def _read_checked(
    resolved: Path,
    shown: Path,
    roots: list[Path] | None,
    max_bytes: int | None,
    missing: str,
    what: str,
) -> tuple[bytes, Path]:
    """The bytes of the regular file ``resolved`` and its real path, read through one
    descriptor that was checked (see :func:`read_checkpoint`)."""
    flags = os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0)
    try:
        fd = os.open(resolved, flags | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise CheckpointError(shown, missing) from None
    except OSError as exc:  # ELOOP: the last component became a link after it was resolved
        raise CheckpointError(shown, f"cannot open the {what}", _reason(exc)) from None
    with os.fdopen(fd, "rb") as handle:
        status = os.fstat(fd)
        if not stat.S_ISREG(status.st_mode):
            raise CheckpointError(shown, f"the {what} is not a regular file")
        real_path = _real_path(fd, resolved)
        if real_path is None or not _inside(real_path, roots):
            raise CheckpointError(
                shown, OUTSIDE_ALLOWED, f"the file opened is {real_path or 'unknown'}"
            )
        if max_bytes is not None and status.st_size > max_bytes:
            raise CheckpointTooLargeError(
                shown, f"the {what} is over the {max_bytes}-byte limit", f"{status.st_size} bytes"
            )
        try:
            data = handle.read() if max_bytes is None else handle.read(max_bytes + 1)
        except OSError as exc:
            raise CheckpointError(shown, f"cannot read the {what}", _reason(exc)) from None
    if max_bytes is not None and len(data) > max_bytes:  # it grew while being read
        raise CheckpointTooLargeError(shown, f"the {what} is over the {max_bytes}-byte limit")
    return data, real_path


def _real_path(fd: int, opened: Path) -> Path | None:
    """Where the open file ``fd`` really is: Linux names it in ``/proc/self/fd``; elsewhere
    ``opened`` if it still names the same file, else None."""
    try:
        return Path(os.readlink(f"/proc/self/fd/{fd}"))
    except OSError:
        pass
    try:
        now, held = os.stat(opened, follow_symlinks=False), os.fstat(fd)
    except OSError:
        return None
    return opened if (now.st_dev, now.st_ino) == (held.st_dev, held.st_ino) else None


def _reason(exc: BaseException) -> str:
    """An exception's text on one line (``strerror`` for OS errors)."""
    text = getattr(exc, "strerror", None) or str(exc) or type(exc).__name__
    return " ".join(str(text).split())


def _parse_metadata(raw: bytes, shown: Path) -> dict[str, Any]:
    try:
        meta = json.loads(raw)
    except (ValueError, RecursionError) as exc:  # ValueError: bad JSON, UTF-8, digits
        message = "nested too deeply" if isinstance(exc, RecursionError) else _reason(exc)
        raise CheckpointError(shown, "metadata: not a readable JSON file", message) from None
    if not isinstance(meta, dict) or meta.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(shown, f"metadata format: expected {CHECKPOINT_FORMAT!r}")
    if meta.get("algorithm") not in ("ddqn", "ddpg"):
        raise CheckpointError(
            shown, "metadata algorithm: expected 'ddqn' or 'ddpg'", f"got {meta.get('algorithm')!r}"
        )
    return meta


def check_archive(zip_bytes: bytes, shown: Path, max_bytes: int | None = None) -> None:
    """Refuse, before anything is decompressed for real, a checkpoint zip that is not a zip,
    has more than :data:`MAX_MEMBERS` members, or expands past ``max_bytes``.

    The expanded size is the sum of the members' declared sizes (``zipfile`` never inflates a
    member past its declared size: a lying header gives a CRC error, not more data), plus what
    the compressed members of the torch archives inside (``*.pth`` are zips too) expand to.
    """
    try:
        archive = zipfile.ZipFile(io.BytesIO(zip_bytes))
    except (zipfile.BadZipFile, ValueError, EOFError) as exc:
        raise CheckpointError(
            shown, "not a valid checkpoint zip (corrupt or truncated)", _reason(exc)
        ) from None
    with archive:
        members = archive.infolist()
        if len(members) > MAX_MEMBERS:
            raise CheckpointError(shown, f"not a checkpoint zip (over {MAX_MEMBERS} members)")
        if max_bytes is None:
            return
        expanded = sum(member.file_size for member in members)
        for member in members:
            if expanded > max_bytes:
                break
            if member.filename.endswith(".pth"):
                expanded += _nested_expansion(archive, member)
        if expanded > max_bytes:
            raise CheckpointTooLargeError(
                shown, f"the checkpoint expands to more than {max_bytes} bytes"
            )


def _nested_expansion(archive: zipfile.ZipFile, member: zipfile.ZipInfo) -> int:
    """What the compressed members of the zip stored in ``member`` expand to (0 when it is not
    a zip, or unreadable: loading it will say so)."""
    try:
        with zipfile.ZipFile(io.BytesIO(archive.read(member))) as inner:
            return sum(
                info.file_size
                for info in inner.infolist()
                if info.compress_type != zipfile.ZIP_STORED
            )
    except (zipfile.BadZipFile, ValueError, EOFError, OSError, NotImplementedError, zlib.error):
        return 0


def load_checkpoint(
    path: Path | str,
    area: AreaConfig = AreaConfig(),
    algorithm: str | None = None,
    device: str = "auto",
    allowed_dirs: Sequence[Path] | None = None,
    max_bytes: int | None = None,
    observation_shape: Sequence[int] | None = None,
) -> tuple[Any, dict[str, Any]]:
    """Load a checkpoint for serving or evaluation: (SB3 model, metadata).

    Raises :class:`CheckpointError` (one line: the file and the problem) for a missing or
    corrupt file, the wrong algorithm, or an observation shape other than ``area``'s. The files
    are read once by :func:`read_checkpoint` (``allowed_dirs``, ``max_bytes``: see there; the
    zip's expanded size is bounded by ``max_bytes`` too, :func:`check_archive`), and the model
    is loaded from those bytes, never from the path again. ``observation_shape``: the shape
    the network must take when it is not the single-UAV observation of ``area`` (a fleet
    agent's ``(9, n_x, n_y)``: :mod:`policies.training.fleet_training`).
    """
    files = read_checkpoint(path, allowed_dirs, max_bytes)
    shown, meta = files.shown, files.metadata
    if algorithm is not None and meta["algorithm"] != algorithm:
        raise CheckpointError(
            shown, f"algorithm: expected {algorithm}, the file holds {meta['algorithm']}"
        )
    expected_shape = (
        [int(n) for n in observation_shape]
        if observation_shape is not None
        else list(area_observation_shape(area))
    )
    if meta.get("observation_shape") != expected_shape:
        raise CheckpointError(
            shown,
            f"observation_shape: built for another area grid (this one needs {expected_shape})",
            f"built for {meta.get('observation_shape')!r}",
        )
    check_archive(files.zip_bytes, shown, max_bytes)
    model_class = algorithm_class(meta["algorithm"])
    try:
        model = model_class.load(
            io.BytesIO(files.zip_bytes),
            device=device,
            custom_objects=moved_objects(files.zip_bytes),
        )
    except Exception as exc:  # SB3 raises many kinds on a damaged file
        raise CheckpointError(
            shown, "cannot load the model", f"{type(exc).__name__}: {_reason(exc)}"
        ) from None
    if list(model.observation_space.shape) != expected_shape:
        raise CheckpointError(
            shown,
            f"observation_shape: the network takes another shape (this area needs "
            f"{expected_shape})",
            f"it takes {list(model.observation_space.shape)}",
        )
    return model, meta


class _MovedUnpickler(pickle.Unpickler):
    """An unpickler that finds a class of :data:`MOVED_MODULES` at its current module."""

    moved = False

    def find_class(self, module: str, name: str) -> Any:
        if module in MOVED_MODULES:
            self.moved = True
            module = MOVED_MODULES[module]
        return super().find_class(module, name)


def moved_objects(checkpoint: bytes | Path) -> dict[str, Any]:
    """SB3's ``custom_objects`` for a checkpoint zip (its bytes or its path) whose ``data``
    names classes at an old module path: each such entry unpickled with the class at its
    current path (:data:`MOVED_MODULES`), the same objects as when it was saved. Empty for a
    checkpoint saved since, and for a file that is not an SB3 zip (loading it says why)."""
    try:
        source = io.BytesIO(checkpoint) if isinstance(checkpoint, bytes) else checkpoint
        with zipfile.ZipFile(source) as archive:
            data = json.loads(archive.read("data"))
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile, zlib.error):
        return {}
    if not isinstance(data, dict):
        return {}
    objects = {}
    for key, item in data.items():
        if not (isinstance(item, dict) and isinstance(item.get(":serialized:"), str)):
            continue
        try:
            raw = base64.b64decode(item[":serialized:"])
        except ValueError:
            continue
        if not any(old.encode() in raw for old in MOVED_MODULES):
            continue
        unpickler = _MovedUnpickler(io.BytesIO(raw))
        try:
            value = unpickler.load()
        except Exception:  # SB3 meets the same entry and says what is wrong with it
            continue
        if unpickler.moved:
            objects[key] = value
    return objects


def load_replay_buffer(model: Any, path: Path) -> None:
    """``model.load_replay_buffer(path)``; a buffer saved before its class moved (a DDQN's
    ``policies.ddqn.MaskedReplayBuffer``) is read with the class at its current path
    (:data:`MOVED_MODULES`) and handed to SB3 as such."""
    try:
        model.load_replay_buffer(path)
    except ModuleNotFoundError as exc:
        if exc.name not in MOVED_MODULES:
            raise
        with open(path, "rb") as handle:
            buffer = _MovedUnpickler(handle).load()
        model.load_replay_buffer(io.BytesIO(pickle.dumps(buffer, pickle.HIGHEST_PROTOCOL)))


# What a policy needs only to learn, never to act: DDPG's critic and the target networks.
_TRAINING_ONLY_NETWORKS = {"ddpg": ("actor_target", "critic", "critic_target"),
                           "ddqn": ("q_net_target",)}  # fmt: skip


def export_checkpoint(
    source: Path,
    dest: Path,
    area: AreaConfig = AreaConfig(),
    serving_only: bool = False,
    observation_shape: Sequence[int] | None = None,
    **extra_metadata: Any,
) -> dict[str, Any]:
    """Write a serving copy of checkpoint ``source`` to ``dest`` (zip + metadata JSON).

    Same network weights (online and target), so it acts exactly as ``source`` does; without
    the optimizer's running statistics (RMSprop's squared-gradient averages: as large as the
    network itself and only needed to continue training; a copy resumed anyway starts them
    afresh) and without a replay buffer (never in the zip); members deflate-compressed. The
    metadata is ``source``'s plus ``extra_metadata`` and an ``exported_from`` note (holding
    ``source``'s own note as ``earlier`` when it was an export itself).

    ``serving_only``: also zero the networks only learning uses (DDPG's critic and both
    targets, DDQN's target Q-network; :data:`_TRAINING_ONLY_NETWORKS`). The acting network is
    untouched, so the copy decides exactly as ``source`` does, and the zip still loads with
    plain stable-baselines3; deflate stores the zeros in a few kilobytes, so the file is about
    a quarter (DDPG) or half (DDQN) of the full one. It cannot continue training: the
    metadata says ``"serving_only": true``.

    ``observation_shape``: what the network must take, as for :func:`load_checkpoint` (a fleet
    checkpoint's: :func:`policies.learned.fleet_checkpoint.fleet_observation_shape`).
    """
    model, meta = load_checkpoint(source, area, device="cpu", observation_shape=observation_shape)
    for name in model._get_torch_save_params()[0]:
        if name.endswith("optimizer"):
            obj = model
            for part in name.split("."):
                obj = getattr(obj, part)
            obj.state.clear()
    dropped = ["optimizer state"]
    if serving_only:
        import torch

        names = _TRAINING_ONLY_NETWORKS[meta["algorithm"]]
        with torch.no_grad():
            for name in names:
                for tensor in getattr(model.policy, name).state_dict().values():
                    tensor.zero_()
        dropped.append(f"{', '.join(names)} (zeroed: only learning uses them)")
    plain, packed = io.BytesIO(), io.BytesIO()
    model.save(plain)
    with (
        zipfile.ZipFile(plain) as src,
        zipfile.ZipFile(packed, "w", compression=zipfile.ZIP_DEFLATED) as out,
    ):
        for item in src.infolist():
            out.writestr(item.filename, src.read(item.filename))
    atomic_write_bytes(Path(dest), packed.getvalue())
    metadata = {
        **{k: v for k, v in meta.items() if k != "format"},
        **extra_metadata,
        "exported_from": {
            "path": str(source),
            "at": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
            "dropped": dropped,
            **({"earlier": meta["exported_from"]} if "exported_from" in meta else {}),
        },
    }
    if serving_only:
        metadata["serving_only"] = True
    atomic_write_json(metadata_path(dest), {"format": CHECKPOINT_FORMAT, **metadata})
    return metadata


def algorithm_class(algorithm: str) -> type:
    if algorithm == "ddqn":
        from policies.learned.ddqn import MaskedDoubleDQN

        return MaskedDoubleDQN
    if algorithm == "ddpg":
        from policies.learned.ddpg import IntervalTargetDDPG

        return IntervalTargetDDPG
    raise ValueError(f"algorithm: expected 'ddqn' or 'ddpg', got {algorithm!r}")
