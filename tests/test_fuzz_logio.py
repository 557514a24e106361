"""Fuzz the log reader: any text or bytes give a log or one typed, one-line error."""

from __future__ import annotations

import string

import numpy as np
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from servobench.bench.log.io import LogWriter, parse_log_text, read_log
from servobench.errors import LogFormatError, ServobenchError

FUZZ = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])

_NUMBER = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-(10**30), 10**30).map(str),
    st.sampled_from(["", " ", "1e999", "-0", "0x10", "nan", "inf", "1,5", "+.5", "1_000", "٣"]),
    st.text(max_size=6),
)
_COLUMN = st.sampled_from(["run", "t", "u", "v", "x", "t_host", "", " t", "T", "v,v", "#"])
_LINE_END = st.sampled_from(["\n", "\r\n", "\r", "\x0b", "\x85", "\u2028", ""])


@st.composite
def log_like(draw: st.DrawFn) -> str:
    """Text shaped like a log (metadata, header, rows, trailer), with damage."""
    parts: list[str] = []
    for _ in range(draw(st.integers(0, 3))):
        key = draw(st.sampled_from(["fs", "status", "reason", "drive", "x y", ""]))
        parts.append(f"# {key} = {draw(_NUMBER)}")
    columns = draw(st.lists(_COLUMN, min_size=0, max_size=7))
    if draw(st.booleans()):
        columns = ["run", "t", "u", "v", "x"]
    parts.append(",".join(columns))
    for _ in range(draw(st.integers(0, 6))):
        width = draw(st.integers(0, len(columns) + 1))
        parts.append(",".join(draw(_NUMBER) for _ in range(width)))
    end = draw(_LINE_END)
    return end.join(parts) + draw(st.sampled_from(["", "\n", end, "\n# status = complete\n"]))


def check_error(err: ServobenchError) -> None:
    message = str(err)
    assert message, "an error needs a message"
    assert len(message.splitlines()) == 1, f"multi-line message: {message!r}"


@FUZZ
@given(st.one_of(log_like(), st.text(max_size=300)))
@example("t,u,v\n0,1,2\n1e400,1,2\n")
@example("run,t,u,v\n1e300,0,1,2\n1e300,1,1,2\n")
@example("t,u,v\n0,1,2\r0.1,1,2\n")
@example("\ufefft,u,v\n0,1,2\n0.1,1,3\n")
def test_parse_log_text_raises_only_log_format_errors(text: str) -> None:
    try:
        log = parse_log_text(text, source="fuzz")
    except LogFormatError as err:
        check_error(err)
        return
    for run in log.runs:  # what it returns is a valid log
        assert len(run) >= 1 and np.all(np.isfinite(run.t)) and np.all(np.isfinite(run.u))
        assert np.all(np.diff(run.t) > 0)
    assert np.isfinite(log.fs_hz) and log.fs_hz > 0


@FUZZ
@given(st.binary(max_size=300), st.sampled_from([".csv", ".mat", ".log", ""]))
@example(b"MATLAB 5.0 MAT-file" + b"\x00" * 120, ".mat")
@example(b"t,u,v\n0,1,\xff\n", ".csv")
def test_read_log_of_any_bytes(tmp_path_factory, data: bytes, suffix: str) -> None:
    path = tmp_path_factory.mktemp("fuzz") / f"log{suffix}"
    path.write_bytes(data)
    try:
        read_log(path)
    except LogFormatError as err:
        check_error(err)


@FUZZ
@given(
    st.dictionaries(
        st.text(string.ascii_letters + "_", min_size=1, max_size=8),
        st.one_of(st.text(max_size=20), st.floats(), st.lists(st.floats(), max_size=3)),
        max_size=4,
    ),
    st.lists(st.tuples(st.floats(-1e9, 1e9), st.floats(-1e9, 1e9)), min_size=1, max_size=20),
)
def test_whatever_the_writer_writes_reads_back(tmp_path_factory, meta, rows) -> None:
    """Metadata of any text (newlines included) never breaks the log it heads."""
    path = tmp_path_factory.mktemp("fuzz") / "log.csv"
    with LogWriter(path, {**meta, "fs": 1000}, ("t", "u", "v")) as w:
        for k, (u, v) in enumerate(rows):
            w.append(k * 1e-3, u, v)
    log = read_log(path)
    assert log.complete and len(log.runs[0]) == len(rows)
    np.testing.assert_allclose(log.runs[0].u, [u for u, _ in rows], rtol=1e-9)


