"""Time per pose of `session new` on the real drivers against labcal's fakes, in the planner's order and ordered.

`cli.ops.sessions.new_session` with ``robot_driver="ur"`` (ur-rtde against ``labcal_fakes.rtde_fake``, which moves
its simulated arm at the commanded speed and acceleration) and ``tracker_driver="serial"`` (the NDI driver on a pty
against ``labcal_fakes.devices.FakeNDIDevice``, which reports the targets where the fake controller's joints put
them, the tracker 2.6 m in front of the base). Robot profile: drivers/ur10-lab.toml with the joint limits narrowed
(NARROW_DEG) and the host of the fake; tracker profile: drivers/ndi-polaris.toml on the fake's pty. "planner's
order": the same plan with ``order_for_motion`` switched off. Wall time of the whole call (connecting, planning,
moving, settling, measuring, sealing) divided by the number of poses.

    python benchmarks/plan_rehearsal.py --poses 30   # about 7 minutes; output in benchmarks/results/plan_rehearsal.txt
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

import labcal.sessions.planning as planning
from labcal.cli.ops.sessions import new_session
from labcal.datasets import SessionStore, load_targets
from labcal.robots import load
from labcal_fakes.devices import FakeNDIDevice
from labcal_fakes.rtde_fake import FakeRTDEServer

ROOT = Path(__file__).resolve().parents[1]
NARROW_DEG = [[-90, 90], [-150, -30], [-150, 150], [-180, 0], [-180, 180], [-180, 180]]
TRACKER = np.array([2.6, 0.0, 0.6])  # m, base frame; the fake tracker's frame is the base frame moved there
HOME = (0.0, -1.5708, 1.5708, -1.5708, 0.0, 0.0)


def _session(folder: Path, poses: int, ordered: bool) -> tuple[float, object]:
    model = load("ur10").model
    targets_file = ROOT / "drivers" / "targets-example.toml"
    targets = load_targets(targets_file)
    with FakeRTDEServer(q0=HOME, control=True) as server:

        def provider():
            q = np.asarray(server.snapshot()["q"], dtype=float)
            return model.target_points(q[None], targets)[0] - TRACKER

        device = FakeNDIDevice(provider, seed=0)
        device.start()
        try:
            text = (ROOT / "drivers" / "ur10-lab.toml").read_text()
            text = text.replace('host = "192.168.1.10"', f'host = "{server.host}"')
            lower, upper = [lo for lo, _ in NARROW_DEG], [hi for _, hi in NARROW_DEG]
            text = text.replace("lower = [-360.0, -360.0, -360.0, -360.0, -360.0, -360.0]", f"lower = {lower}")
            text = text.replace("upper = [360.0, 360.0, 360.0, 360.0, 360.0, 360.0]", f"upper = {upper}")
            (folder / "robot.toml").write_text(text)
            ndi = (ROOT / "drivers" / "ndi-polaris.toml").read_text()
            (folder / "ndi.toml").write_text(ndi.replace('url = "/dev/ttyUSB0"', f'url = "{device.port}"'))
            original = planning.order_for_motion
            if not ordered:
                planning.order_for_motion = lambda q, *args, **kwargs: np.arange(len(q))
            try:
                start = time.monotonic()
                summary = new_session(
                    SessionStore(folder / "store"), robot="ur10", targets_file=targets_file, poses=poses,
                    robot_driver="ur", tracker_driver="serial", profile=str(folder / "robot.toml"),
                    tracker_profile=str(folder / "ndi.toml"), seed=0,
                )  # fmt: skip
                return time.monotonic() - start, summary
            finally:
                planning.order_for_motion = original
        finally:
            device.close()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--poses", type=int, default=30, help="poses per session (default 30)")
    args = parser.parse_args(argv)
    print(f"ur10-lab narrowed, {args.poses} poses, fake controller + fake NDI tracker on a pty")
    header = f"{'order':<16} {'exit':<8} {'valid':>5} {'rejected':>8} {'wall time':>10} {'per pose':>9}"
    print(header)
    print("-" * len(header))
    for name, ordered in (("planner's order", False), ("ordered", True)):
        with tempfile.TemporaryDirectory() as tmp:
            seconds, s = _session(Path(tmp), args.poses, ordered)
        print(
            f"{name:<16} {s.exit_status:<8} {s.valid:>5} {s.rejected:>8} {seconds:>8.1f} s "
            f"{seconds / args.poses:>7.2f} s"
        )


if __name__ == "__main__":
    main()
