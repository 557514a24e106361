"""servobench: SIDBE identification of servo drives with friction, on a real bus.

The public API is the names in ``__all__``; everything below them may move::

    import servobench as sb

    with sb.open_drive("sim://") as drive:        # any drive URL; stopped and closed on exit
        result = sb.sidbe(drive, out="run")       # the whole procedure: result.model, .verdict, .log
    log = sb.read_log("run/log.csv")              # sb.Log: runs as numpy arrays, metadata, .to_pandas()
    model = sb.identify(log)                      # sb.Model: M, B, coulomb_pos, coulomb_neg, std, units, ...
    report = sb.diagnose(log)                     # .verdict, .effects, .model, .gap_percent, .noise_floor_percent
    check = sb.validate(model, log)               # .verdict, .fit_percent, .gap_percent
    values = sb.program(model)                    # the values to program into the drive
    v = model.simulate(u, fs=1000.0)              # velocity for a command sequence
    model.save("model.json"); same = sb.load_model("model.json")

Every result is a frozen dataclass whose ``to_dict()`` is the JSON the CLI
command of the same name prints with ``--json``; every error is a
:class:`ServobenchError` with the CLI's one-line message. ``import servobench``
stays light: the functions and their numerical code are imported on first use.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from servobench.errors import (
    DriveConfigError,
    DriveConnectionError,
    DriveError,
    DriveFaultError,
    DriveTimeoutError,
    DriveUnavailableError,
    DriveWarning,
    IdentificationError,
    LimitExceededError,
    LogFormatError,
    ServobenchError,
    StateTransitionError,
    UsageError,
)
from servobench.verdict import Verdict

__version__ = "0.1.0"

#: Public name -> the module that defines it, imported on first use.
_LAZY = {
    "open_drive": "servobench.drivers.registry",
    "Log": "servobench.log",
    "read_log": "servobench.log",
    "Model": "servobench.model",
    "load_model": "servobench.model",
    "identify": "servobench.analysis",
    "Diagnosis": "servobench.analysis",
    "diagnose": "servobench.analysis",
    "Validation": "servobench.analysis",
    "validate": "servobench.analysis",
    "ProgramValues": "servobench.analysis",
    "program": "servobench.analysis",
    "SidbeResult": "servobench.procedures",
    "sidbe": "servobench.procedures",
    "CommissionResult": "servobench.procedures",
    "commission": "servobench.procedures",
    "FleetResult": "servobench.procedures",
    "fleet": "servobench.procedures",
}

__all__ = [
    "__version__",
    # drives and procedures
    "open_drive", "sidbe", "SidbeResult", "commission", "CommissionResult", "fleet", "FleetResult",
    # logs and models
    "read_log", "Log", "identify", "Model", "load_model",
    "diagnose", "Diagnosis", "validate", "Validation", "program", "ProgramValues",
    "Verdict",
    # errors
    "ServobenchError", "DriveError", "DriveUnavailableError", "DriveConfigError", "DriveConnectionError",
    "DriveTimeoutError", "DriveFaultError", "StateTransitionError", "LimitExceededError",
    "IdentificationError", "LogFormatError", "UsageError", "DriveWarning",
]  # fmt: skip

if TYPE_CHECKING:
    from servobench.analysis import (
        Diagnosis,
        ProgramValues,
        Validation,
        diagnose,
        identify,
        program,
        validate,
    )
    from servobench.drivers.registry import open_drive
    from servobench.log import Log, read_log
    from servobench.model import Model, load_model
    from servobench.procedures import (
        CommissionResult,
        FleetResult,
        SidbeResult,
        commission,
        fleet,
        sidbe,
    )


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'servobench' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # a submodule of the same name can no longer shadow it
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
