"""The robot: IK/FK round trip, unreachable poses, reported versus true rod pose."""

import numpy as np
import pybullet
import pytest

from testbed.robot import Robot, RobotSpec, RodSpec, SweepSpec, rod_bodies


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


def test_analytic_jacobian_equals_finite_differences():
    """The inverse kinematics' Jacobian (pybullet's analytic one) against central differences
    of the forward kinematics at random joints: equal to the differences' own error (their
    step's curvature term and single-precision link poses, ~0.05 mm per unit)."""
    rng = np.random.default_rng(3)
    with Robot(RobotSpec(), rng=0) as robot:
        for _ in range(6):
            q = robot.lower + rng.uniform(0.1, 0.9, 5) * (robot.upper - robot.lower)
            J = robot._jacobian(q)
            ref = robot._jacobian_reference(q)
            assert np.abs(J - ref).max() < 0.1, np.abs(J - ref).max()
            assert np.abs(ref).max() > 100.0


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
    # the offending gap is named, a negative one too (a review: not shown)
    with pytest.raises(ValueError, match=r"3 bead diameters \(6 mm with bead_diameter_mm = "
                                         r"2\); got \[-27.0\] mm"):
        RodSpec(bead_spacings_mm=(14.0, -27.0, 16.0), bead_diameter_mm=2.0)
    # gaps that do not tell the beads apart (a held-out scene's equal gaps loaded, then
    # every view's calibration failed after a whole simulation)
    with pytest.raises(ValueError, match="beads 0-3 read backwards look like themselves"):
        RodSpec(bead_spacings_mm=(20.0,) * 7)
    with pytest.raises(ValueError, match="beads 0-3 look like beads 3-6"):
        RodSpec(bead_spacings_mm=(14.0, 27.0, 16.0, 14.0, 27.0, 16.0))
    with pytest.raises(ValueError, match="beads 0-3 look like beads 4-7 read backwards"):
        RodSpec(bead_spacings_mm=(14.0, 27.0, 16.0, 12.0, 16.0, 27.0, 14.0))
    RodSpec(bead_spacings_mm=(14.0, 27.0, 16.0, 12.0))          # a shorter rod is fine


def test_sweep_spec_refuses_planes_that_cannot_calibrate_or_validate():
    """A held-out scene with the near and far planes 0.1 mm apart and the validation row in
    the near plane passed its own validation and registered 158 mm off."""
    with pytest.raises(ValueError, match="at least 0.05 of the source-to-image distance"):
        SweepSpec(near_fraction=0.83, far_fraction=0.8301, validation_fraction=0.9)
    with pytest.raises(ValueError, match="validation_fraction = 0.83 lies 0 from a calibration"):
        SweepSpec(near_fraction=0.83, far_fraction=0.95, validation_fraction=0.83)
    with pytest.raises(ValueError, match="greater than or equal to 0.25"):
        SweepSpec(coverage=1e-6)
    # the shipped planes, and a row beyond the far plane, are fine
    SweepSpec(near_fraction=0.83, far_fraction=0.95, validation_fraction=0.89)
    SweepSpec(near_fraction=0.76, far_fraction=0.88, validation_fraction=0.94)


# --------------------------------------------------------------------------- clinic errors
def _rod_only(spec, **rod):
    return spec.model_copy(update=dict(rod=spec.rod.model_copy(update=rod)))


def _random_joints(rng, n):
    for _ in range(n):
        yield np.r_[rng.uniform(-1.5, 1.5), rng.uniform(0.4, 2.2) * rng.choice([-1, 1]),
                    rng.uniform(-300, 300), rng.uniform(-2.5, 2.5), rng.uniform(-1.0, 1.0)]


def test_absolute_accuracy_at_the_rod_is_in_the_published_range():
    """Default kinematic-parameter errors: the reported beads miss the true ones by
    0.1-0.6 mm (median over robots and poses; uncalibrated arms, docs/error-model.md)."""
    spec = _rod_only(RobotSpec(rod_mount_error_mm=0.0, rod_mount_error_deg=0.0),
                     bead_along_error_mm=0.0, bead_across_error_mm=0.0, sag=False)
    errs = []
    for seed in range(4):
        rng = np.random.default_rng(50 + seed)
        with Robot(spec, rng=seed) as robot:
            for q in _random_joints(rng, 8):
                robot.move_joints(q)
                e = np.linalg.norm(robot.bead_positions(true=True) - robot.bead_positions(),
                                   axis=1)
                errs.append(e.mean())
    med = float(np.median(errs))
    assert 0.1 < med < 0.6, med
    # the ideal profile's robot (0.02 mm / 0.002 deg) stays at repeatability level
    ideal = spec.ideal()
    small = []
    with Robot(ideal, rng=0) as robot:
        for q in _random_joints(np.random.default_rng(50), 8):
            robot.move_joints(q)
            small.append(np.linalg.norm(robot.bead_positions(true=True)
                                        - robot.bead_positions(), axis=1).mean())
    assert np.median(small) < med / 3


