"""The one TOML table reader: checked access, and errors that name the file, the table and the key."""

from __future__ import annotations

import math

import pytest

from servobench.errors import DriveConfigError, UsageError
from servobench.tomlfile import SENTENCE, TomlTable, read_toml

DOC = {
    "map": {"name": "m", "fc23": True, "gap": 3, "scale": 2, "order": "big", "words": [1, 2]},
    "registers": {"velocity": {"address": 36}},
    "setup": [{"address": 1}, {"address": 2}],
}


def keyed(doc=DOC) -> TomlTable:
    return TomlTable(doc, "my.toml")


def sentence(doc=DOC) -> TomlTable:
    return TomlTable(doc, "dialect my.toml", wording=SENTENCE)


def test_typed_get_with_defaults():
    head = keyed().table("map")
    assert head.get("name", str) == "m"
    assert head.get("fc23", bool) is True
    assert head.get("gap", int) == 3
    assert head.get("scale", float) == 2  # TOML writes whole numbers without a point
    assert head.number("scale") == 2.0 and isinstance(head.number("scale"), float)
    assert head.get("colour", str, "red") == "red"
    assert head.get("colour", str, None) is None
    assert head.choice("order", ("big", "little"), "little") == "big"
    assert head.choice("other_order", ("big", "little"), "little") == "little"
    assert head.sequence("words", int) == (1, 2)
    assert head.sequence("more_words", int, ()) == ()
    head.done()


@pytest.mark.parametrize(
    ("read", "message"),
    [
        (lambda t: t.get("name", int), "my.toml: [map] name: expected int, got 'm'"),
        (lambda t: t.get("fc23", int), "my.toml: [map] fc23: expected int, got True"),
        (lambda t: t.get("fc23", float), "my.toml: [map] fc23: expected number, got True"),
        (lambda t: t.get("gap", bool), "my.toml: [map] gap: expected bool, got 3"),
        (lambda t: t.get("gap", str), "my.toml: [map] gap: expected string, got 3"),
        (lambda t: t.sequence("words", str), "my.toml: [map] words: expected list of strings, got [1, 2]"),
        (lambda t: t.sequence("name", int), "my.toml: [map] name: expected list of ints, got 'm'"),
        (lambda t: t.table("name"), "my.toml: [map] name: expected table, got 'm'"),
    ],
)
def test_wrong_type_names_file_table_key_and_value(read, message):
    with pytest.raises(DriveConfigError) as info:
        read(keyed().table("map"))
    assert str(info.value) == message


def test_missing_required_key_and_table():
    with pytest.raises(DriveConfigError) as info:
        keyed().table("map").get("address", int)
    assert str(info.value) == "my.toml: [map] address: is required"
    with pytest.raises(DriveConfigError) as info:
        keyed().table("units")
    assert str(info.value) == "my.toml: [top level] units: is required"
    assert keyed().table("units", required=False).data == {}
    with pytest.raises(DriveConfigError) as info:
        keyed().table("registers").require(["velocity", "position"])
    assert str(info.value) == "my.toml: [registers] position: is required"


def test_bad_choice_names_the_options():
    with pytest.raises(DriveConfigError) as info:
        keyed().table("map").choice("order", ("little", "middle"))
    assert str(info.value) == "my.toml: [map] order: 'big' is not one of 'little', 'middle'"


def test_unknown_keys_are_those_never_asked_for():
    head = keyed().table("map")
    head.get("name", str)
    head.get("description", str, "")  # asked for, absent: still known
    with pytest.raises(DriveConfigError) as info:
        head.done()
    assert str(info.value) == (
        "my.toml: [map] fc23, gap, scale, order, words: unknown keys (known: description, name)"
    )
    vel = keyed().table("registers").table("velocity")
    with pytest.raises(DriveConfigError) as info:
        vel.done()
    assert str(info.value) == "my.toml: [registers.velocity] address: unknown key (known: none)"


def test_allowed_keys_are_declared_up_front():
    regs = keyed().table("registers")
    assert regs.allow({"velocity", "position"}, noun="register") == ["velocity"]
    regs.done()  # every allowed key counts as read
    with pytest.raises(DriveConfigError) as info:
        keyed().allow(("map", "setup"), noun="table")
    assert str(info.value) == "my.toml: [top level] registers: unknown table (known: map, setup)"


