"""The sweep file: a YAML grid of training runs, read and checked before anything is written.

::

    name: smoke                      # optional; default: the file's stem
    retries: 2                       # optional: a failed trial runs at most 1 + retries times
    test_sets:                       # at least one; a file, or generated into OUT/test_sets/
      small: {generate: {n: 8, users: 3, seed: 4242}}   # also family, total_load_mbps,
      big: {file: ../data/test500.json}                 # environment; file paths are relative
                                                        # to the sweep file
    grid:                            # every combination of these lists is a trial
      algorithm: [ddqn, ddpg]
      strategy: [spec, gen10k]
      episodes: [100, 1000]
      seed: [1, 2, 3]
    train:                           # one value for every trial (any grid key may be here)
      preset: fast
      preset.learning_starts: 64     # any scalar field of policies.training.presets.Preset
      preset.network.hidden: 32      # and of its NetworkPreset
    evaluate:
      final: true                    # the final evaluation on the whole test set (default)
      curve_scenarios: 100           # test scenarios per learning-curve point
      test_sets: [big]               # also evaluate each final checkpoint on these sets

Trial parameters (:data:`PARAMETERS`), each either a ``grid`` list or a ``train`` value:
``algorithm``, ``strategy``, ``episodes``, ``seed`` (required), ``test_set`` (default: the
only one defined), ``preset`` (default ``fast``), ``queueing``, ``world``, ``world_set`` (a
mapping of world settings, as ``--world-set key=value``), ``environment``, ``families``,
``users`` (a count or ``[low, high]``), ``action``, ``envs``, ``checkpoint_every``, and
``preset.<field>`` / ``preset.network.<field>``. ``tupa train``'s own checks run on every
trial before anything starts, so an impossible combination (``action: residual`` with DDQN)
fails naming the trial.

A trial's id is readable and stable: ``<algorithm>-<strategy>-e<episodes>-s<seed>-<hash>``, the
hash covering every parameter and the definition of its test set. Reordering the file, adding
a seed or a new axis value keeps the ids of the trials that were already there; changing what a
trial trains on (a preset field, the test set) gives it a new id, so a resumed sweep never
mistakes an old result for a new one.

Errors are :class:`sim.errors.InputError` naming the file and the key (``tupa`` exits 2).
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

from sim.errors import InputError

SPEC_KEYS: tuple[str, ...] = ("name", "retries", "test_sets", "grid", "train", "evaluate")
EVALUATE_KEYS: tuple[str, ...] = ("final", "curve_scenarios", "test_sets")
GENERATE_KEYS: tuple[str, ...] = (
    "n",
    "users",
    "seed",
    "family",
    "total_load_mbps",
    "environment",
)
REQUIRED: tuple[str, ...] = ("algorithm", "strategy", "episodes", "seed")
PARAMETERS: tuple[str, ...] = (
    *REQUIRED,
    "test_set",
    "preset",
    "queueing",
    "world",
    "world_set",
    "environment",
    "families",
    "users",
    "action",
    "envs",
    "checkpoint_every",
)
DEFAULT_RETRIES = 2
MAX_TRIALS = 10_000
ID_HASH_CHARS = 8

# Preset fields a sweep may not change: they name the preset and its algorithm.
_FIXED_PRESET_FIELDS = ("name", "algorithm", "network")


@dataclass(frozen=True)
class TestSet:
    """A test set: an existing scenario file, or one generated into the sweep directory."""

    name: str
    file: Path | None = None
    generate: dict[str, Any] | None = None
    content_hash: str | None = None  # a file's scenario_set_hash

    def definition(self) -> dict[str, Any]:
        """What the set is, as JSON (part of every trial's id): a file by its content (moving
        it, or running from another directory, keeps the ids), a generated set by its
        settings."""
        if self.file is not None:
            return {"file_hash": self.content_hash}
        return {"generate": dict(self.generate or {})}

    def path(self, out_dir: Path) -> Path:
        """Where the scenario file is: generated sets in ``OUT/test_sets/<name>-<hash>.json``,
        the hash of their settings (a changed definition never reuses an older file)."""
        if self.file is not None:
            return self.file
        canonical = json.dumps(self.generate, sort_keys=True)
        digest = hashlib.sha256(canonical.encode()).hexdigest()[:ID_HASH_CHARS]
        return out_dir / "test_sets" / f"{self.name}-{digest}.json"


@dataclass(frozen=True)
class Trial:
    """One training run of the grid: ``params`` holds every trial parameter (JSON values)."""

    id: str
    params: dict[str, Any]

    @property
    def label(self) -> str:
        """The trained version's name, as its checkpoint evaluates under."""
        return f"{self.params['algorithm']}-{self.params['strategy']}"


