"""The documentation: built by the README's command with warnings as errors, every example run.

- The site builds offline with ``sphinx-build -W -b html docs OUT`` (its figures drawn from runs
  on ``sim://`` during the build), well within a minute and a half, and writes nothing into docs/.
- Every page's examples run in order, in a fresh folder per page, in a process of their own:
  `````python`` blocks by ``exec`` in one namespace per page (matplotlib's Agg backend),
  the ``$`` lines of `````console`` blocks in bash; a page's examples share the folder.
- Examples that need hardware (`````sh`` blocks, ``{code-block} python`` blocks) cannot run here:
  each ``servobench`` line is parsed by the CLI's own parser and each drive URL is checked by
  ``sb.open_drive`` (every key checked, nothing opened); the Python compiles.
- The API reference documents every public name; its example is the README's, word for word.
- The README: at most 200 lines, its Quick start unchanged, its relative links reaching files.
"""

from __future__ import annotations

import ast
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

import servobench as sb

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
README = REPO / "README.md"
PAGES = sorted(p for p in DOCS.rglob("*.md") if "_build" not in p.parts)
#: The README's first lines, which stay as they are (the two commands of .ci/run among them).
QUICK_START = """# servobench

## Quick start

```sh
pip install -e ".[test,fleet]" && servobench sidbe --drive sim://
python -m pytest -q
```
"""
#: Fence info strings a page may use; anything else would be an example nobody checks.
RUN = {"python", "console"}
CHECK = {"sh", "{code-block} python"}
SHOW = {"text", "toml"}
DIRECTIVES = ("{sim-figure}", "{toctree}", "{literalinclude}", "{include}", "{servobench-help}")
BUILD_TIMEOUT_S = 100
PAGE_TIMEOUT_S = 240
URL = re.compile(
    r"""["']((?:sim|canopen|modbus\+tcp|modbus\+rtu|serial|ethercat)://[^"'\s]*)["']"""
)


@dataclass(frozen=True)
class Block:
    info: str
    body: str
    line: int  # 1-based line of the first body line


def blocks(path: Path) -> list[Block]:
    """The fenced code blocks of a Markdown file, in order (fences of three or more backticks)."""
    found, lines = [], path.read_text(encoding="utf-8").splitlines()
    i = 0
    while i < len(lines):
        m = re.match(r"^(\s*)(`{3,})(.*)$", lines[i])
        if m and "`" not in m.group(3):
            fence, start, body = m.group(2), i + 1, []
            i += 1
            while i < len(lines) and lines[i].strip() != fence:
                body.append(lines[i][len(m.group(1)) :])
                i += 1
            assert i < len(lines), f"{path}:{start}: a code block is never closed"
            found.append(Block(m.group(3).strip(), "\n".join(body) + "\n", start + 1))
        i += 1
    return found


def _rel(path: Path) -> str:
    return str(path.relative_to(REPO))


def _api_block() -> str:
    m = re.search(r"## Python API.*?```python\n(.*?)```", README.read_text(encoding="utf-8"), re.S)
    assert m is not None, "the README lost its Python API example"
    return m.group(1)


# ---------------------------------------------------------------------------- the build
def _docs_files() -> set[Path]:
    return {p for p in DOCS.rglob("*") if not {"_build", "__pycache__"} & set(p.parts)}


