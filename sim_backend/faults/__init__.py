"""Fault injection for the served simulated drive (``serve-sim --fault SPEC``).

Layers::

    host driver  <-- wire -->  transport server  --  hook  --  FaultInjector  --  SimulatedDevice
                                (serve_canopen,      (can,       (injector.py)
                                 serve_modbus,        modbus,
                                 serve_serial)        serial)

* :mod:`.spec` -- the grammar shared by every transport (``KIND@N[:ARG]``,
  ``N`` = the drive's clocking cycle from 1) and which kind applies where;
* :mod:`.injector` -- counts cycles, applies the drive's own faults (a fault
  code, frozen feedback) and hands the wire faults to the hook;
* :mod:`.can`, :mod:`.modbus`, :mod:`.serial` -- one hook per transport:
  lost, late, duplicated, refused, corrupted or mixed answers, bus-off;
* :mod:`.state` -- the drive-side state report (``serve-sim --state-file``);
* :mod:`.scenario` -- runs one fault against a served drive and judges the
  outcome (used by the tests and ``benchmarks/faults.py``).

What the host does about each fault (the policy the tests hold it to)
---------------------------------------------------------------------
A run either *ends* -- the runner quick-stops and disables the axis, marks
the log ``# status = incomplete`` with the one-line reason and re-raises --
or *rides through*, when the protocol proves a retry or a wait is safe. A
lock-step sample is bound to its cycle: a request that may have clocked the
drive is never repeated (a repeated SYNC, FC23 or feedback query would skip
a sample or apply a command twice).

=================  ============================================================
CANopen
``drop``           ends: DriveTimeoutError "no TPDO ... of SYNC" (the drive was
                   clocked; a sync TPDO cannot be asked for again)
``delay`` < pdo    rides through (the host waits up to ``pdo_timeout``, 100 ms)
``delay`` > pdo    ends: timeout; the late TPDOs are recognised (time stamp
                   0x1013 already seen) and dropped
``dup``            rides through: the duplicate's time stamp was seen, dropped
``busoff``         ends: timeout; the drive faults itself (0x8140, abort
                   connection option 0x6007 = 1), the host cannot reach it
``fault``          ends: DriveFaultError from the statusword (and its EMCY)
``emcy``           ends: DriveFaultError "sent EMCY": any error EMCY stops a run
Modbus
``exception`` 6    rides through: "busy" means not executed; retried once
``exception`` *    ends: the typed error of :func:`servobench.drivers.modbus.drive.exception_error`
``timeout``, ``crc``  ends: DriveTimeoutError (the FC23 may have been executed)
``delay``          rides through below ``timeout=`` (0.25 s), else ends
``fault``          ends: DriveFaultError from the fault register
(``drop``/``dup`` are not injected: the pymodbus server answers each request
once; a lost answer is what ``timeout`` shows the host)
Serial
``garble``, ``truncate``, ``interleave``  ends: MalformedReplyError; the
                   driver resynchronises the line before its next request
``drop``           ends: DriveTimeoutError
``dup``            rides through: a reply line repeated before the next request
                   is dropped; other unsolicited bytes end the run
``delay``          rides through below ``timeout=`` (0.1 s), else ends
``fault``          ends at the next error poll (``poll=``, 0.1 s): the feedback
                   reply carries no drive state, so the samples of up to one
                   poll period after the fault are logged
Every transport
``freeze``         ends: the runner sees position and velocity bit-identical
                   for ``frozen_cycles`` (100) cycles while the reported
                   velocity should have moved the position by two of its
                   smallest steps (or while ``|u| >= breakaway`` when given):
                   DriveError "feedback frozen"; those samples are in the log,
                   flagged by the reason
host killed        the drive's watchdog (heartbeat consumer, Modbus watchdog
                   register, serial watchdog) faults the axis; the log, flushed
                   per sample, ends without a trailer: ``# status = running``
                   from its header marks it incomplete
=================  ============================================================
"""
