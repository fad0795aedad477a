"""The robot: IK/FK round trip, unreachable poses, reported versus true rod pose."""

import numpy as np
import pybullet
import pytest

from testbed.robot import Robot, RobotSpec, RodSpec, rod_bodies


def _random_reachable_lines(robot, rng, n):
    """Rod lines made by the nominal arm at random joints (so they are reachable)."""
    out = []
    for _ in range(n):
        q = np.r_[rng.uniform(-1.5, 1.5), rng.uniform(0.4, 2.2) * rng.choice([-1, 1]),
                  rng.uniform(-300, 300), rng.uniform(-2.5, 2.5), rng.uniform(-1.0, 1.0)]
        pose = robot.forward(q)
        out.append((pose.t.copy(), pose.R[:, 0].copy()))
    return out


def test_ik_fk_round_trip_below_0_01_mm():
    rng = np.random.default_rng(7)
    spec = RobotSpec().without_errors()
    with Robot(spec, rng=1) as robot:
        s = spec.rod.bead_positions_mm()
        for p, d in _random_reachable_lines(robot, rng, 8):
            robot.place_rod(p, d)
            beads = robot.bead_positions()
            want = p + s[:, None] * d
            assert np.abs(beads - want).max() < 0.01
            # the true arm of a perfect robot is where the robot says
            assert np.abs(robot.bead_positions(true=True) - beads).max() < 1e-3


def test_reported_pose_differs_from_true_pose_with_robot_errors():
    rng = np.random.default_rng(3)
    spec = RobotSpec(encoder_noise_deg=0.002, encoder_noise_mm=0.005,
                     kinematic_offset_mm=0.05, kinematic_offset_deg=0.005)
    with Robot(spec, rng=5) as robot:
        diffs = []
        for p, d in _random_reachable_lines(robot, rng, 5):
            robot.place_rod(p, d)
            # the robot reports the commanded line (its servo reads the commanded joints)
            rep = robot.bead_positions()
            assert np.linalg.norm(rep[0] - p) < 0.01
            diffs.append(np.abs(robot.bead_positions(true=True) - rep).max())
        diffs = np.array(diffs)
        assert np.all(diffs > 1e-3)     # a real robot is never exactly where it says
        assert np.all(diffs < 1.0)      # but close (offsets of 0.05 mm / 0.005 deg)


def test_unreachable_pose_raises_with_distance():
    with Robot(RobotSpec(), rng=0) as robot:
        with pytest.raises(ValueError, match=r"unreachable.*mm off the commanded line"):
            robot.place_rod((3000.0, 0.0, 0.0), (1.0, 0.0, 0.0))
        with pytest.raises(ValueError, match="zero length"):
            robot.place_rod((600.0, 0.0, 0.0), (0.0, 0.0, 0.0))
        with pytest.raises(ValueError, match=r"\(3,\)"):
            robot.place_rod((600.0, 0.0), (1.0, 0.0, 0.0))


def test_close_disconnects_the_client():
    robot = Robot(RobotSpec(), rng=0)
    cid = robot.client
    assert pybullet.getConnectionInfo(physicsClientId=cid)["isConnected"] == 1
    robot.close()
    assert pybullet.getConnectionInfo(physicsClientId=cid)["isConnected"] == 0
    robot.close()  # twice is harmless


def test_rod_bodies_put_the_beads_on_the_axis():
    from reglib.geometry import RigidTransform

    rod = RodSpec()
    pose = RigidTransform.from_rotvec([0.1, -0.4, 0.7], [500.0, 20.0, 100.0])
    rodb, beads, tip = rod_bodies(rod, pose)
    assert rodb.mesh.is_watertight and tip.mesh.is_watertight
    assert beads.inside == rodb.name and beads.material == "steel"
    s = rod.bead_positions_mm()
    want = pose.t + s[:, None] * pose.R[:, 0]
    assert np.allclose(beads.sphere_centers, want, atol=1e-9)
    # every bead lies inside the ULTEM cylinder
    assert rodb.mesh.contains(beads.sphere_centers).all()


def test_rod_spec_rejects_too_few_or_too_close_beads():
    with pytest.raises(ValueError, match="at least 3 gaps"):
        RodSpec(bead_spacings_mm=(20.0, 30.0))
    with pytest.raises(ValueError, match="3 bead diameters"):
        RodSpec(bead_spacings_mm=(20.0, 5.0, 30.0))
