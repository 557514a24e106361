"""The bench: excite a drive, log it, identify, diagnose and report (the SIDBE flow).

=============  ==============================================================
``run/``       streaming runs to a drive, the feedback check, timing figures
``identify/``  SIDBE, the joint estimator, IDIM-LS, verification
``diagnose/``  where simulation and measurement disagree, and which effect
``report/``    summaries, plots, the diagnose and commissioning reports
``commission`` field commissioning sequence
``commands/``  the ``servobench`` subcommands
``testing/``   harnesses for tests and benchmarks only (not installed)
=============  ==============================================================

At this level: the excitation design (:mod:`.excitation`), the log format
(:mod:`.logio`, with :mod:`.logtable` parsing the CSV text and :mod:`.logmap`
naming the signals of other tools' files), the identified model
(:mod:`.model`) and its files (:mod:`.modelfile`), validation of a model
against another log (:mod:`.validate`), the SIDBE procedure
(:mod:`.procedure`) and the command line (:mod:`.cli`).
"""
