"""What a command ends with, and the one mapping from it to the exit status.

A script that drives servobench trusts the exit status and the first line,
so both come from the same verdict:

====  ==========================================================================
0     the command ran to the end and its verdict is a pass (or it has no verdict:
      ``identify``, ``diagnose``, ``run``, ``list``, ``fleet`` ...)
1     an error: bad input, a drive that faults or drops the link, an axis that
      never moved above the sensor noise (nothing to judge, no model written)
2     a malformed command line (argparse)
3     the command ran to the end and its verdict is a fail (``commission``,
      ``sidbe`` below its fit threshold, ``validate`` below its threshold)
130   Ctrl-C (the axis was stopped first)
====  ==========================================================================

A command's ``run(args)`` returns a :class:`Verdict` when it judges
something, else ``None`` (or ``0``); :func:`exit_status` is the only place
that turns either into the exit status. The first line the command prints
and the first key of its ``--json`` object (``verdict``) carry
:attr:`Verdict.word`, the same word the report's banner shows.
"""

from __future__ import annotations

from enum import Enum

#: Exit statuses (see the module docstring).
EXIT_PASS = 0
EXIT_ERROR = 1
EXIT_USAGE = 2
EXIT_FAIL = 3
EXIT_INTERRUPTED = 130


class Verdict(Enum):
    """A command's verdict; ``value`` is the word its first line, its JSON and its report use."""

    PASS = "pass"
    REMARKS = "pass with remarks"
    FAIL = "fail"

    @property
    def word(self) -> str:
        return self.value

    @property
    def passed(self) -> bool:
        return self is not Verdict.FAIL

    @classmethod
    def of(cls, passed: bool, remarks: bool = False) -> Verdict:
        """PASS, REMARKS or FAIL from a judgement."""
        if not passed:
            return cls.FAIL
        return cls.REMARKS if remarks else cls.PASS

    def line(self, what: str) -> str:
        """The first line of a command's text output: ``PASS: what`` / ``FAIL: what``."""
        head = "PASS with remarks" if self is Verdict.REMARKS else self.value.upper()
        return f"{head}: {what}"


def exit_status(outcome: Verdict | int | None) -> int:
    """The exit status of a command that ran to the end and returned ``outcome``."""
    if outcome is None:
        return EXIT_PASS
    if isinstance(outcome, Verdict):
        return EXIT_PASS if outcome.passed else EXIT_FAIL
    return int(outcome)
