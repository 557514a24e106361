"""Field commissioning: from "plugged in" to "identified, compensated, documented".

The step sequence (:mod:`servobench.bench.commission.sequence`) checks the link and the
drive, confirms the limits, bump-tests the axis, runs SIDBE with its
verification loop and the diagnosis, designs friction feed-forward and a
velocity-loop PI from the identified model, checks both in simulation and
writes the commissioning record (``model.json``, the log, ``report.html``,
``commission.mat``): verdict and identity first, then the values to program
into the drive, then the evidence. The values to program themselves are
computed by :mod:`servobench.bench.model.program` (pure, shared with
``servobench program``).

Modules
-------
errors       CommissionRefused
config       the ``bench.toml`` commissioning configuration
limits       confirm the safety limits and put them into the drive URL
checks       link, identity, state and fault checks
bump         the bump test: does it move, in the right direction, with sane feedback
integration  the one adapter to the SIDBE procedure, the model and the diagnosis
design       friction feed-forward and PI design (pure)
closedloop   velocity-loop simulation of the design on the identified plant
source       which model the values to program come from (SIDBE, or the diagnosed model)
record       model.json, the .mat export, commission.json
figures      the plots only commissioning draws (excitation, bump, compensation)
report       the self-contained HTML page
document     the report sections from the results
ui           messages and progress bars (rich)
sequence     the steps, Ctrl-C safe
"""

from servobench.bench.commission.errors import CommissionRefused

__all__ = ["CommissionRefused"]