def test_bead_placement_shows_in_the_true_beads_only():
    spec = _rod_only(RobotSpec().without_errors(), bead_along_error_mm=0.1,
                     bead_across_error_mm=0.05)
    along, across = [], []
    for seed in range(6):
        with Robot(spec, rng=seed) as robot:
            robot.place_rod((700.0, 100.0, 150.0), (0.0, 1.0, 0.0))
            rep, tru = robot.bead_positions(), robot.bead_positions(true=True)
            local = robot.true_rod2robot.inverse().apply(tru)
            nominal = np.column_stack([spec.rod.bead_positions_mm(), np.zeros((8, 2))])
            along.extend(local[:, 0] - nominal[:, 0])
            across.extend((local[:, 1:] - nominal[:, 1:]).ravel())
            # the reported beads are the nominal rod's; the rendered beads are the true ones
            np.testing.assert_allclose(robot.true_rod2robot.inverse().apply(rep), nominal,
                                       atol=0.01)
            beads = [b for b in robot.rod_bodies() if b.name == "rod_beads"][0]
            np.testing.assert_allclose(beads.sphere_centers, tru, atol=1e-9)
    assert np.std(along) == pytest.approx(0.1, rel=0.3)
    assert np.std(across) == pytest.approx(0.05, rel=0.3)


def test_rod_sag_follows_the_cantilever_formula_and_gravity():
    rod = RodSpec()
    L = rod.mount_mm + rod.bead_positions_mm()[-1] + rod.tip_gap_mm + rod.tip_length_mm
    E = rod.youngs_modulus_gpa * 1e3                         # N/mm^2
    inertia = np.pi * (rod.diameter_mm / 2) ** 4 / 4         # mm^4
    q = rod.density_g_cm3 * 1e-6 * np.pi * (rod.diameter_mm / 2) ** 2 * 9.81  # N/mm
    P = 7.9e-6 * np.pi * (rod.tip_diameter_mm / 2) ** 2 * rod.tip_length_mm * 9.81  # N
    tip = q * L**4 / (8 * E * inertia) + P * L**3 / (3 * E * inertia)  # textbook end values
    assert rod.sag_mm([L - rod.mount_mm])[0] == pytest.approx(tip, rel=1e-9)
    assert rod.sag_mm([-rod.mount_mm])[0] == 0.0
    assert 0.2 < tip < 2.0   # a 10 mm ULTEM rod of ~0.3 m sags by a fraction of a mm
    spec = _rod_only(RobotSpec().without_errors(), sag=True)
    with Robot(spec, rng=0) as robot:
        robot.place_rod((700.0, 100.0, 150.0), (0.0, 1.0, 0.0))          # horizontal
        drop = robot.bead_positions()[:, 2] - robot.bead_positions(true=True)[:, 2]
        np.testing.assert_allclose(drop, rod.sag_mm(rod.bead_positions_mm()), atol=0.01)
        assert np.all(np.diff(drop) > 0)         # grows towards the free end
        d = np.array([0.0, 1.0, -1.0]) / np.sqrt(2)                   # 45 deg down
        robot.place_rod((700.0, 0.0, 250.0), d)
        dev = robot.bead_positions(true=True) - robot.bead_positions()
        np.testing.assert_allclose(np.linalg.norm(dev, axis=1),
                                   rod.sag_mm(rod.bead_positions_mm()) / np.sqrt(2), atol=0.01)


def test_rod_mounting_error_moves_the_true_rod():
    spec = RobotSpec(rod_mount_error_mm=0.1, rod_mount_error_deg=0.05).without_errors()
    spec = spec.model_copy(update=dict(rod_mount_error_mm=0.1, rod_mount_error_deg=0.05))
    shifts = []
    for seed in range(5):
        with Robot(spec, rng=seed) as robot:
            robot.place_rod((700.0, 100.0, 150.0), (0.0, 1.0, 0.0))
            shifts.append(np.linalg.norm(robot.rod_mount_error.t))
            diff = robot.bead_positions(true=True) - robot.bead_positions()
            assert 1e-3 < np.linalg.norm(diff, axis=1).max() < 1.5
    # |t| of a 3-D Gaussian of sigma 0.1 mm: mean 0.16 mm
    assert 0.05 < np.mean(shifts) < 0.3