@dataclass(frozen=True)
class SweepSpec:
    """A checked sweep file and its trials, in grid order."""

    path: Path
    name: str
    retries: int
    test_sets: dict[str, TestSet]
    trials: tuple[Trial, ...]
    final_eval: bool
    curve_scenarios: int
    extra_test_sets: tuple[str, ...]
    raw: dict[str, Any]

    def trial(self, trial_id: str) -> Trial:
        for trial in self.trials:
            if trial.id == trial_id:
                return trial
        raise KeyError(trial_id)


# --------------------------------------------------------------------------------------------
# Reading


def load_spec(path: Path) -> SweepSpec:
    """Read and check the sweep file ``path``: every key, every trial's training settings and
    every test set file (generated ones are checked, not written). ``InputError`` naming the
    file and the key otherwise."""
    import yaml

    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{path}: no such sweep file") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read: {exc.strerror or exc}") from None
    try:
        document = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" (line {mark.line + 1})" if mark is not None else ""
        problem = getattr(exc, "problem", None) or "invalid YAML"
        raise InputError(f"{path}: not valid YAML{where}: {problem}") from None
    return parse_spec(document, path)


def parse_spec(document: Any, path: Path) -> SweepSpec:
    """Check a parsed sweep document (see the module doc); ``path`` names it in errors and
    anchors relative test-set files."""
    path = Path(path)

    def fail(key: str, message: str) -> InputError:
        return InputError(f"{path}: {key}: {message}")

    if not isinstance(document, dict):
        raise fail("top level", "must be a mapping of keys (name, test_sets, grid, ...)")
    _no_unknown(document, SPEC_KEYS, "", fail)
    name = document.get("name", path.stem)
    if not isinstance(name, str) or not name.strip() or "/" in name:
        raise fail("name", f"must be a non-empty name without '/', got {name!r}")
    retries = document.get("retries", DEFAULT_RETRIES)
    if not _is_int(retries) or retries < 0:
        raise fail("retries", f"must be an integer >= 0, got {retries!r}")
    test_sets = _parse_test_sets(document.get("test_sets"), path, fail)
    final_eval, curve_scenarios, extra = _parse_evaluate(document.get("evaluate"), test_sets, fail)

    grid = document.get("grid", {})
    train = document.get("train", {})
    for key, value in (("grid", grid), ("train", train)):
        if not isinstance(value, dict):
            raise fail(key, "must be a mapping of trial parameters")
    axes: dict[str, list[Any]] = {}
    for key, values in grid.items():
        _check_parameter_name(str(key), f"grid.{key}", fail)
        if not isinstance(values, list) or not values:
            raise fail(f"grid.{key}", f"must be a non-empty list of values, got {values!r}")
        if key in train:
            raise fail(f"grid.{key}", "also given in train: give it in one place")
        normal = [_normalise(key, v, f"grid.{key}", test_sets, fail) for v in values]
        seen = [json.dumps(v, sort_keys=True) for v in normal]
        repeated = sorted({s for s in seen if seen.count(s) > 1})
        if repeated:
            raise fail(f"grid.{key}", f"repeated value {repeated[0]}")
        axes[str(key)] = normal
    fixed = {}
    for key, value in train.items():
        _check_parameter_name(str(key), f"train.{key}", fail)
        fixed[str(key)] = _normalise(key, value, f"train.{key}", test_sets, fail)
    if "test_set" not in axes and "test_set" not in fixed:
        if len(test_sets) > 1:
            raise fail(
                "grid.test_set",
                f"several test sets defined ({', '.join(test_sets)}): "
                "say which the trials use (grid.test_set or train.test_set)",
            )
        fixed["test_set"] = next(iter(test_sets))
    fixed.setdefault("preset", "fast")
    for key in REQUIRED:
        if key not in axes and key not in fixed:
            raise fail(f"grid.{key}", "missing (give a list in grid or a value in train)")

    count = math.prod(len(v) for v in axes.values())
    if count > MAX_TRIALS:
        raise fail("grid", f"{count} trials, more than {MAX_TRIALS}: split the sweep")
    trials = []
    for combination in itertools.product(*axes.values()):
        params = {**fixed, **dict(zip(axes, combination, strict=True))}
        params = {key: params[key] for key in sorted(params)}
        trial = Trial(id=trial_id(params, test_sets[params["test_set"]]), params=params)
        _check_trial(trial, test_sets, curve_scenarios, final_eval, path)
        trials.append(trial)
    return SweepSpec(
        path=path,
        name=name,
        retries=int(retries),
        test_sets=test_sets,
        trials=tuple(trials),
        final_eval=final_eval,
        curve_scenarios=curve_scenarios,
        extra_test_sets=extra,
        raw=document,
    )


