"""Errors of ``servobench commission``."""

from __future__ import annotations

from servobench.errors import ServobenchError


class CommissionRefused(ServobenchError):
    """Commissioning stopped on purpose: the axis is not safe or not fit to identify.

    The message tells the technician what was found and what to change; the
    CLI prints it as one ``servobench: error: ...`` line and exits with 1.
    """
