"""``servobench udev install|lint|list``: the udev rules for the bench's adapters.

``install`` renders the shipped templates (group, CAN bitrate, bus-off
restart delay, fixed CAN interface names) and writes them to
``ROOT/etc/udev/rules.d``; ``lint`` checks rule files (the shipped ones by
default, as templates and as rendered); ``list`` shows the rule files, the
USB ids they match and which of those devices are plugged in.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from servobench.udev.rules import InstallOptions

RELOAD_HINT = "udevadm control --reload-rules && udevadm trigger"


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="udev_command", metavar="ACTION", parser_class=type(p))
    sub.required = True

    inst = sub.add_parser("install", help="install the rules into ROOT/etc/udev/rules.d")
    inst.add_argument("--root", type=Path, default=Path("/"), help="file-system root (default /)")
    inst.add_argument(
        "--bitrate", type=int, default=1_000_000, help="CAN bitrate [bit/s] (default 1000000)"
    )
    inst.add_argument(
        "--restart-ms", type=int, default=100, help="CAN bus-off auto-restart delay [ms]"
    )
    inst.add_argument(
        "--group", default="plugdev", help="group given access (default plugdev; e.g. servobench)"
    )
    inst.add_argument(
        "--can-name",
        action="append",
        default=[],
        metavar="NAME=serial:SERIAL|NAME=path:ID_PATH",
        help="fixed SocketCAN name for one adapter (repeatable; default: servocan<N>)",
    )
    inst.add_argument(
        "--dry-run", action="store_true", help="print the rendered rules, write nothing"
    )
    inst.set_defaults(_udev=_install)

    lint = sub.add_parser("lint", help="check udev rule files (default: the shipped ones)")
    lint.add_argument("files", nargs="*", type=Path, metavar="FILE")
    lint.add_argument("--template", action="store_true", help="accept @VARIABLE@ placeholders")
    lint.add_argument("--strict", action="store_true", help="fail on warnings too")
    lint.set_defaults(_udev=_lint)

    ls = sub.add_parser("list", help="show the rule files, their USB ids and devices present")
    ls.add_argument("--sysfs", type=Path, default=Path("/sys"), help=argparse.SUPPRESS)
    ls.set_defaults(_udev=_list)


def run(args: argparse.Namespace) -> int:
    return int(args._udev(args))


def _options(args: argparse.Namespace) -> InstallOptions:
    from servobench.udev.rules import InstallOptions, parse_can_name

    return InstallOptions(
        bitrate=args.bitrate,
        restart_ms=args.restart_ms,
        group=args.group,
        can_names=tuple(parse_can_name(s) for s in args.can_name),
    )


def _install(args: argparse.Namespace) -> int:
    from servobench.udev.rules import install, render, shipped_rules

    options = _options(args)
    if args.dry_run:
        for src in shipped_rules():
            print(f"# ---- {src.name}")
            print(render(src.read_text(encoding="utf-8"), options), end="")
        return 0
    result = install(args.root, options)
    print(f"installed {len(result.files)} rule files into {result.target}:")
    for f in result.files:
        print(f"  {f.name}")
    print(
        f"CAN interfaces come up at {options.bitrate} bit/s, restart-ms {options.restart_ms}; "
        f"devices are given to group {options.group!r}"
    )
    if args.root.resolve() == Path("/"):
        try:
            import grp  # POSIX only: imported here so that the CLI loads everywhere

            grp.getgrnam(options.group)
        except KeyError:
            print(
                f"note: group {options.group!r} does not exist: groupadd --system "
                f"{options.group} && usermod -aG {options.group} $USER"
            )
    print(f"reload with: {RELOAD_HINT}")
    return 0


def _lint(args: argparse.Namespace) -> int:
    from servobench.udev.lint import lint_file, lint_text
    from servobench.udev.rules import InstallOptions, render, shipped_rules

    results = []
    if args.files:
        results = [lint_file(f, template=args.template) for f in args.files]
    else:
        for src in shipped_rules():
            text = src.read_text(encoding="utf-8")
            results.append(lint_text(text, str(src), template=True))
            rendered = render(text, InstallOptions())
            results.append(lint_text(rendered, f"{src} (rendered)"))
    for res in results:
        for finding in res.findings:
            print(finding)
    errors = sum(len(r.errors) for r in results)
    warnings = sum(len(r.warnings) for r in results)
    rules = sum(len(r.rules) for r in results)
    print(f"{len(results)} files, {rules} rules: {errors} errors, {warnings} warnings")
    return 1 if errors or (args.strict and warnings) else 0


def _list(args: argparse.Namespace) -> int:
    from servobench.udev.lint import lint_file
    from servobench.udev.rules import rules_dir, scan_usb, shipped_rules, udev_glob, usb_matches

    sources = shipped_rules()
    results = [lint_file(src, template=True) for src in sources]
    print(f"rule files in {rules_dir()}:")
    for src in sources:
        title = next(
            (ln[2:] for ln in src.read_text(encoding="utf-8").splitlines() if ln.startswith("# ")),
            "",
        )
        print(f"  {src.name:32s} {title.removeprefix('servobench: ')}")
    matches = usb_matches(results)
    print("USB ids matched (vendor:product):")
    for m in matches:
        print(f"  {m.vendor + ':' + m.product:40s} {m.file}")
    present = [
        (d, m)
        for d in scan_usb(args.sysfs)
        for m in matches
        if udev_glob(m.vendor, d.vendor) and udev_glob(m.product, d.product)
    ]
    print("plugged in now:" if present else "plugged in now: none of these")
    seen = set()
    for d, m in present:
        if d.port not in seen:
            seen.add(d.port)
            print(
                f"  {d.port:10s} {d.vendor}:{d.product} {d.name!r} serial {d.serial or '-'}  ({m.file})"
            )
    return 0