def test_each_robot_error_source_keeps_its_draws_when_another_is_switched_off():
    """Kinematic offsets, rod mounting, bead placement and the encoders draw from streams
    of their own: switching the mounting off leaves the beads' errors, the offsets and the
    encoders' noise of the same seed as they were (the error budget compares
    configurations one source apart)."""
    spec = RobotSpec()
    assert spec.rod_mount_error_mm > 0 and spec.rod.bead_along_error_mm > 0
    no_mount = spec.model_copy(update=dict(rod_mount_error_mm=0.0, rod_mount_error_deg=0.0))
    out = []
    for s in (spec, no_mount):
        with Robot(s, rng=4) as robot:
            robot.place_rod((700.0, 100.0, 150.0), (0.0, 1.0, 0.0))
            out.append((robot.kinematic_offsets.copy(), robot.bead_errors_mm.copy(),
                        robot.q_true - robot.q_commanded,
                        np.linalg.norm(robot.rod_mount_error.t)))
    (k1, b1, q1, m1), (k2, b2, q2, m2) = out
    assert m1 > 0 and m2 == 0
    np.testing.assert_array_equal(k1, k2)
    np.testing.assert_array_equal(b1, b2)
    np.testing.assert_array_equal(q1, q2)
    assert np.abs(b1).max() > 0 and np.abs(q1).max() > 0


def test_a_user_urdf_is_loaded_and_a_file_that_is_none_is_named(tmp_path):
    """The builtin robot's URDF written to a file loads as a user URDF with the same joints;
    a file that is no URDF is refused in one line (a review's urdf = '/etc/passwd' let
    Bullet print its parser's lines first)."""
    from testbed.robot import robot_urdf

    good = tmp_path / "arm.urdf"
    good.write_text(robot_urdf(RobotSpec()))
    with Robot(RobotSpec(urdf=str(good)), rng=0) as user, Robot(RobotSpec(), rng=0) as builtin:
        assert np.allclose(user.lower, builtin.lower) and np.allclose(user.upper, builtin.upper)
    for text, match in (("root:x:0:0:root:/root:/bin/bash\n", "is not a URDF \\(not XML"),
                        ("<sdf version='1.6'/>",
                         "is not a URDF \\(its XML root is <sdf>, expected <robot>")):
        bad = tmp_path / "bad.urdf"
        bad.write_text(text)
        with pytest.raises(ValueError, match="robot.urdf: .*bad.urdf' " + match):
            Robot(RobotSpec(urdf=str(bad)), rng=0)


def test_bullets_parser_messages_stay_off_the_output(tmp_path, capfd):
    """Bullet prints its URDF parser's warnings and errors (without a final newline) on the
    C stdout and stderr: a URDF without inertia gave five warning lines before the error,
    the error glued to the last ('...basetestbed: ...'). Now none reach the output, and the
    parser's last message goes into the error of a file it cannot load."""
    import pybullet  # noqa: F401  (imported, its build banner printed, before the capture)

    capfd.readouterr()
    cases = (
        ('<robot name="r"><link name="base"/></robot>', "lacks the joints"),
        ('<robot name="r"><joint name="j" type="revolute"><parent link="a"/>'
         '<child link="b"/></joint></robot>',
         "cannot be loaded as a URDF .*its parser said: No links found"),
    )
    for text, match in cases:
        f = tmp_path / "user.urdf"
        f.write_text('<?xml version="1.0"?>\n' + text + "\n")
        with pytest.raises(ValueError, match=match):
            Robot(RobotSpec(urdf=str(f)), rng=0)
        out, err = capfd.readouterr()
        assert out == "" and err == "", (out, err)


def test_rod_and_sweep_fields_absurd_as_a_whole_are_refused():
    """A review's rod of 24 m and a validation row 1e8 mm off the axis loaded, then failed as
    'unreachable ... move the view', naming the wrong field."""
    from pydantic import ValidationError

    from testbed.robot import RodSpec, SweepSpec

    with pytest.raises(ValidationError, match=r"the rod would be 24157 mm long .*at most "
                                              r"1000 mm"):
        RodSpec(bead_spacings_mm=(4000.0, 3000.0, 5000.0, 12000.0))
    with pytest.raises(ValidationError, match="validation_offset_mm"):
        SweepSpec(validation_offset_mm=1e8)
    with pytest.raises(ValidationError, match="move_time_s"):
        SweepSpec(move_time_s=1e-9)
    assert RodSpec().bead_spacings_mm and SweepSpec().validation_offset_mm == 5.0