def test_numbers_are_finite_unless_told():
    t = keyed({"a": math.inf, "b": -math.inf, "c": math.nan, "d": 1})
    assert t.number("b", allow_inf=True) == -math.inf
    assert t.number("d") == 1.0
    with pytest.raises(DriveConfigError, match=r"^my.toml: \[top level\] a: expected finite number, got inf$"):
        t.number("a")
    with pytest.raises(DriveConfigError, match=r"^my.toml: \[top level\] c: expected number, got nan$"):
        t.number("c", allow_inf=True)


def test_arrays_of_tables_are_named_by_index():
    setup = keyed().tables("setup")
    assert [s.get("address", int) for s in setup] == [1, 2]
    assert setup[1].error("value", "too big").args == ("my.toml: [setup[1]] value: too big",)
    assert keyed().tables("more_setup", []) == []
    with pytest.raises(DriveConfigError) as info:
        keyed({"setup": [{"a": 1}, 3]}).tables("setup")
    assert str(info.value) == "my.toml: [top level] setup[1]: expected table, got 3"


def test_the_sentence_wording():
    head = sentence().table("map")
    cases = [
        (lambda: head.get("gap", str), "dialect my.toml [map]: gap must be a string, got 3"),
        (lambda: head.get("address", int), "dialect my.toml [map]: missing key 'address'"),
        (lambda: sentence().table("units"), "dialect my.toml: missing table [units]"),
        (
            lambda: head.choice("order", ("none", "xor")),
            "dialect my.toml [map]: order must be one of 'none', 'xor', got 'big'",
        ),
        (
            lambda: head.allow(("name", "fc23", "gap", "scale")),
            "dialect my.toml [map]: unknown key(s) order, words (known: fc23, gap, name, scale)",
        ),
    ]
    for read, message in cases:
        with pytest.raises(DriveConfigError) as info:
            read()
        assert str(info.value) == message
    assert str(head.table_error("a and b go together")) == "dialect my.toml [map]: a and b go together"
    assert str(head.error("gap", "is odd")) == "dialect my.toml [map] gap: is odd"


def test_the_error_class_is_the_callers_and_messages_stay_one_line():
    t = TomlTable({"limits": {"max_u": "5", "a\nb": 1}}, "bench.toml", wording=SENTENCE, error=UsageError)
    limits = t.table("limits")
    with pytest.raises(UsageError, match=r"^bench.toml \[limits\]: max_u must be a number, got '5'$"):
        limits.number("max_u")
    with pytest.raises(UsageError) as info:
        limits.done()
    assert not isinstance(info.value, DriveConfigError)
    assert len(str(info.value).splitlines()) == 1 and "a b" in str(info.value)


def test_read_toml_errors_name_the_file(tmp_path):
    with pytest.raises(DriveConfigError, match=r"cannot read plant file '.*none.toml': no such file"):
        read_toml(tmp_path / "none.toml", "plant file")
    with pytest.raises(UsageError, match="cannot read config '.*': not a regular file"):
        read_toml(tmp_path, "config", UsageError)
    bad = tmp_path / "bad.toml"
    bad.write_text("[map\n")
    with pytest.raises(DriveConfigError, match=r"register map file .*bad.toml is not valid TOML"):
        read_toml(bad, "register map file")
    bad.write_bytes(b"a = '\xff'\n")
    with pytest.raises(DriveConfigError, match=r"dialect file .*bad.toml is not UTF-8 text"):
        read_toml(bad, "dialect file")
    good = tmp_path / "good.toml"
    good.write_text("[map]\nname = 'm'\n")
    assert read_toml(good, "register map file") == {"map": {"name": "m"}}


def test_a_plant_file_refuses_drive_url_keys(tmp_path):
    """Limits in a plant file would be dropped (only the URL sets them): an error, not silence."""
    from servobench.errors import DriveConfigError
    from servobench.sim_backend.simurl import plant_from_url

    path = tmp_path / "plant.toml"
    path.write_text("[plant]\nM = 0.2\nmax_u = 3\n")
    with pytest.raises(DriveConfigError, match=r"\[plant\] max_u: is a drive URL key"):
        plant_from_url(f"sim://?plant={path}")
    path.write_text("[plant]\nM = 0.2\n")
    assert plant_from_url(f"sim://?plant={path}&max_u=3").M == 0.2
