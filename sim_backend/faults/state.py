"""The served drive's state report: ``serve-sim --state-file PATH``.

A JSON object, rewritten atomically (write, then rename) whenever the power
state, the fault code or the watchdog trip count changes, and once more when
the server stops (``"final": true``, written *before* serve-sim's own
clean-up disables the drive, so it shows what the host and the faults left)::

    {"state": "disabled", "torque_off": true, "command": 0.0,
     "velocity": 0.12, "position": 3.4, "t_s": 0.6, "cycles": 600,
     "fault_code": 0, "fault_reason": "", "watchdog_trips": 0,
     "faults_injected": [{"kind": "drop", "cycle": 120, "arg": null}],
     "tick": {"tick_s": 0.001, "phase_s": 0.00042, "commands": 600, "mean_delay_s": 0.001,
              "min_delay_s": 0.001, "max_delay_s": 0.001, "reads": 600,
              "repeated_reads": 0, "skipped_ticks": 3},
     "history": [{"state": "enabled", "cycle": 0, "fault_code": 0}, ...],
     "final": false, "pid": 1234}

``torque_off`` is true unless the power stage is enabled, ``command`` what it applies (0 unless enabled), ``velocity``
and ``position`` the plant's true state at the last cycle (read without
drawing sensor noise, so reporting never perturbs the lock-step run),
``cycles`` the clocking requests the injector counted, ``tick`` the drive's
record of its timing (:meth:`~SimulatedDevice.timing`: its control tick, the
action delay of its commands, its reads; tick 0 and delays 0 for a drive
without a tick of its own). Like every field it is as of the last write: the
final report has it complete.
"""

from __future__ import annotations

import json
import os
import threading
from pathlib import Path

from servobench.sim_backend.device import PowerState, SimulatedDevice
from servobench.sim_backend.faults.injector import FaultInjector

#: Longest wait between two writes of the report [s]; state changes are written at once
#: and every change enters the history (the device calls the reporter on each).
POLL_S = 0.02


def snapshot(
    device: SimulatedDevice,
    injector: FaultInjector | None,
    now: tuple[float, float, float] | None = None,
    timing: dict[str, float | int] | None = None,
) -> dict[str, object]:
    """The report's fields, now (no sensor noise drawn, no clocking).

    ``now`` and ``timing``: the device's :meth:`~SimulatedDevice.true_state` and
    :meth:`~SimulatedDevice.timing` taken by the caller (outside any lock the
    device's listeners take), else taken here.
    """
    t_s, v, x = now if now is not None else device.true_state()
    timing = timing if timing is not None else device.timing()
    state = device.state
    return {
        "state": state.value,
        "torque_off": state is not PowerState.ENABLED,
        "command": device.command,
        "velocity": v,
        "position": x,
        "t_s": t_s,
        "cycles": injector.cycle if injector is not None else None,
        "fault_code": device.fault_code,
        "fault_reason": device.fault_reason,
        "watchdog_trips": device.watchdog_trips,
        "faults_injected": injector.record() if injector is not None else [],
        "tick": timing,
    }


def write_json_atomic(path: Path, data: object) -> None:
    """Write ``data`` as JSON to ``path`` so that readers never see half a file.

    Raises
    ------
    OSError
        Naming ``path`` (not the temporary file beside it).
    """
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(json.dumps(data, indent=1) + "\n", encoding="utf-8")
        os.replace(tmp, path)
    except OSError as err:
        raise OSError(err.errno, err.strerror, str(path)) from None


class StateReporter(threading.Thread):
    """Writes the state report on every change until :meth:`finish`.

    Parameters
    ----------
    device : SimulatedDevice
        The served drive.
    injector : FaultInjector or None
        Its injector (for the cycle count and the faults applied).
    path : path-like
        The JSON file.
    """

    def __init__(
        self, device: SimulatedDevice, injector: FaultInjector | None, path: str | os.PathLike[str]
    ) -> None:
        super().__init__(name="sim-state-report", daemon=True)
        self.device = device
        self.injector = injector
        self.path = Path(path)
        self.history: list[dict[str, object]] = []
        self._key: tuple[object, ...] | None = None
        self._stop_event = threading.Event()
        self._write_lock = threading.Lock()
        self.failure: BaseException | None = None
        self._changed = threading.Event()
        self._record(device.state, device.fault_code)
        device.listeners.append(self._on_change)
        self._poll(final=False)  # the file exists before the URL is announced

    def _record(self, state: PowerState, fault_code: int) -> None:
        cycle = self.injector.cycle if self.injector is not None else None
        self.history.append({"state": state.value, "cycle": cycle, "fault_code": fault_code})

    def _on_change(self, state: PowerState, fault_code: int) -> None:
        """Device listener (under the device's lock): every change enters the history."""
        with self._write_lock:
            self._record(state, fault_code)
        self._changed.set()

    def _poll(self, final: bool) -> None:
        dev = self.device
        now = dev.true_state()  # not under the write lock: listeners take it under the device's
        timing = dev.timing()
        with self._write_lock:
            key = (dev.state, dev.fault_code, dev.watchdog_trips, len(self.history))
            if key == self._key and not final:
                return
            self._key = key
            data = snapshot(dev, self.injector, now, timing)
            write_json_atomic(
                self.path, {**data, "history": self.history, "final": final, "pid": os.getpid()}
            )

    def run(self) -> None:
        try:
            while not self._stop_event.is_set():
                self._changed.wait(POLL_S)
                self._changed.clear()
                self._poll(final=False)
        except BaseException as err:  # surfaced by finish()
            self.failure = err

    def finish(self) -> None:
        """Stop polling and write the final report."""
        self._stop_event.set()
        if self.is_alive():
            self.join(timeout=1.0)
        self._poll(final=True)