def test_a_touched_point_is_reported_with_the_robots_own_error():
    """Robot.digitize: the nominal model sent to the reported point puts the true arm's first
    bead (with the rod's mounting error) back on the touched point, to second order; a
    perfect robot reports the point itself; nothing is drawn from the robot's stream."""
    rng = np.random.default_rng(11)
    spec = RobotSpec(kinematic_offset_mm=0.3, kinematic_offset_deg=0.03,
                     rod_mount_error_mm=0.2, rod_mount_error_deg=0.1, encoder_noise_deg=0.0,
                     encoder_noise_mm=0.0)
    with Robot(spec.without_errors(), rng=1) as perfect, Robot(spec, rng=2) as robot:
        checked = 0
        for p, _ in _random_reachable_lines(robot, rng, 6):
            radial = np.array([p[0], p[1], 0.0]) / np.hypot(p[0], p[1])
            try:     # the arm on the branch that reaches p along the radial direction...
                robot.move_joints(robot.inverse(p, radial))
            except ValueError:
                continue
            assert np.linalg.norm(perfect.digitize(p) - p) < 0.01
            state = robot.rng.bit_generator.state
            x = robot.digitize(p)        # ...which its inverse kinematics starts from
            assert robot.rng.bit_generator.state == state
            err = np.linalg.norm(x - p)
            assert 0.05 < err < 5.0                     # the robot's own absolute error
            # commanding the reported point on that branch: the true bead is back at p, up
            # to the error field's change over err (second order)
            robot.place_rod(x, radial)
            assert np.linalg.norm(robot.bead_positions(true=True)[0] - p) < 0.1 * err
            checked += 1
        assert checked >= 2
    with Robot(RobotSpec(), rng=0) as robot:
        assert robot.digitize([1e5, 0.0, 0.0]) is None   # far out of reach


def test_placed_cylinders_equal_trimesh_made_and_moved():
    """The rod's cylinders are made once per size and moved per frame: the same vertices
    and faces, bit for bit, as trimesh's cylinder made anew and moved by apply_transform
    (the reference), on random rigid poses; the cached arrays stay untouched."""
    import trimesh

    from reglib.geometry import RigidTransform
    from testbed.robot import _cylinder_arrays, _placed_cylinder

    rng = np.random.default_rng(5)
    for _ in range(20):
        r, h, n = rng.uniform(0.5, 8.0), rng.uniform(5.0, 400.0), int(rng.integers(8, 64))
        pose = RigidTransform.from_rotvec(rng.normal(size=3), rng.uniform(-900, 900, 3))
        ref = trimesh.creation.cylinder(radius=r, height=h, sections=n)
        ref.apply_transform(pose.as_matrix())
        got = _placed_cylinder(r, h, n, pose.as_matrix())
        assert np.array_equal(got.vertices, ref.vertices)
        assert np.array_equal(got.faces, ref.faces)
        got.faces[0] = got.faces[0][::-1]                # a user's edit stays in its mesh
        assert np.array_equal(_cylinder_arrays(r, h, n)[1][0], ref.faces[0])


def test_a_slide_beyond_an_operating_room_is_refused():
    """A bad-input review: slide_range_mm = (-1e9, 1e9) was taken; ends within 5 m stay."""
    with pytest.raises(ValueError, match=r"slide_range_mm: expected ends within \+-5000 mm"):
        RobotSpec(slide_range_mm=(-1e9, 1e9))
    assert RobotSpec(slide_range_mm=(-5000.0, 5000.0)).slide_range_mm == (-5000.0, 5000.0)


def test_robot_lengths_in_metres_are_told_their_units():
    """A held-out review (h93) gave [robot] lengths in metres: the run said the first sweep
    pose was unreachable and to move the view. The links and the slide are refused naming
    the field and the unit; lengths far too long too; the base height, which may be small,
    is named in the unreachable pose's message (tests/test_cli.py)."""
    for field, value, match in (("link1_mm", 0.55, "link1_mm: .* got 0.55; given in metres"),
                                ("link2_mm", 0.45, "link2_mm: .*given in metres"),
                                ("quill_mm", 0.25, "quill_mm: .*given in metres"),
                                ("link1_mm", 5.5e5, "link1_mm: expected a surgical arm's"),
                                ("base_height_mm", 1e8, "base_height_mm: expected at most"),
                                ("slide_range_mm", (-0.9, 0.3), "spans 1.2 mm.*metres")):
        with pytest.raises(ValueError, match=match):
            RobotSpec(**{field: value})
    RobotSpec(base_height_mm=0.0, link1_mm=10.0, slide_range_mm=(-5.0, 5.0),
              pitch_drop_mm=2.0)       # still taken (a compact wrist's pitch axis: h94)
