"""Hostile checkpoints for the security tests: copies of the shipped DDQN with extras.

A checkpoint is an SB3 zip whose ``data`` member may hold pickled objects, and SB3 unpickles them
while loading. :func:`crafted_checkpoint` puts :class:`Call` objects there, so that *loading* the
copy runs a harmless call of the test's choosing (make a marker directory, sleep): the test can
then tell whether a file was loaded at all, not only whether it was served. It also pads members
(a zip bomb of zeros) for the size limits.
"""

from __future__ import annotations

import base64
import json
import pickle
import zipfile
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import pytest

from service.policy_runtime import SHIPPED_DDQN

PAYLOAD_KEY = "tupa_test_payload"


class Call:
    """Pickles as the call ``func(*args)``: what any pickle may do when it is loaded."""

    def __init__(self, func: Callable[..., Any], *args: Any) -> None:
        self.func = func
        self.args = args

    def __reduce__(self) -> tuple[Callable[..., Any], tuple[Any, ...]]:
        return self.func, self.args


def shipped_or_skip() -> Path:
    if not SHIPPED_DDQN.is_file():
        pytest.skip(f"the shipped DDQN checkpoint {SHIPPED_DDQN} is not in this checkout")
    return SHIPPED_DDQN


def crafted_checkpoint(
    dest: Path,
    *,
    strategy: str = "gen10k",
    calls: Sequence[Call] = (),
    data_padding: int = 0,
    extra_members: Mapping[str, bytes] | None = None,
    replace_members: Mapping[str, bytes] | None = None,
) -> Path:
    """Write a copy of the shipped DDQN to ``dest`` (with ``dest.json`` beside it) and return
    ``dest``.

    ``strategy`` goes into the metadata (the served name is ``ddqn-STRATEGY``); ``calls`` run when
    SB3 loads the zip; ``data_padding`` bytes of JSON whitespace are appended to ``data`` (still
    valid JSON, deflated to almost nothing); ``extra_members`` are added and ``replace_members``
    replace members of the same name.
    """
    source = shipped_or_skip()
    extra_members = extra_members or {}
    replace_members = replace_members or {}
    dest.parent.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(source) as src, zipfile.ZipFile(dest, "w") as out:
        for info in src.infolist():
            data = replace_members.get(info.filename) or src.read(info.filename)
            if info.filename == "data" and (calls or data_padding):
                document = json.loads(data)
                if calls:
                    document[PAYLOAD_KEY] = {
                        ":type:": "<class 'tuple'>",
                        ":serialized:": base64.b64encode(pickle.dumps(tuple(calls))).decode(),
                    }
                data = json.dumps(document).encode() + b" " * data_padding
            out.writestr(info.filename, data, compress_type=zipfile.ZIP_DEFLATED, compresslevel=1)
        for name, data in extra_members.items():
            out.writestr(name, data, compress_type=zipfile.ZIP_DEFLATED, compresslevel=1)
    metadata = json.loads(source.with_suffix(".json").read_text())
    metadata["strategy"] = strategy
    metadata.pop("name", None)  # the shipped one's name; a copy is named ddqn-STRATEGY
    # A copy stands for any servable checkpoint: the shipped DDQN's own refusal to be served
    # (it dithers on a real vehicle) is tests/policies/test_shipped.py's.
    metadata.pop("not_for_serving", None)
    dest.with_suffix(".json").write_text(json.dumps(metadata))
    return dest
