"""The servobench log: its format, the parsed table, column mappings of other tools' files, and
which axis and time a log belongs to.

Modules
-------
io        read and write the log format, streaming (``read_log``, ``LogWriter``, ``ExperimentLog``)
table     the text of a CSV log parsed: metadata lines, header, the table of numbers
mapping   naming the signals of another tool's file (``--columns``, ``--mat-map``)
identity  the ``# axis`` and ``# time`` of a log (which axis, when)
"""
