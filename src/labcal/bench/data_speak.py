"""Corrections only where the data speak (issue 27): narrow data, the weak-direction rule, the validity region.

:func:`narrow` simulates an ISO-9283-style series: the UR10's tool at one constant orientation, its position
uniform in a cube (default 300 mm), base or tracker frame. :func:`main` prints, for that series and a wide one,
the held-out target-point error and the corrections of local POE with the rule (default options), without it
(``error_bound=inf``), with a prior toward the nominal instead, and of an independent plain least-squares fit
(:mod:`labcal.bench.plain_lsq`), plus whether the default fit passes the gates (an export without ``--force``).

    python benchmarks/data_speak.py
"""

from __future__ import annotations

import math

import numpy as np

from labcal.bench.paper import _ik
from labcal.bench.plain_lsq import fit_plain
from labcal.calibration import Observations, fit
from labcal.calibration.local_poe import fit_local_poe
from labcal.kinematics import se3
from labcal.robots import load
from labcal.simulation import ErrorSpec, simulate
from labcal.simulation.scenarios import TARGETS

Q0 = np.array([0.3, -1.3, 1.6, -1.9, -1.57, 0.4])  # rad: the cube's centre pose (elbow up, wrist down)
T_TRACKER = se3.pose(np.array([3.0, 1.0, -0.5]))


def narrow(
    k: int = 80,
    *,
    cube: float = 0.3,
    tilt: float = 0.0,
    spin: float = 0.0,
    seed: int = 0,
    frame: str = "tracker",
    held_out: int = 0,
):
    """(observations, held-out (q, true points in the observations' frame), nominal model, true robot): k poses of
    the UR10 with the tool at the orientation of :data:`Q0` and its position uniform in a cube of side ``cube``
    (m) around it; tilt > 0 (rad) turns each pose's tool by a random rotation up to it ("little change of
    orientation"); spin > 0 (rad) turns it about its own z axis by up to that, the axis itself fixed. The
    held-out poses come from the same cube, measured without noise."""
    spec = load("ur10")
    model = spec.model
    actual = simulate(spec, ErrorSpec.default(), seed=seed)
    rng = np.random.default_rng([seed, 27])
    T0 = model.fk(Q0)

    def poses(count):
        T = np.tile(T0, (count, 1, 1))
        T[:, :3, 3] = T0[:3, 3] + rng.uniform(-cube / 2, cube / 2, (count, 3))
        if tilt > 0:
            T[:, :3, :3] = se3.exp_so3(rng.uniform(-tilt, tilt, (count, 3))) @ T0[:3, :3]
        if spin > 0:
            about_z = np.zeros((count, 3))
            about_z[:, 2] = rng.uniform(-spin, spin, count)
            T[:, :3, :3] = T[:, :3, :3] @ se3.exp_so3(about_z)
        q, ok = _ik(model, T, Q0)
        return q[ok]

    q = poses(k)
    T = T_TRACKER if frame == "tracker" else np.eye(4)

    def in_frame(p):
        return np.einsum("ab,kmb->kma", T[:3, :3], p) + T[:3, 3]

    points = in_frame(actual.measure(q, TARGETS, np.random.default_rng([seed, 7919])))
    obs = Observations(q, points, TARGETS, frame=frame)
    qh = poses(held_out) if held_out else np.zeros((0, 6))
    truth = in_frame(actual.true_points(qh, TARGETS)) if held_out else np.zeros((0, 3, 3))
    return obs, (qh, truth), model, actual


def point_error(robot, q, truth) -> float:
    """Mean held-out target-point error (m) of a calibrated robot, in the data's frame."""
    T = np.asarray(robot.T_tracker_base)
    pred = np.einsum("ab,kmb->kma", T[:3, :3], robot.predict_points(q, TARGETS)) + T[:3, 3]
    return float(np.mean(np.linalg.norm(pred - truth, axis=-1)))


def _largest_correction(robot, q) -> float:
    return float(np.max(np.abs(robot.correct(q, extrapolate=True) - q)))


def main(argv=None) -> int:
    for tilt in (0.0, 0.1):
        _table(tilt)
    return 0


def _table(tilt: float) -> None:
    obs, (qh, truth), model, _actual = narrow(80, tilt=tilt, held_out=60)
    box = np.random.default_rng(3).uniform(obs.q.min(0), obs.q.max(0), (200, 6))
    print(f"\nnarrow UR10 series: 80 poses, tool orientation within ±{tilt:g} rad per axis, 300 mm cube, tracker "
          "frame; 60 held out")  # fmt: skip
    print(f"{'fit':34s} {'weak':>4s} {'held-out mm':>11s} {'max |Δq| data box rad':>22s} {'max tool frame Δ mm':>19s}")
    rows = [
        ("local POE, rule (default)", {}),
        ("local POE, no rule (error_bound=inf)", {"error_bound": math.inf}),
        ("local POE, prior toward nominal", {"weak_rule": "prior"}),
    ]
    for eb in (0.05, 0.02, 0.005, 0.002, 0.001):
        rows.append((f"local POE, rule, error_bound {eb * 1e3:g} mm", {"error_bound": eb}))
    for name, opts in rows:
        robot, info = fit_local_poe(obs, model, **opts)
        tool = np.abs(info["delta_zeta"][:, :3]).max() * 1e3
        print(f"{name:34s} {info['weak']:4d} {point_error(robot, qh, truth) * 1e3:11.4f} "
              f"{_largest_correction(robot, box):22.4f} {tool:19.2f}")  # fmt: skip
    plain = fit_plain(model, obs.q, obs.points, TARGETS, frame="tracker")
    err = float(np.mean(np.linalg.norm(plain.predict_points(qh, TARGETS) - truth, axis=-1)))
    print(f"{'plain least squares (independent)':34s} {'':4s} {err * 1e3:11.4f}")
    result = fit(obs, model, "local-poe")
    codes = [w["code"] for w in result.warnings]
    print(f"fit(method='local-poe') default options: warnings {codes or 'none'} (export without --force: "
          f"{'yes' if not codes else 'no'}); validity radius {result.robot.validity.radius:.3f} rad, "
          f"{np.mean(result.robot.validity.inside(box)):.0%} of the data's joint box inside it")  # fmt: skip
    for note in result.notes:
        if note.startswith("weak:"):
            print("  " + note[:400])
