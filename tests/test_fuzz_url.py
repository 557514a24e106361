"""Fuzz drive URLs: parsing, and constructing every registered backend (never connecting).

Any URL either builds a closed drive or raises a :class:`ServobenchError`
whose message is one line.
"""

from __future__ import annotations

import math
from urllib.parse import quote

from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from servobench.drivers.base import COMMON_QUERY_KEYS, Drive
from servobench.drivers.registry import BACKENDS, open_drive, resolve
from servobench.drivers.url import DriveURL, parse_drive_url
from servobench.errors import DriveConfigError, ServobenchError

FUZZ = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
SCHEMES = sorted(BACKENDS)
_VALUES = st.one_of(
    st.integers(-(10**20), 10**20).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(
        [
            "",
            "0",
            "1",
            "-1",
            "0x7f",
            "1e9",
            "nan",
            "inf",
            "-inf",
            "true",
            "off",
            "fast",
            "real",
            "cst",
            "pt",
            "servobench-sim",
            "zlac8015d",
            "odrive",
            "socketcand",
            "virtual",
            "N",
            "E",
            "missing.toml",
            "a/b",
            "/",
            ".",
            "..",
            "%00",
            "é",
            "1,2",
            "0.001",
            "1e-300",
        ]
    ),  # fmt: skip
    st.text(max_size=12),
)


def check_error(err: ServobenchError) -> None:
    message = str(err)
    assert message and len(message.splitlines()) == 1, repr(message)


@st.composite
def drive_urls(draw: st.DrawFn) -> str:
    scheme = draw(st.sampled_from(SCHEMES))
    keys = sorted(COMMON_QUERY_KEYS | resolve(scheme).query_keys) + ["bogus"]
    query = draw(st.dictionaries(st.sampled_from(keys), _VALUES, max_size=6))
    host = draw(
        st.one_of(
            st.just(""),
            st.sampled_from(["127.0.0.1", "vcan0", "can0", "localhost", "[::1]", "h"]),
            st.text("abcz09.-_:[]@%", max_size=10),
        )
    )
    port = draw(
        st.one_of(st.none(), st.integers(-5, 70000).map(str), st.text("0123456789x", max_size=6))
    )
    path = draw(st.one_of(st.just(""), st.sampled_from(["/dev/ttyUSB0", "/dev/pts/99", "/x y"]),
                          st.text(max_size=8).map(lambda p: "/" + quote(p))))  # fmt: skip
    netloc = host + (f":{port}" if port is not None else "")
    text = "&".join(f"{quote(k)}={quote(v, safe='')}" for k, v in query.items())
    return f"{scheme}://{netloc}{path}" + (f"?{text}" if draw(st.booleans()) or query else "")


@FUZZ
@given(st.one_of(st.text(max_size=80), drive_urls()))
@example("sim://?M=1&M=2")
@example("canopen://[::1")
@example("modbus+tcp://h:99999")
@example("x://\n?a=b")
@example("sim://?a=%0A")
def test_parse_drive_url(text: str) -> None:
    try:
        url = parse_drive_url(text)
    except DriveConfigError as err:
        check_error(err)
        return
    assert isinstance(url, DriveURL) and url.scheme == url.scheme.lower() and url.raw == text
    for key in url.query:  # typed getters raise only the typed error
        for getter in (url.get_float, url.get_int, url.get_bool):
            try:
                value = getter(key)
            except DriveConfigError as err:
                check_error(err)
                continue
            if getter is url.get_float:
                assert math.isfinite(value)


@FUZZ
@given(drive_urls())
@example("sim://?max_u=-1")
@example("sim://?watchdog=0")
@example("sim://?M=0")
@example("sim://?plant=/")
@example("sim://?seed=-1")
@example("sim://?B=0&plant=%0D")
@example("serial://?dialect=/")
@example("serial:///dev/ttyUSB0?dialect=..")
@example("modbus+tcp://h?map=/&unit=1")
@example("modbus+rtu://h/dev/x?map=servobench-sim")
@example("canopen://vcan0?node=2&sync_cob=0x80000")
@example("canopen://vcan0?node=0x7f&host_node=127")
@example("canopen://?interface=socketcand&node=2&host=h")
def test_open_drive_constructs_or_raises_one_typed_line(text: str) -> None:
    try:
        drive = open_drive(text)
    except ServobenchError as err:
        check_error(err)
        return
    assert isinstance(drive, Drive) and not drive.is_open  # constructed, never connected
    assert drive.limits.max_command > 0 and drive.watchdog_s > 0
