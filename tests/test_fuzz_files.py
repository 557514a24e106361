"""Fuzz register-map and dialect files: any content loads or raises DriveConfigError in one line.

Two sources of input: random TOML text written to a file, and the shipped
files with random damage (keys removed, values replaced by values of any
type), which reaches far deeper into the validation than random text does.
"""

from __future__ import annotations

import copy

from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from servobench.drivers.modbus.regmap import load_map, parse_map, resolve_map
from servobench.drivers.serial.dialect import dialect_path, load_dialect, parse_dialect
from servobench.errors import DriveConfigError

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

FUZZ = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
SHIPPED_MAP = tomllib.loads(resolve_map("servobench-sim").read_text(encoding="utf-8"))
SHIPPED_DIALECT = tomllib.loads(dialect_path("odrive").read_text(encoding="utf-8"))

_SCALARS = st.one_of(
    st.integers(-(2**40), 2**40),
    st.sampled_from([0, 1, -1, 0xFFFF, 0x10000, 125, 126]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.booleans(),
    st.text(max_size=12),
    st.sampled_from(["", "big", "little", "int32", "float32", "string", "holding", "input", "r",
                     "w", "rw", "register", "xor", "none", "\n", "\r\n", "{x} {v}", "{u}", "{",
                     "c {axis} {u}", "{bogus}", "{x:>4}", ".6f", "q"]),
)  # fmt: skip
_VALUES = st.recursive(
    _SCALARS,
    lambda inner: st.one_of(
        st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=6), inner, max_size=3)
    ),
    max_leaves=6,
)


def check_error(err: DriveConfigError) -> None:
    message = str(err)
    assert message and len(message.splitlines()) == 1, repr(message)


def _paths(doc: object, prefix: tuple = ()) -> list[tuple]:
    """Every key path (dict keys and list indices) in a parsed TOML document."""
    out = []
    if isinstance(doc, dict):
        for k, v in doc.items():
            out.append((*prefix, k))
            out += _paths(v, (*prefix, k))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            out.append((*prefix, i))
            out += _paths(v, (*prefix, i))
    return out


@st.composite
def damaged(draw: st.DrawFn, shipped: dict) -> dict:
    """``shipped`` with 1-4 random keys removed, replaced or added."""
    doc = copy.deepcopy(shipped)
    for _ in range(draw(st.integers(1, 4))):
        paths = _paths(doc)
        if not paths:
            break
        path = draw(st.sampled_from(paths))
        parent = doc
        for key in path[:-1]:
            parent = parent[key]
        action = draw(st.sampled_from(["delete", "replace", "add"]))
        if action == "delete":
            del parent[path[-1]]
        elif action == "replace":
            parent[path[-1]] = draw(_VALUES)
        elif isinstance(parent, dict):
            parent[draw(st.text(max_size=8))] = draw(_VALUES)
    return doc


def _toml_text() -> st.SearchStrategy[str]:
    lines = st.one_of(
        st.text(max_size=30),
        st.sampled_from(["[map]", "[registers.velocity]", "[dialect]", "[commands]", "x = 1",
                         "name = \"n\"", "address = 70000", "[[setup]]", "a = [1, \"b\"]",
                         "\"k\\nk\" = 1", "[units]"]),
    )  # fmt: skip
    return st.lists(lines, max_size=12).map("\n".join)


@FUZZ
@given(damaged(SHIPPED_MAP))
@example({"map": {"name": "m", "max_gap": 200}})
def test_damaged_register_maps(doc: dict) -> None:
    try:
        regmap = parse_map(doc, "fuzz.toml")
    except DriveConfigError as err:
        check_error(err)
        return
    assert regmap.blocks and "velocity" in regmap.feedback.names


@FUZZ
@given(damaged(SHIPPED_DIALECT))
def test_damaged_dialects(doc: dict) -> None:
    try:
        dialect = parse_dialect(doc, "fuzz.toml")
    except DriveConfigError as err:
        check_error(err)
        return
    assert dialect.has("feedback") and "feedback" in dialect.replies


@FUZZ
@given(_toml_text(), st.sampled_from(["map", "dialect"]))
@example('[map]\nname = "m"\n[registers."a\\nb"]\naddress = 1', "map")
@example('[dialect]\n"a\\rb" = 1', "dialect")
@example("\udcff", "map")
def test_any_file_content(tmp_path_factory, text: str, which: str) -> None:
    path = tmp_path_factory.mktemp("fuzz") / "file.toml"
    path.write_bytes(text.encode("utf-8", "surrogateescape"))
    try:
        (load_map if which == "map" else load_dialect)(str(path))
    except DriveConfigError as err:
        check_error(err)


def test_folders_and_devices_are_no_files(tmp_path) -> None:
    for loader in (load_map, load_dialect):
        for path in (str(tmp_path) + "/", "/dev/zero", str(tmp_path / "none.toml")):
            try:
                loader(path)
            except DriveConfigError as err:
                check_error(err)
            else:
                raise AssertionError(f"{loader.__name__}({path!r}) did not fail")
