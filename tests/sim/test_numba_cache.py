"""The numba cache is keyed by the sim package's sources (sim/__init__.py): a kernel compiled
against an older version of a module it calls is never reused."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

import sim

pytestmark = pytest.mark.process  # each test starts an interpreter

SIM = Path(sim.__file__).resolve().parent
PRINT_DIR = "import os, sim; print(os.environ['NUMBA_CACHE_DIR'])"


def _cache_dir(env: dict[str, str]) -> str:
    done = subprocess.run(
        [sys.executable, "-c", PRINT_DIR], env=env, capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


def test_cache_directory_is_named_by_the_hash_of_every_sim_source():
    digest = hashlib.sha256()
    for source in sorted(SIM.rglob("*.py")):
        digest.update(source.relative_to(SIM).as_posix().encode())
        digest.update(source.read_bytes())
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    path = Path(_cache_dir(env))
    assert path.name.endswith(f"numba-{digest.hexdigest()[:16]}")
    assert path.is_dir()


def test_a_cache_directory_the_caller_sets_wins(tmp_path):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    assert _cache_dir(env) == str(tmp_path)


def test_every_numba_kernel_of_the_sim_releases_the_gil():
    """The service decides on its own thread while the event loop answers HTTP and the link
    streams setpoints: a kernel that held the GIL through a 1,000-user decision stalled both
    (PX4's offboard-loss failsafe fired). Every compiled kernel in ``sim`` is ``nogil``."""
    import importlib
    import pkgutil

    from numba.core.registry import CPUDispatcher

    import sim

    kernels = {}
    for info in pkgutil.iter_modules(sim.__path__):
        if info.name.startswith("ns3"):
            continue  # the optional ns-3 backend needs its extra
        module = importlib.import_module(f"sim.{info.name}")
        for name, value in vars(module).items():
            if isinstance(value, CPUDispatcher) and value.__module__ == module.__name__:
                kernels[f"{module.__name__}.{name}"] = value.targetoptions.get("nogil", False)
    assert len(kernels) >= 20
    assert [name for name, nogil in kernels.items() if not nogil] == []
