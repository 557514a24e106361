"""The few signal-processing routines identification and diagnosis call thousands of times,
without importing :mod:`scipy.signal`.

``import scipy.signal`` takes 0.6 s of a process on the 2-core machine of the benchmarks (its
array-API layer parses every docstring at import), a fifth of a whole ``servobench diagnose``
on the EMPS log. Each routine here is scipy's, operation for operation, for the cases the
package uses, and is tested against it (``tests/test_dsp.py``):

* :mod:`.iir`: the Butterworth low-pass design, ``lfilter`` with initial conditions, the
  filter's steady state, its frequency response;
* :mod:`.spectral`: Welch's power and cross spectral densities.

Everything else of scipy.signal (Savitzky-Golay, ``cont2discrete``) is imported where used,
on paths the default procedures do not take.
"""
