"""The identified model: what it is, its files, the values to program from it, and its
validation against another log.

Modules
-------
servo     ``ServoModel``, ``IdentificationResult`` and the fit measure
file      read back any model file servobench writes (``read_model``)
program   the values to program into a drive, in the log's and the drive's own units (pure)
validate  how well a saved model reproduces another log (pure)
"""