def trial_id(params: dict[str, Any], test_set: TestSet) -> str:
    """``<algorithm>-<strategy>-e<episodes>-s<seed>-<hash of everything>``."""
    canonical = json.dumps(
        {"params": params, "test_set": test_set.definition()}, sort_keys=True, default=str
    )
    digest = hashlib.sha256(canonical.encode()).hexdigest()[:ID_HASH_CHARS]
    p = params
    return f"{p['algorithm']}-{p['strategy']}-e{p['episodes']}-s{p['seed']}-{digest}"


# --------------------------------------------------------------------------------------------
# Pieces


def _no_unknown(mapping: dict, known: tuple[str, ...], prefix: str, fail: Any) -> None:
    for key in mapping:
        if key not in known:
            raise fail(f"{prefix}{key}", f"unknown key (known: {', '.join(known)})")


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _preset_fields() -> dict[str, Any]:
    """``{"preset.<field>": default, "preset.network.<field>": default}`` for scalar fields."""
    from policies.training.presets import NetworkPreset, get_preset

    base = get_preset("paper", "ddqn")
    known = {
        f"preset.{f.name}": getattr(base, f.name)
        for f in fields(base)
        if f.name not in _FIXED_PRESET_FIELDS
    }
    known.update(
        {
            f"preset.network.{f.name}": getattr(NetworkPreset(), f.name)
            for f in fields(NetworkPreset)
        }
    )
    return known


def _check_parameter_name(key: str, where: str, fail: Any) -> None:
    if key in PARAMETERS or key in _preset_fields():
        return
    hint = "preset.<field> (policies/training/presets.py)" if key.startswith("preset.") else ""
    raise fail(
        where,
        f"unknown trial parameter (known: {', '.join(PARAMETERS)}, {hint or 'preset.<field>'})",
    )


def _normalise(key: str, value: Any, where: str, test_sets: dict[str, TestSet], fail: Any) -> Any:
    """One trial parameter's value checked and in canonical JSON form."""
    from policies.training.presets import ALGORITHMS, PRESET_NAMES
    from policies.training.training import STRATEGIES
    from sim.config import QUEUEING_CHOICES, environment_problem
    from sim.scenarios import FAMILIES

    choices = {
        "algorithm": ALGORITHMS,
        "strategy": STRATEGIES,
        "preset": PRESET_NAMES,
        "queueing": QUEUEING_CHOICES,
        "action": ("coordinates", "residual"),
        "test_set": tuple(test_sets),
    }
    if key == "environment":  # a named one or site:PATH, the site there
        problem = environment_problem(value, on_disk=True)
        if problem is not None:
            raise fail(where, problem)
        return value
    if key in choices:
        if value not in choices[key]:
            raise fail(where, f"must be one of {', '.join(choices[key])}, got {value!r}")
        return value
    if key in ("episodes", "envs", "checkpoint_every", "seed"):
        low = 0 if key == "seed" else 1
        if not _is_int(value) or value < low:
            raise fail(where, f"must be an integer >= {low}, got {value!r}")
        return value
    if key == "world":
        from sim.world import WORLDS

        names = [n.strip() for n in value.split(",")] if isinstance(value, str) else [None]
        for name in names:
            if name not in WORLDS:
                raise fail(
                    where,
                    f"unknown world {name!r} (known: {', '.join(WORLDS)}; "
                    "several separated by commas)",
                )
        return ",".join(names)
    if key == "world_set":
        if not isinstance(value, dict):
            raise fail(where, f"must be a mapping of world settings, got {value!r}")
        return {str(k): v for k, v in value.items()}
    if key == "families":
        items = [value] if isinstance(value, str) else value
        if not isinstance(items, list) or not items or any(f not in FAMILIES for f in items):
            raise fail(where, f"must be families among {', '.join(FAMILIES)}, got {value!r}")
        return list(items)
    if key == "users":
        if value is None:
            return None
        pair = [value, value] if _is_int(value) else value
        if (
            not isinstance(pair, list)
            or len(pair) != 2
            or not all(_is_int(u) and u >= 1 for u in pair)
            or pair[0] > pair[1]
        ):
            raise fail(where, f"must be a count or [low, high], got {value!r}")
        return list(pair)
    default = _preset_fields()[key]
    if isinstance(default, tuple):
        if not isinstance(value, list) or not all(_is_int(v) and v >= 1 for v in value):
            raise fail(where, f"must be a list of positive integers, got {value!r}")
        return list(value)
    if isinstance(default, (bool, str)):
        if type(value) is not type(default):
            raise fail(where, f"must be a {type(default).__name__}, got {value!r}")
        return value
    if isinstance(default, int):
        if not _is_int(value):
            raise fail(where, f"must be an integer, got {value!r}")
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise fail(where, f"must be a number, got {value!r}")
    return float(value)


