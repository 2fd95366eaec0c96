"""Malformed files for the scenario, case and checkpoint loaders: only InputError comes out.

Hypothesis writes JSON documents of any shape (and valid documents with one part replaced by
anything), random bytes, truncated and bit-flipped files, and very deep or very long numbers.
``load_scenarios``, ``load_cases`` and ``load_checkpoint`` either load them or raise
:class:`sim.errors.InputError` with one line naming the file; no other exception escapes.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from policies.learned.checkpoints import CHECKPOINT_FORMAT, load_checkpoint, metadata_path
from service.policy_runtime import SHIPPED_DDQN
from sim.config import AreaConfig
from sim.errors import InputError
from sim.files import cases_document, load_cases, load_scenarios, scenarios_document
from sim.scenarios import Case, Scenario

AREA = AreaConfig()
FUZZ = settings(
    max_examples=150,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)

# --------------------------------------------------------------------------- documents

json_scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(),
    st.integers(min_value=10**300, max_value=10**400),  # too large for a float
    st.floats(allow_nan=True, allow_infinity=True),  # json.dumps writes NaN, Infinity
    st.text(max_size=20),
    st.sampled_from(["tupa-scenarios/1", "tupa-cases/1", CHECKPOINT_FORMAT, "ddqn", "ddpg"]),
)
json_values = st.recursive(
    json_scalars,
    lambda children: st.one_of(
        st.lists(children, max_size=5),
        st.dictionaries(st.text(max_size=10), children, max_size=5),
        st.dictionaries(
            st.sampled_from(["id", "x_m", "y_m", "z_m", "load_bps", "users", "uav", "area"]),
            children,
            max_size=4,
        ),
    ),
    max_leaves=25,
)

VALID_SCENARIOS = scenarios_document(
    AREA,
    [
        Scenario("s0", np.array([[10.0, 20.0], [400.0, 300.0]]), np.array([30e6, 10e6])),
        Scenario("s1", np.array([[250.0, 250.0]]), np.array([40e6])),
    ],
)
VALID_CASES = cases_document(
    AREA,
    [
        Case(
            "c0",
            np.array([250.0, 250.0, 25.0]),
            np.array([[10.0, 20.0], [400.0, 300.0]]),
            np.array([30e6, 10e6]),
        )
    ],
)


def _paths(doc: Any, prefix: tuple[Any, ...] = ()) -> Iterator[tuple[Any, ...]]:
    """Every path into a JSON document (keys and list indices)."""
    yield prefix
    if isinstance(doc, dict):
        for key, value in doc.items():
            yield from _paths(value, (*prefix, key))
    elif isinstance(doc, list):
        for index, value in enumerate(doc):
            yield from _paths(value, (*prefix, index))


def _replace(doc: Any, path: tuple[Any, ...], value: Any) -> Any:
    if not path:
        return value
    copy = json.loads(json.dumps(doc))
    node = copy
    for part in path[:-1]:
        node = node[part]
    node[path[-1]] = value
    return copy


def mutated(valid: dict[str, Any]) -> st.SearchStrategy[Any]:
    """``valid`` with one part (anything from the whole document to one number) replaced, or one
    key dropped or added."""
    paths = list(_paths(valid))

    @st.composite
    def build(draw: Any) -> Any:
        path = draw(st.sampled_from(paths))
        how = draw(st.sampled_from(["replace", "drop", "add"]))
        if how == "replace" or not path:
            return _replace(valid, path, draw(json_values))
        parent = json.loads(json.dumps(valid))  # a copy: the valid document stays valid
        node = parent
        for part in path[:-1]:
            node = node[part]
        if how == "drop":
            del node[path[-1]]
        elif isinstance(node, dict):
            node[draw(st.text(max_size=8))] = draw(json_values)
        else:
            node.append(draw(json_values))
        return parent

    return build()


def documents(valid: dict[str, Any]) -> st.SearchStrategy[bytes]:
    """File contents: JSON (any shape, or a near-valid document), random bytes, truncated."""
    as_json = st.one_of(json_values, mutated(valid)).map(lambda d: json.dumps(d).encode())
    text = json.dumps(valid).encode()
    return st.one_of(
        as_json,
        as_json,
        st.binary(max_size=300),
        st.integers(0, len(text) - 1).map(lambda n: text[:n]),  # truncated
        st.tuples(st.integers(0, len(text) - 1), st.integers(0, 255)).map(
            lambda p: text[: p[0]] + bytes([p[1]]) + text[p[0] + 1 :]  # one byte changed
        ),
        st.sampled_from(
            [
                b"[" * 100_000 + b"]" * 100_000,  # nested too deeply for the parser
                b'{"format": ' + b"9" * 5000 + b"}",  # an integer over Python's digit limit
                text.replace(b"30000000.0", b"3" + b"0" * 5000),
                text.replace(b"30000000.0", b"1e999"),  # infinity, spelt as a number
                text.replace(b"30000000.0", b"NaN"),
                b"\xef\xbb\xbf" + text,  # a UTF-8 byte-order mark
                text.decode().encode("utf-16"),
                b"",
                b"null",
            ]
        ),
    )


def _check_one_line_error(error: InputError, path: Path) -> None:
    message = str(error)
    assert "\n" not in message and "\r" not in message, message
    assert message.startswith(str(path)), message


@pytest.fixture
def workdir() -> Iterator[Path]:
    # hypothesis runs many examples per test: one directory for all of them, cleaned at the end
    path = Path(tempfile.mkdtemp(prefix="tupa-fuzz-"))
    yield path
    shutil.rmtree(path, ignore_errors=True)


@pytest.mark.parametrize(
    ("loader", "valid"),
    [
        pytest.param(load_scenarios, VALID_SCENARIOS, id="scenarios"),
        pytest.param(load_cases, VALID_CASES, id="cases"),
    ],
)
def test_scenario_and_case_loaders_raise_only_input_error(
    workdir: Path, loader: Callable[[Path], Any], valid: dict[str, Any]
) -> None:
    path = workdir / "input.json"
    path.write_text(json.dumps(valid))
    loader(path)  # the valid document loads

    @given(content=documents(valid))
    @FUZZ
    def check(content: bytes) -> None:
        path.write_bytes(content)
        try:
            loader(path)
        except InputError as error:
            _check_one_line_error(error, path)

    check()


def test_missing_file_and_directory_are_input_errors(workdir: Path) -> None:
    for loader in (load_scenarios, load_cases):
        for path in (workdir / "absent.json", workdir):
            with pytest.raises(InputError) as info:
                loader(path)
            _check_one_line_error(info.value, path)


# --------------------------------------------------------------------------- checkpoints

VALID_METADATA: dict[str, Any] = {
    "format": CHECKPOINT_FORMAT,
    "algorithm": "ddqn",
    "observation_shape": [6, 20, 20],
    "area": AREA.to_dict(),
    "episodes": 10,
}


def _zip_bytes() -> bytes:
    import io
    import zipfile

    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as z:
        z.writestr("data", "{}")
    return buffer.getvalue()


def test_checkpoint_metadata_fuzz_raises_only_input_error(workdir: Path) -> None:
    """Any metadata JSON beside a zip that is not a checkpoint (loading stops at the first
    problem it finds: the metadata, then the zip)."""
    zip_path = workdir / "model.zip"
    zip_path.write_bytes(_zip_bytes())
    meta_path = metadata_path(zip_path)

    @given(content=documents(VALID_METADATA))
    @FUZZ
    def check(content: bytes) -> None:
        meta_path.write_bytes(content)
        with pytest.raises(InputError) as info:
            load_checkpoint(zip_path, AREA, device="cpu")
        message = str(info.value)
        assert "\n" not in message, message
        assert str(zip_path) in message or str(meta_path) in message, message

    check()


@pytest.fixture(scope="module")
def shipped() -> tuple[bytes, bytes]:
    if not SHIPPED_DDQN.is_file():
        pytest.skip(f"the shipped DDQN checkpoint {SHIPPED_DDQN} is not in this checkout")
    return SHIPPED_DDQN.read_bytes(), metadata_path(SHIPPED_DDQN).read_bytes()


def test_damaged_copies_of_the_shipped_checkpoint_raise_only_input_error(
    workdir: Path, shipped: tuple[bytes, bytes]
) -> None:
    """Truncated, bit-flipped and random-byte zips with the real metadata beside them."""
    data, meta = shipped
    zip_path = workdir / "ddqn.zip"
    metadata_path(zip_path).write_bytes(meta)
    cut = st.integers(0, len(data) - 1)
    damaged = st.one_of(
        cut.map(lambda n: data[:n]),  # truncated
        st.tuples(cut, st.integers(1, 255)).map(  # one byte flipped (the zip still opens)
            lambda p: data[: p[0]] + bytes([data[p[0]] ^ p[1]]) + data[p[0] + 1 :]
        ),
        st.binary(max_size=2000),
    )

    @given(content=damaged)
    @settings(FUZZ, max_examples=12)
    def check(content: bytes) -> None:
        assume(content != data)
        zip_path.write_bytes(content)
        try:
            load_checkpoint(zip_path, AREA, device="cpu")
        except InputError as error:
            message = str(error)
            assert "\n" not in message, message
            assert message.startswith(str(zip_path)), message

    check()


def test_checkpoint_path_problems_are_input_errors(workdir: Path) -> None:
    for path in (workdir / "absent.zip", workdir, workdir / ("x" * 300 + ".zip")):
        with pytest.raises(InputError) as info:
            load_checkpoint(path, AREA, device="cpu")
        assert "\n" not in str(info.value)
