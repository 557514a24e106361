"""The SIDBE procedure on a drive: design the excitation, stream, identify, verify, repeat
(the paper's step 6), in open loop or, on an axis with limited travel, in closed loop.

Modules
-------
excitation     the periodic multi-frequency binary excitation ``u1``, ``u2 = r u1``
sidbe          the procedure: options, the open-loop rounds, the result and ``model.json``
closed_rounds  the rounds in closed loop, inside the travel window (the streaming itself
               is :mod:`servobench.bench.run.closed`)
run_folder     the run folder: which file is which, refusing to overwrite an earlier run
"""