def _parse_test_sets(raw: Any, path: Path, fail: Any) -> dict[str, TestSet]:
    from sim.config import environment_problem
    from sim.files import load_scenarios, scenario_set_hash
    from sim.scenarios import FAMILIES, MAX_USERS

    if not isinstance(raw, dict) or not raw:
        raise fail(
            "test_sets",
            "missing: name at least one test set ({file: ...} or {generate: {n, users, seed}})",
        )
    sets = {}
    for name, definition in raw.items():
        where = f"test_sets.{name}"
        if not isinstance(name, str) or not name or "/" in name:
            raise fail(where, "must be a name without '/'")
        if not isinstance(definition, dict) or len(definition) != 1:
            raise fail(where, "must be {file: PATH} or {generate: {...}}")
        kind, value = next(iter(definition.items()))
        if kind == "file":
            if not isinstance(value, str) or not value:
                raise fail(f"{where}.file", f"must be a path, got {value!r}")
            file = Path(value) if Path(value).is_absolute() else path.parent / value
            if not file.is_file():
                raise fail(f"{where}.file", f"no such scenario file: {file}")
            try:
                area, scenarios = load_scenarios(file)
            except InputError as exc:
                raise fail(f"{where}.file", str(exc)) from None
            if not scenarios:
                raise fail(f"{where}.file", f"{file} holds no scenarios")
            sets[name] = TestSet(
                name=name, file=file.resolve(), content_hash=scenario_set_hash(area, scenarios)
            )
        elif kind == "generate":
            if not isinstance(value, dict):
                raise fail(f"{where}.generate", "must be a mapping (n, users, seed, ...)")
            _no_unknown(value, GENERATE_KEYS, f"{where}.generate.", fail)
            settings = {
                "n": 100,
                "users": 3,
                "seed": 4242,
                "family": "exponential",
                "total_load_mbps": 40.0,
                "environment": "open",
                **value,
            }
            n, users, seed = settings["n"], settings["users"], settings["seed"]
            if not _is_int(n) or n < 1:
                raise fail(f"{where}.generate.n", f"must be an integer >= 1, got {n!r}")
            if not _is_int(users) or not 1 <= users <= MAX_USERS:
                raise fail(f"{where}.generate.users", f"must be in 1..{MAX_USERS}, got {users!r}")
            if not _is_int(seed) or seed < 0:
                raise fail(f"{where}.generate.seed", f"must be an integer >= 0, got {seed!r}")
            if settings["family"] not in FAMILIES:
                raise fail(f"{where}.generate.family", f"must be one of {', '.join(FAMILIES)}")
            problem = environment_problem(settings["environment"], on_disk=True)
            if problem is not None:
                raise fail(f"{where}.generate.environment", problem)
            load = settings["total_load_mbps"]
            if isinstance(load, bool) or not isinstance(load, (int, float)) or not load > 0:
                raise fail(f"{where}.generate.total_load_mbps", f"must be positive, got {load!r}")
            settings["total_load_mbps"] = float(load)
            sets[name] = TestSet(name=name, generate=settings)
        else:
            raise fail(f"{where}.{kind}", "unknown key (known: file, generate)")
    return sets


