"""The numba cache is keyed by the sim package's sources (sim/__init__.py): a kernel compiled
against an older version of a module it calls is never reused."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import sim

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
    for source in sorted(SIM.glob("*.py")):
        digest.update(source.name.encode())
        digest.update(source.read_bytes())
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    path = Path(_cache_dir(env))
    assert path.name.endswith(f"numba-{digest.hexdigest()[:16]}")
    assert path.is_dir()


def test_a_cache_directory_the_caller_sets_wins(tmp_path):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    assert _cache_dir(env) == str(tmp_path)
