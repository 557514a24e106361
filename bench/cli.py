"""The ``servobench`` command line.

Each subcommand lives in ``servobench.bench.commands.<module>`` and exposes
``add_arguments(parser)`` and ``run(args) -> int``; a module is imported only
when its subcommand runs (``servobench --help`` imports none). With no
arguments, ``servobench`` prints its usage. ``run`` returns the command's
verdict (:class:`~servobench.verdict.Verdict`) or None, and
:func:`~servobench.verdict.exit_status` alone maps it to the
exit status: 0 pass, 3 fail. Any :class:`~servobench.errors.ServobenchError`
(and file-system errors) becomes one line on stderr and exit status 1;
Ctrl-C exits with 130 after the command's own clean-up has stopped the axis.
The notes an error carries (where the partial log of an interrupted run is
kept) end that line. Under ``--json``, an error also prints one JSON object
``{"error": "..."}`` on stdout, so that stdout always holds exactly one object.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib
import json
import os
import sys
import tempfile
import warnings
from pathlib import Path

from servobench.errors import DriveWarning, ServobenchError, SessionWarning, notes_of
from servobench.verdict import EXIT_ERROR, EXIT_INTERRUPTED, EXIT_USAGE, exit_status

DESCRIPTION = "Identify servo drives with friction (SIDBE) on a real bus or the simulated drive."

#: subcommand -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "sidbe": ("servobench.bench.commands.sidbe", "run the whole SIDBE procedure on a drive"),
    "run": ("servobench.bench.commands.run", "excite a drive with u1/u2 and log only"),
    "identify": ("servobench.bench.commands.identify", "identify the model from a log"),
    "serve-sim": ("servobench.bench.commands.serve_sim", "serve the simulated drive over a real protocol"),
    "diagnose": ("servobench.bench.commands.diagnose", "find, name and add the effect the model lacks"),
    "validate": ("servobench.bench.commands.validate", "check a saved model against another log"),
    "program": ("servobench.bench.commands.program", "the values to program into the drive, from a saved model"),
    "list": ("servobench.bench.commands.list", "list shipped maps, dialects, effects and URL keys"),
    "commission": ("servobench.bench.commands.commission", "commission a drive in the field"),
    "udev": ("servobench.bench.commands.udev", "install the udev rules for bench adapters"),
    "fleet": ("servobench.bench.commands.fleet", "re-identify a fleet's logs on Dask and trend each axis"),
}


class _Parser(argparse.ArgumentParser):
    #: Set by :func:`main` when the command line asks for ``--json``.
    json_errors = False

    def error(self, message: str) -> None:  # one line, exit 2
        if _Parser.json_errors:
            _print_json_error(message)
        self.exit(EXIT_USAGE, f"servobench: error: {message}\n")


def _print_json_error(message: str) -> None:
    print(json.dumps({"error": message}), flush=True)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``servobench`` parser; only ``command``'s module is imported (all when None).

    The other subcommands are listed with their one-line help, so that
    ``servobench --help`` loads no subcommand at all (``command=""``).
    """
    from servobench import __version__

    parser = _Parser(prog="servobench", description=DESCRIPTION)
    parser.add_argument("--version", action="version", version=f"servobench {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for name, (module_name, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if command is not None and name != command:
            continue
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as err:
            if err.name != module_name:
                raise
            continue
        module.add_arguments(p)
        p.set_defaults(_module=module)
    return parser


def _command_of(argv: list[str]) -> str:
    """The subcommand ``argv`` names (its first word that is not an option), or ``""``."""
    for word in argv:
        if not word.startswith("-"):
            return word if word in COMMANDS else ""
    return ""


_show_warning = warnings.showwarning


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """A :class:`DriveWarning` as one line on stderr (a :class:`SessionWarning` once per terminal
    session); other warnings as Python shows them."""
    if issubclass(category, SessionWarning) and said_this_session(str(message)):
        return
    if issubclass(category, DriveWarning):
        print(f"servobench: warning: {message}", file=file or sys.stderr)
    else:
        _show_warning(message, category, filename, lineno, file, line)


def session_file() -> Path:
    """Where this terminal session's said warnings are remembered (per user, per session id)."""
    return Path(tempfile.gettempdir()) / f"servobench-{os.getuid()}" / f"said-{os.getsid(0)}"


def said_this_session(text: str) -> bool:
    """True when ``text`` was said in this terminal session already; else remember it, False."""
    key = hashlib.sha256(text.encode()).hexdigest()[:32]
    path = session_file()
    try:
        if path.exists() and key in path.read_text(encoding="utf-8").split():
            return True
        path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        with open(path, "a", encoding="utf-8") as fh:
            fh.write(key + "\n")
    except OSError:  # nowhere to remember: say it
        return False
    return False


#: OpenBLAS threads of a command's process, unless the user's environment sets them: every solve
#: of the commands runs on one BLAS thread anyway (:mod:`~servobench.bench.blas_threads`), and the
#: threads that numpy's and scipy's two OpenBLAS builds start when they load cost a process
#: 0.15-0.2 s of CPU (measured: ``sidbe --help``, 0.67 s of user CPU against 0.46 s).
BLAS_THREADS = {"OPENBLAS_NUM_THREADS": "1"}


def main(argv: list[str] | None = None) -> int:
    for name, value in BLAS_THREADS.items():  # before numpy loads (a command's module imports it)
        os.environ.setdefault(name, value)
    argv = sys.argv[1:] if argv is None else list(argv)
    _Parser.json_errors = "--json" in argv
    warnings.showwarning = _one_line_warning
    parser = build_parser(_command_of(argv))
    if not argv:
        parser.print_help()
        return 0
    args = parser.parse_args(argv)
    module = getattr(args, "_module", None)
    if module is None:
        parser.error(f"command {args.command!r} is not available in this build")
    as_json = bool(getattr(args, "json", False))
    try:
        return exit_status(module.run(args))
    except ServobenchError as err:
        return _fail(str(err), err, as_json)
    except OSError as err:
        where = f"{err.filename}: " if getattr(err, "filename", None) else ""
        return _fail(f"{where}{err.strerror or err}", err, as_json)
    except KeyboardInterrupt as err:
        message = "; ".join(["interrupted; axis stopped", *notes_of(err)])
        print(f"servobench: {message}", file=sys.stderr)
        if as_json:
            _print_json_error(message)
        return EXIT_INTERRUPTED


def _fail(message: str, err: BaseException, as_json: bool) -> int:
    """One line on stderr (and one JSON object on stdout under ``--json``); exit status 1."""
    message = "; ".join([message, *notes_of(err)])
    print(f"servobench: error: {message}", file=sys.stderr)
    if as_json:
        _print_json_error(message)
    return EXIT_ERROR


if __name__ == "__main__":
    sys.exit(main())
