"""EMPS cross-test: the model identified on emps.csv, validated on the pulses record.

Prints ``servobench validate``'s figures for servobench's own model and for
the published IDIM-LS model (Janot et al., "Data set and reference models of
EMPS", 2019), beside the figure the reference publishes (relative force
error 5.98 % on the pulses record) and that figure re-run here with the
reference script's processing (Butterworth 100 Hz on position, central
differences, decimation by 10), which tells the metric's processing apart
from the model.

Run: ``python benchmarks/validate_emps.py``
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from scipy import signal
from scipy.io import loadmat

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from servobench.bench.identify.auto import identify  # noqa: E402
from servobench.bench.log.io import read_log  # noqa: E402
from servobench.bench.model.servo import ServoModel  # noqa: E402
from servobench.bench.model.validate import validate  # noqa: E402

EMPS = Path(__file__).resolve().parents[2] / "shared" / "data" / "emps"
PUBLISHED = {"M": 95.1089, "Fv": 203.5034, "Fc": 20.3935, "offset": -3.1648}
PUBLISHED_ERROR = {"emps": 4.08, "pulses": 5.98}


def reference_script(mat: str, M: float, Fv: float, fc_pos: float, fc_neg: float) -> float:
    """Relative force error [%] the way the reference's script computes it."""
    d = loadmat(EMPS / mat, squeeze_me=True)
    force = float(d["gtau"]) * d["vir"]
    b, a = signal.butter(4, 100.0 / 500.0)
    q = signal.filtfilt(b, a, d["qm"])
    dq = np.gradient(q, 1e-3)
    ddq = np.gradient(dq, 1e-3)
    fc, offset = 0.5 * (fc_pos + fc_neg), 0.5 * (fc_pos - fc_neg)
    X = np.column_stack([ddq, dq, np.sign(dq), np.ones_like(dq)])[49:]
    Xd = np.column_stack([signal.decimate(X[:, i], 10) for i in range(4)])
    yd = signal.decimate(force[49:], 10)
    err = yd - Xd @ np.array([M, Fv, fc, offset])
    return 100 * float(np.linalg.norm(err) / np.linalg.norm(yd))


def main() -> None:
    ours = identify(read_log(EMPS / "emps.csv")).model
    p = PUBLISHED
    published = ServoModel(p["M"], p["Fv"], p["Fc"] + p["offset"], p["Fc"] - p["offset"])
    print("EMPS: relative force error 100 ||u - u_hat|| / ||u|| [%], u_hat the inverse model on the motion")
    print(f"{'model':<26}{'record':<10}{'validate':>10}{'ref. script':>13}{'published':>11}"
          f"{'fit %':>9}{'gap %':>8}")  # fmt: skip
    for label, m in (("servobench (emps.csv)", ours), ("published IDIM-LS", published)):
        for record, csv_name, mat in (("emps", "emps.csv", "DATA_EMPS.mat"),
                                      ("pulses", "emps_pulses.csv", "DATA_EMPS_PULSES.mat")):  # fmt: skip
            v = validate(m, read_log(EMPS / csv_name))
            script = reference_script(mat, m.M, m.B, m.coulomb_pos, m.coulomb_neg)
            pub = f"{PUBLISHED_ERROR[record]:.2f}" if m is published else "-"
            print(f"{label:<26}{record:<10}{v.force_error_percent:>10.2f}{script:>13.2f}{pub:>11}"
                  f"{v.fit_percent:>9.2f}{v.gap_percent:>8.2f}")  # fmt: skip
    print(f"servobench's model: M = {ours.M:.2f} kg, B = {ours.B:.2f} N s/m, "
          f"Coulomb +{ours.coulomb_pos:.2f} / -{ours.coulomb_neg:.2f} N")


if __name__ == "__main__":
    main()