@pytest.mark.slow
def test_the_docs_build_with_warnings_as_errors(tmp_path):
    before = _docs_files()
    out = tmp_path / "html"
    done = subprocess.run(
        [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html", str(DOCS), str(out)],
        capture_output=True, text=True, timeout=BUILD_TIMEOUT_S, cwd=tmp_path,
        env={**os.environ, "MPLBACKEND": "Agg"},
    )  # fmt: skip
    assert done.returncode == 0, f"sphinx-build failed:\n{done.stdout}\n{done.stderr}"
    assert not done.stderr.strip(), done.stderr  # -q: warnings would be all it prints
    after = _docs_files()
    assert after == before, f"the build wrote into docs/: {sorted(map(str, after - before))}"
    # every page became a page; the figures are in it, drawn from runs on sim://
    for page in PAGES:
        html = out / page.relative_to(DOCS).with_suffix(".html")
        assert html.exists(), html
    names = set(re.findall(r"\{sim-figure\} (\S+)", "".join(p.read_text() for p in PAGES)))
    assert names >= {"sidbe-fit", "closed-loop", "validation"}
    for name in names:
        png = out / "_images" / f"{name}.png"
        assert png.exists() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name
    # the API reference documents every public name, and the CLI reference every command
    api = (out / "api.html").read_text(encoding="utf-8")
    for name in sb.__all__:
        if name != "__version__":
            assert f'id="servobench.{name}"' in api, f"api.html lacks servobench.{name}"
    cli = (out / "cli.html").read_text(encoding="utf-8")
    from servobench.bench.cli import COMMANDS

    for command in COMMANDS:
        assert f"usage: servobench {command}" in cli, command


def test_the_api_reference_names_every_public_name():
    text = (DOCS / "api.rst").read_text(encoding="utf-8")
    documented = set(re.findall(r"^\.\. auto(?:function|class|exception):: (\w+)", text, re.M))
    assert documented == set(sb.__all__) - {"__version__"}


def test_the_api_example_is_the_readmes():
    assert (DOCS / "examples" / "api.py").read_text(encoding="utf-8") == _api_block()


# ---------------------------------------------------------------------------- the examples
#: Runs one page's examples in order, in the current folder: Python in one namespace, console
#: lines in bash; each traceback names the page and its line.
RUNNER = r"""
import json, subprocess, sys
import matplotlib
matplotlib.use("Agg")
page, examples = json.load(open(sys.argv[1]))
scope = {"__name__": "__main__"}
for kind, line, body in examples:
    if kind == "python":
        exec(compile("\n" * (line - 1) + body, page, "exec"), scope)
        continue
    for n, text in enumerate(body.splitlines()):
        if text.startswith("$ "):
            print(f"{page}:{line + n}: {text}", flush=True)
            done = subprocess.run(["bash", "-c", text[2:]])
            if done.returncode != 0:
                sys.exit(f"{page}:{line + n}: exit status {done.returncode}: {text}")
"""


def _examples(path: Path) -> list[tuple[str, int, str]]:
    out = []
    for b in blocks(path):
        if b.info in RUN:
            if path == README and b.info == "python" and b.body == _api_block():
                continue  # tests/test_readme_api.py runs it (and checks what it gives)
            out.append((b.info, b.line, b.body))
    return out


def _env() -> dict[str, str]:
    """This interpreter's scripts (``servobench``) first on PATH, matplotlib without a display."""
    path = os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")])
    return {**os.environ, "PATH": path, "MPLBACKEND": "Agg"}


def _run_examples(name: str, examples: list[tuple[str, int, str]], where: Path) -> None:
    where.mkdir(parents=True, exist_ok=True)
    (where / "examples").mkdir(exist_ok=True)
    shutil.copy(REPO / "examples" / "bench.toml", where / "examples" / "bench.toml")
    script = where.parent / f"{where.name}.json"
    script.write_text(json.dumps([name, examples]), encoding="utf-8")
    done = subprocess.run(
        [sys.executable, "-c", RUNNER, str(script)], cwd=where, capture_output=True, text=True,
        timeout=PAGE_TIMEOUT_S, env=_env(),
    )  # fmt: skip
    assert done.returncode == 0, (
        f"{name}: an example failed\n{done.stdout[-4000:]}\n{done.stderr[-6000:]}"
    )


RUNNABLE = [p for p in [*PAGES, README] if _examples(p)]


@pytest.mark.slow
@pytest.mark.timeout(PAGE_TIMEOUT_S + 60)
@pytest.mark.parametrize("path", RUNNABLE, ids=[_rel(p) for p in RUNNABLE])
def test_the_examples_of_a_page_run(path, tmp_path):
    _run_examples(_rel(path), _examples(path), tmp_path / "work")


def test_every_code_block_is_run_checked_or_shown():
    for path in [*PAGES, README]:
        for b in blocks(path):
            known = b.info in RUN | CHECK | SHOW or b.info.startswith(DIRECTIVES)
            assert known, f"{_rel(path)}:{b.line}: a ```{b.info} block: run it, check it or show it"


def _servobench_lines(body: str) -> list[list[str]]:
    """The ``servobench ...`` command lines of a shell block, as words (``sudo`` dropped)."""
    out = []
    for line in body.splitlines():
        words = shlex.split(line, comments=True)
        if words[:1] == ["sudo"]:
            words = words[1:]
        if words[:1] == ["servobench"]:
            out.append(words[1:])
    return out


def _check_drive_url(url: str, where: str) -> None:
    try:
        sb.open_drive(url)  # makes the drive, checking the scheme and every key; opens nothing
    except sb.DriveUnavailableError as err:
        if "pysoem" not in str(err):
            raise AssertionError(f"{where}: {url}: {err}") from None
    except sb.ServobenchError as err:
        if re.search(r"file '[^']+' does not exist", str(err)):
            return  # the user's own map or dialect file, named by path, which only the bench has
        raise AssertionError(f"{where}: {url}: {err}") from None


def test_the_hardware_examples_parse_and_name_valid_drives(capsys):
    from servobench.bench.cli import build_parser

    parser = build_parser()
    checked = 0
    for path in [*PAGES, README]:
        for b in blocks(path):
            where = f"{_rel(path)}:{b.line}"
            if b.info == "sh":
                for words in _servobench_lines(b.body):
                    try:
                        args = parser.parse_args(words)
                    except SystemExit:
                        raise AssertionError(f"{where}: servobench {shlex.join(words)}: "
                                             f"{capsys.readouterr().err.strip()}") from None  # fmt: skip
                    if getattr(args, "drive", None):
                        _check_drive_url(args.drive, where)
                    checked += 1
            elif b.info == "{code-block} python":
                code = "\n".join(line for line in b.body.splitlines() if not line.startswith(":"))
                ast.parse(code, where)
                for url in URL.findall(code):
                    _check_drive_url(url, where)
                    checked += 1
    assert checked >= 20


def test_every_page_is_in_the_table_of_contents():
    index = (DOCS / "index.md").read_text(encoding="utf-8")
    listed = set(re.findall(r"^([\w/-]+)$", index, re.M))
    pages = {str(p.relative_to(DOCS).with_suffix("")) for p in [*PAGES, *DOCS.glob("*.rst")]} - {
        "index"
    }
    assert pages <= listed, f"not in a toctree: {sorted(pages - listed)}"


# ---------------------------------------------------------------------------- the README
def test_the_readme_is_short_and_starts_as_it_did():
    text = README.read_text(encoding="utf-8")
    assert text.startswith(QUICK_START)
    assert len(text.splitlines()) <= 200
    after = (
        text[len(QUICK_START) :].strip().split("\n\n")[0]
    )  # the paragraph after the two commands
    assert "identifies the simulated" in after and "runs the whole test suite" in after
    assert "sphinx-build -W -b html docs docs/_build/html" in text  # the documented build command


def test_the_readme_links_reach_files():
    links = re.findall(r"\]\(([^)\s]+)\)", README.read_text(encoding="utf-8"))
    relative = [link.split("#")[0] for link in links if "://" not in link]
    assert len(relative) >= 20
    missing = [link for link in relative if not (REPO / link).exists()]
    assert not missing, missing
    pages = {str(p.relative_to(REPO)) for p in PAGES} | {"docs/api.rst"}
    assert pages - {"docs/index.md"} <= set(relative), "the README does not link every page"
