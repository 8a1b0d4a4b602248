"""Fewer targets on hard data, default options, against the independent plain least-squares fit.

Five adversarial data sets the target-count work was not built on (36-pose single-joint sweeps, a singular wrist,
two targets, 30 % of cells empty, tracker-frame data with one target), each fitted on its first two thirds with
``fit(…, "local-poe")`` and ``fit(…, "auto")`` (seed 0) and with ``bench.plain_lsq.fit_plain``; the held-out error
is the mean distance to the true (noise-free) target points of the last third, in the data's frame.

    python benchmarks/unseen_targets.py > benchmarks/results/unseen_targets.txt
"""

import warnings

import numpy as np

import scenarios as S
from labcal.calibration.fit import fit
from labcal.calibration.observations import Observations
from labcal.robots import load
from plain_lsq import fit_plain

warnings.filterwarnings("ignore")


def held(scn, k_fit):
    return scn.subset(np.arange(k_fit)), scn.subset(np.arange(k_fit, scn.k))


cases = {
    "sweeps 1 target": lambda: S.with_targets(S.sweeps("ur10", n_poses=36, seed=5), [0]),
    "singular wrist 1 target": lambda: S.with_targets(S.singular_wrist("ur10", 60, seed=6), [0]),
    "good 60 poses, 2 targets": lambda: S.with_targets(S.good("ur10", 60, seed=7), [0, 1]),
    "good, 3 targets, 30% missing": lambda: S.with_dropout(S.good("ur10", 60, seed=8), 0.3, seed=1),
    "tracker frame, 1 target": lambda: S.with_targets(S.in_tracker_frame(S.good("ur10", 90, seed=9)), [0]),
}
for name, make in cases.items():
    scn = make()
    k_fit = int(scn.k * 2 / 3)
    a, b = held(scn, k_fit)
    nominal = load(scn.robot).model
    obs = Observations(a.q, a.points, a.targets, a.frame)
    row = [name]
    # held-out: true points at held-out poses (noise-free), base frame
    truth = scn.actual.true_points(b.q, b.targets)
    if scn.frame == "tracker":
        Tt = scn.T_tracker_base
        truth = np.einsum("ab,kmb->kma", Tt[:3, :3], truth) + Tt[:3, 3]

    def to_frame(robot, p):
        T = np.asarray(robot.T_tracker_base, float)
        return np.einsum("ab,kmb->kma", T[:3, :3], p) + T[:3, 3]

    for method in ("local-poe", "auto"):
        try:
            res = fit(obs, nominal, method, seed=0)
            pred = to_frame(res.robot, res.robot.predict_points(b.q, b.targets))
            err = np.linalg.norm(pred - truth, axis=-1).mean()
            row.append(f"{method} {err * 1e3:.3f} mm ({len(res.warnings)} warn: {[w['code'] for w in res.warnings]})")
        except Exception as e:
            row.append(f"{method} CRASH {type(e).__name__}: {e}")
    try:
        pf = fit_plain(nominal, a.q, a.points, a.targets, a.frame)
        pred = pf.predict_points(b.q, b.targets) if hasattr(pf, "predict_points") else None
        row.append(f"plain {np.linalg.norm(pred - truth, axis=-1).mean() * 1e3:.3f} mm (converged {pf.converged})")
    except Exception as e:
        row.append(f"plain CRASH {e}")
    print(" | ".join(row), flush=True)