def _parse_evaluate(
    raw: Any, test_sets: dict[str, TestSet], fail: Any
) -> tuple[bool, int, tuple[str, ...]]:
    raw = {} if raw is None else raw
    if not isinstance(raw, dict):
        raise fail("evaluate", "must be a mapping (final, curve_scenarios, test_sets)")
    _no_unknown(raw, EVALUATE_KEYS, "evaluate.", fail)
    final = raw.get("final", True)
    if not isinstance(final, bool):
        raise fail("evaluate.final", f"must be true or false, got {final!r}")
    curve = raw.get("curve_scenarios", 100)
    if not _is_int(curve) or curve < 1:
        raise fail("evaluate.curve_scenarios", f"must be an integer >= 1, got {curve!r}")
    extra = raw.get("test_sets", [])
    if not isinstance(extra, list):
        raise fail("evaluate.test_sets", "must be a list of test set names")
    for name in extra:
        if name not in test_sets:
            raise fail(
                "evaluate.test_sets", f"{name!r} is not in test_sets ({', '.join(test_sets)})"
            )
    return final, curve, tuple(extra)


def _check_trial(
    trial: Trial, test_sets: dict[str, TestSet], curve: int, final: bool, path: Path
) -> None:
    """``tupa train``'s own checks on the trial's settings (nothing is read or written)."""
    try:
        train_config(
            trial,
            test_sets[trial.params["test_set"]].path(Path(".")),
            Path("."),
            curve_scenarios=curve,
            final_eval=final,
        )
    except InputError as exc:
        shown = ", ".join(f"{k}={v}" for k, v in trial.params.items() if k in PARAMETERS)
        raise InputError(f"{path}: grid: impossible trial ({shown}): {exc}") from None


def train_config(
    trial: Trial,
    test_file: Path,
    out_dir: Path,
    curve_scenarios: int = 100,
    final_eval: bool = True,
) -> Any:
    """The :class:`policies.training.training.TrainConfig` of ``trial`` (what ``tupa train`` would
    build from the same options), training into ``out_dir``."""
    from policies.training.presets import NetworkPreset, get_preset
    from policies.training.training import TrainConfig

    p = trial.params
    action = p.get("action", "coordinates")
    try:
        preset = get_preset(p["preset"], p["algorithm"], action)
    except ValueError as exc:
        raise InputError(f"--{exc}") from None
    changes = {k.removeprefix("preset."): v for k, v in p.items() if k.startswith("preset.")}
    network = {k.removeprefix("network."): v for k, v in changes.items() if "." in k}
    scalars = {
        k: tuple(v) if isinstance(v, list) else v for k, v in changes.items() if "." not in k
    }
    if network:
        values = {k: tuple(v) if isinstance(v, list) else v for k, v in network.items()}
        scalars["network"] = replace(preset.network, **values)
    preset = replace(preset, **scalars)
    if not isinstance(preset.network, NetworkPreset):  # pragma: no cover - replace keeps it
        raise InputError("preset.network: not a network preset")
    world_set = [f"{k}={v}" for k, v in (p.get("world_set") or {}).items()]
    if "environment" in p:
        world_set.append(f"environment={p['environment']}")
    users = p.get("users")
    return TrainConfig(
        algorithm=p["algorithm"],
        strategy=p["strategy"],
        episodes=p["episodes"],
        preset=preset,
        seed=p["seed"],
        test_scenarios=test_file,
        out_dir=out_dir,
        queueing=p.get("queueing", "fq-codel"),
        world=p.get("world", "paper"),
        world_set=tuple(world_set),
        families=tuple(p.get("families", ["exponential"])),
        users=(users[0], users[1]) if users else None,
        action=action,
        envs=p.get("envs", 1),
        checkpoint_every=p.get("checkpoint_every", 500),
        curve_scenarios=curve_scenarios,
        final_eval=final_eval,
        progress=False,
    )


def write_test_sets(spec: SweepSpec, out_dir: Path) -> dict[str, Path]:
    """Generate the spec's generated test sets into ``OUT/test_sets/`` (once: an existing file
    is kept) and return every set's path by name."""
    from sim.config import AreaConfig
    from sim.files import save_scenarios
    from sim.scenarios import generate_scenarios

    paths = {}
    for name, test_set in spec.test_sets.items():
        path = test_set.path(out_dir)
        if test_set.generate is not None and not path.exists():
            g = test_set.generate
            area = AreaConfig(environment=g["environment"])
            scenarios = generate_scenarios(
                g["n"],
                g["users"],
                seed=g["seed"],
                area=area,
                total_load_bps=g["total_load_mbps"] * 1e6,
                family=g["family"],
            )
            generator = {
                "family": g["family"],
                "users": g["users"],
                "seed": g["seed"],
                "total_load_bps": g["total_load_mbps"] * 1e6,
            }
            save_scenarios(path, area, scenarios, extra={"generator": generator})
        paths[name] = path
    return paths
