"""The simulated drive served as a CANopen CiA 402 node over socketcand (``serve-sim --transport canopen``).

:mod:`.serve_canopen` serves it on :mod:`.socketcand_server`'s hub (wire codec :mod:`.wire`);
:mod:`.drive` is the CiA 402 node with its :mod:`.pdo`, :mod:`.sync`, :mod:`.heartbeat`,
:mod:`.factor` and :mod:`.position_loop` parts, which the EtherCAT slave reuses for CoE.
"""
