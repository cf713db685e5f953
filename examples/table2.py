"""The paper's Table 2 (PD-ILC vs D-ILC) with the public API alone — a notebook-style script.

The experiment behind each row is what ``ilcrig reproduce`` runs for Table 2
(host/studies/paper/plan.py): path 1, a 0.25 s single journey, the paper's 4-5-6-7 polynomial motion
law, no disturbance, ten trials; the table gives MaxE and the mean error (MAE) of each joint in the
last trial, in degrees.  The published numbers are typed in below (Li et al. 2022, Table 2).

    python examples/table2.py [--iterations 10]
"""

from __future__ import annotations

import argparse

import numpy as np

import ilcrig

#: the paper's Table 2: law → (MaxE j1..j4, mean error j1..j4), deg
PAPER = {
    "PD-ILC": ((0.71, 0.0021, 0.61, 0.0016), (0.27, 0.0004, 0.24, 0.0003)),
    "D-ILC": ((0.94, 0.0035, 0.81, 0.0026), (0.33, 0.0018, 0.30, 0.0016)),
}
#: our law for each row: the paper's law as implemented here and its D-type baseline
LAWS = {"PD-ILC": "pd-ilc", "D-ILC": "d-ilc"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iterations", type=int, default=10)
    iterations = ap.parse_args().iterations

    # %% run both rows in-process
    results = {
        row: ilcrig.Experiment(law=law, path="1", cycle_s=0.25, profile="poly4567", iterations=iterations).run()
        for row, law in LAWS.items()
    }

    # %% the table: our last trial beside the paper's numbers
    header = (
        "case      source  " + "  ".join(f"MaxE j{j}" for j in range(1, 5)) + "  " + "  ".join(f" MAE j{j}" for j in range(1, 5))
    )
    print(header)
    for row, res in results.items():
        last = res.final
        ours = np.concatenate([last.max_abs_deg, last.mae_deg])
        paper = np.concatenate(PAPER[row])
        print(f"{row:<8}  ilcrig  " + "  ".join(f"{v:7.4f}" for v in ours))
        print(f"{'':<8}  paper   " + "  ".join(f"{v:7.4f}" for v in paper))

    # %% the paper's claim: PD-ILC ends below D-ILC on every joint (MaxE and mean error)
    pd, d = results["PD-ILC"].final, results["D-ILC"].final
    beats = bool(np.all(pd.max_abs_deg < d.max_abs_deg) and np.all(pd.mae_deg < d.mae_deg))
    print(f"PD-ILC below D-ILC on every joint: {'yes' if beats else 'no'}")
    print(f"digests: PD-ILC {results['PD-ILC'].digest[:16]}…, D-ILC {results['D-ILC'].digest[:16]}…")


if __name__ == "__main__":
    main()