# ------------------------------------------------------------ fast pass = reference
def _reference(text: str):
    """What the line-by-line reference parser makes of ``text`` (result or error message)."""
    from servobench.bench.log import table as logtable

    text = text.removeprefix("\ufeff")
    truncated = bool(text) and not text.endswith(("\n", "\r"))
    lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    if truncated:
        lines = lines[:-1]
    try:
        meta, header, columns = logtable.checked_parse(lines, "fuzz", lambda h: None)
    except LogFormatError as err:
        return str(err)
    return meta, header, columns


def _fast(text: str, engine: str):
    from servobench.bench.log import table as logtable

    try:
        table = logtable.parse_table(text, "fuzz", lambda h: None, engine)
    except LogFormatError as err:
        return str(err)
    return table.metadata, table.header, table.columns


def _same(a, b) -> None:
    assert type(a) is type(b), (a, b)
    if isinstance(a, str):
        assert a == b
        return
    assert a[0] == b[0] and a[1] == b[1]
    assert len(a[2]) == len(b[2])
    for x, y in zip(a[2], b[2], strict=True):
        np.testing.assert_array_equal(x, y)


@FUZZ
@given(st.one_of(log_like(), st.text(max_size=300)), st.sampled_from(["numpy", "pyarrow"]))
@example("t,u,v\n0,1,2\n 1,1,2 \n", "pyarrow")
@example("t,u,v\n0,1,2\n1,1,2#3\n", "numpy")
@example("t;u;v\n0;1,5;2\n1;1;2\n# status = complete\n", "pyarrow")
@example("t,u,v\n0,1,2\n\n1,1,nan\n", "pyarrow")
@example("t,u,v\n0,1,2\n1,1,\n", "pyarrow")
def test_fast_readers_agree_with_the_line_by_line_reference(text: str, engine: str) -> None:
    """numpy's and pyarrow's C readers return exactly what the reference parser does."""
    _same(_fast(text, engine), _reference(text))
    _same(_fast(text.encode("utf-8"), engine), _reference(text))  # read_log hands bytes


def test_a_clean_log_never_needs_the_reference(monkeypatch) -> None:
    """The fast pass really runs: with the reference disabled, clean logs (',' and ';') still read."""
    from servobench.bench.log import table as logtable

    def no_reference(*_args):
        raise AssertionError("the line-by-line reference ran")

    monkeypatch.setattr(logtable, "checked_parse", no_reference)
    rows = "".join(f"1,{k / 100:.2f},1.5,{k},0\n" for k in range(50))
    text = "# fs = 100\nrun,t,u,v,x\n" + rows + "# status = complete\n"
    for engine in logtable.ENGINES:
        for variant in (text, text.replace(",", ";").replace(".", ",").replace("# fs = 100", "# fs = 100")):
            log = parse_log_text(variant.encode(), engine=engine)
            assert len(log.runs[0]) == 50 and log.complete and log.fs_hz == 100.0
            np.testing.assert_array_equal(log.runs[0].v, np.arange(50.0))


def test_the_pyarrow_reader_starts_no_thread_pool() -> None:
    """A large log read through pyarrow starts none of Arrow's CPU pool threads: a pool torn
    down at interpreter exit with a worker alive aborts the process (exit -6, once seen after a
    complete ``sidbe``; apache/arrow#34314). Counted in a fresh interpreter: the allocator's
    background thread and one reader thread at most."""
    import subprocess
    import sys

    probe = (
        "import os\n"
        "import pyarrow\n"
        "from servobench.bench.log.io import parse_log_text\n"
        "rows = ''.join(f'1,{k / 1000:.3f},0.5,{k},0\\n' for k in range(60000))\n"
        "text = '# fs = 1000\\nrun,t,u,v,x\\n' + rows + '# status = complete\\n'\n"
        "before = len(os.listdir('/proc/self/task'))\n"
        "log = parse_log_text(text.encode(), engine='pyarrow')\n"
        "assert len(log.runs[0]) == 60000\n"
        "print(len(os.listdir('/proc/self/task')) - before)\n"
    )
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert int(done.stdout) <= 2, f"{done.stdout.strip()} threads started by one read"
