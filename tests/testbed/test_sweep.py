"""Sweeps: planning, rendering, and the calibration they feed (simulate -> estimate -> truth)."""

import numpy as np
import pytest

from reglib.calibration import calibrate
from reglib.markers import Markers, SweepData, find_markers
from testbed.fluoroscope import FluoroscopeSpec, ViewSpec, make_carm
from testbed.robot import Robot, RobotSpec, SweepSpec
from testbed.sweep import plan_sweep, run_sweep
from testbed.workspace import WorkspaceError

VIEW = ViewSpec(name="ap", isocenter_mm=(800.0, 0.0, 200.0))


def _spec(**kw):
    kw.setdefault("coverage", 0.75)
    return RobotSpec(sweep=SweepSpec(rows_per_plane=4, **kw)).without_errors()


@pytest.fixture(scope="module")
def clean_sweep():
    """A noise-free, distortion-free sweep with a perfect robot (10 frames)."""
    fl = FluoroscopeSpec(distortion=False, noise=False).ideal()
    carm = make_carm(fl, VIEW)
    with Robot(_spec(), rng=0) as robot:
        sw = run_sweep(robot, carm, fl, rng=1)
    return carm, sw


def test_plan_lays_rows_in_planes_perpendicular_to_the_beam():
    fl = FluoroscopeSpec(distortion=False).ideal()
    carm = make_carm(fl, VIEW)
    spec = _spec(tilt_deg=0.0)
    poses = plan_sweep(carm, spec)
    codes = [p.plane for p in poses]
    assert codes == [-1, 0, 0, 0, 0, 1, 1, 1, 1, 2]
    each = plan_sweep(carm, _spec(reference_frames="each"))
    assert [p.plane for p in each] == [-1, 0, 0, 0, 0, -1, 1, 1, 1, 1, -1, 2]
    for p in poses:
        depth = (p.point_robot - carm.source_robot) @ carm.axis_robot
        assert abs(p.direction_robot @ carm.axis_robot) < 1e-12   # rod parallel to the image
        want = {0: spec.sweep.near_fraction, 1: spec.sweep.far_fraction,
                2: spec.sweep.validation_fraction}.get(p.plane)
        if want is not None:
            assert depth == pytest.approx(want * carm.sid_mm)


def test_a_validation_row_mostly_outside_the_field_is_refused_naming_the_offset():
    """A review's validation_offset_mm of 90 mm left 2 of the row's 8 beads in a 9-inch
    field, and every view then failed as '0 validation markers', naming no field."""
    carm = make_carm(FluoroscopeSpec(), ViewSpec(name="v", isocenter_mm=(800.0, 0.0, 200.0)))
    plan_sweep(carm, _spec(validation_offset_mm=60.0))
    with pytest.raises(ValueError, match=r"robot.sweep.validation_offset_mm = 95: only \d of "
                                         r"the validation row's 8 beads fall within the field"):
        plan_sweep(carm, _spec(validation_offset_mm=95.0))
    # a rod too long for the field: no offset helps, and the rod's spacings are named (a
    # review: 432 mm between its end beads, and the default offset of 5 mm was blamed)
    from testbed.robot import RodSpec

    long_rod = RobotSpec(rod=RodSpec(bead_spacings_mm=(42.0, 81.0, 48.0, 36.0, 90.0, 63.0, 72.0)),
                         sweep=SweepSpec(rows_per_plane=4, coverage=0.75)).without_errors()
    with pytest.raises(ValueError, match=r"^robot.rod.bead_spacings_mm: the rod's 8 beads span "
                                         r"432 mm, and only [0-3] of them .* on the beam's axis"):
        plan_sweep(carm, long_rod)


@pytest.mark.slow
def test_sweep_reports_time_dose_and_positions(clean_sweep):
    carm, sw = clean_sweep
    assert sw.frames.shape == (10, carm.height_px, carm.width_px)
    assert sw.frames.dtype == np.uint8
    assert sw.duration_s == pytest.approx(10.0)
    assert sw.dose_mrem == pytest.approx(10.0 / 60.0 * 45.0)
    ref = sw.plane < 0
    assert np.isnan(sw.beads_reported[ref]).all()
    assert np.abs(sw.beads_reported[~ref] - sw.beads_true[~ref]).max() < 1e-3


@pytest.mark.slow
def test_detection_finds_every_bead_in_the_field_and_no_false_ones(clean_sweep):
    carm, sw = clean_sweep
    m = find_markers(SweepData(**sw.for_calibration()))
    # every marker is the bead it claims to be, at its true projection; sub-pixel on the
    # whole (a mutation audit: without the centroid's floor of the blob's values, RMS 0.097
    # against 0.039 px, the max test alone passed, and testbed run's mTRE moved 0.370 ->
    # 0.441 mm)
    true_xy = carm.project(sw.beads_true[m.frame, m.bead])
    err = np.linalg.norm(m.xy_px - true_xy, axis=1)
    assert np.abs(m.xy_px - true_xy).max() < 0.3
    assert np.sqrt(np.mean(err**2)) < 0.06, np.sqrt(np.mean(err**2))
    # every bead well inside the field is found; beads outside are reported missing
    for f in np.flatnonzero(sw.plane >= 0):
        rho = carm.fov_rho(carm.project(sw.beads_true[f]))
        found = set(m.bead[m.frame == f].tolist())
        inside = set(np.flatnonzero(rho < 0.95).tolist())
        assert inside <= found, f"frame {f}: beads {sorted(inside - found)} missed"
        assert all(rho[b] < 1.0 for b in found)
        outside = sorted(np.flatnonzero(rho > 1.0).tolist())
        if outside:
            msg = [p for p in m.problems if f"frame {f}:" in p and "not found" in p]
            assert msg and f"view {carm.name}" in msg[0]
            assert all(str(b) in msg[0] for b in outside)


@pytest.mark.slow
def test_calibration_from_rendered_sweep_validates_below_0_1_mm(clean_sweep):
    carm, sw = clean_sweep
    m = find_markers(SweepData(**sw.for_calibration()))
    cal = calibrate(m, min_markers=10)
    xy, pts = m.select(2)
    assert len(xy) >= 6
    assert cal.distances(xy, pts).max() < 0.1
    assert np.linalg.norm(cal.center_of_perspective() - carm.source_robot) < 5.0


def test_paths_match_true_rays_to_1e_3_mm_without_distortion_and_noise():
    """Planes parallel to the intensifier, exact marker pixels: the two-plane TPS is exact."""
    fl = FluoroscopeSpec(distortion=False, noise=False).ideal()
    carm = make_carm(fl, VIEW)
    spec = _spec()
    frame, plane, bead, xy, robot_pts = [], [], [], [], []
    with Robot(spec, rng=0) as robot:
        for f, pose in enumerate(plan_sweep(carm, spec)):
            if pose.plane < 0:
                continue
            robot.place_rod(pose.point_robot, pose.direction_robot)
            b = robot.bead_positions()
            frame.append(np.full(len(b), f))
            plane.append(np.full(len(b), pose.plane))
            bead.append(np.arange(len(b)))
            xy.append(carm.project(robot.bead_positions(true=True)))
            robot_pts.append(b)
    m = Markers(VIEW.name, *(np.concatenate(a) for a in (frame, plane, bead, xy, robot_pts)))
    cal = calibrate(m, smoothing=0.01)
    g = carm.pixel_grid()[::8, ::8].reshape(-1, 2)
    g = g[carm.fov_rho(g) <= 1.0]
    o, d = cal.paths(g)
    to, td = carm.true_rays(g)
    ax = carm.axis_robot
    for depth in (300.0, 650.0, 1000.0):
        p_true = to + (depth / (td @ ax))[:, None] * td
        t = ((p_true - o) @ ax) / (d @ ax)
        assert np.abs(o + t[:, None] * d - p_true).max() < 1e-3


@pytest.mark.slow
def test_a_hidden_bead_is_named_and_the_view_still_calibrates(clean_sweep):
    carm, sw = clean_sweep
    f = int(np.flatnonzero(sw.plane == 0)[1])
    b = 4
    x, y = np.rint(carm.project(sw.beads_true[f, b][None])[0]).astype(int)
    frames = sw.frames.copy()
    frames[:, y - 6:y + 7, x - 6:x + 7] = 3        # a steel instrument there all along
    data = sw.for_calibration() | {"frames": frames}
    m = find_markers(SweepData(**data))
    assert b not in m.bead[m.frame == f]
    msg = [p for p in m.problems if f"frame {f}:" in p and "not found" in p]
    assert msg and str(b) in msg[0], m.problems
    cal = calibrate(m, min_markers=10)
    xy, pts = m.select(2)
    assert cal.distances(xy, pts).max() < 0.1


@pytest.mark.slow
def test_the_validation_row_identified_by_the_calibrations_paths(clean_sweep):
    """The validation row identified by the calibration's paths: with 5 of its beads
    visible (the rest under steel all along), the beads that the full row's identification
    gives, at the same pixels; with 3, dropped (identify_row's 4 are needed); a calibration
    off by 5 mm at one end of the row (2 of 6 beads), dropped (blobs on the row that match
    no bead), not validated on the 4 beads it agrees with; paths 10 mm off across
    the beam and the rod: nothing identified."""
    from reglib.markers import identify_by_paths

    carm, sw = clean_sweep
    full = find_markers(SweepData(**sw.for_calibration()))
    cal = calibrate(full, min_markers=10)
    f = int(np.flatnonzero(sw.plane == 2)[0])
    seen = sorted(full.bead[full.frame == f].tolist())
    assert len(seen) >= 6

    def hide_all_but(keep):
        frames = sw.frames.copy()
        for b in set(seen) - set(keep):
            x, y = np.rint(carm.project(sw.beads_true[f, b][None])[0]).astype(int)
            frames[:, y - 6:y + 7, x - 6:x + 7] = 3
        return SweepData(**(sw.for_calibration() | {"frames": frames}))

    five = hide_all_but(seen[:5])
    frame, bead, xy, robot, notes = identify_by_paths(five, cal.distances, [f])
    assert np.all(frame == f) and sorted(bead.tolist()) == seen[:5]
    ref = {int(b): p for b, p in zip(full.bead[full.frame == f], full.xy_px[full.frame == f])}
    assert max(np.linalg.norm(ref[int(b)] - p) for b, p in zip(bead, xy)) < 1e-9
    assert np.allclose(robot, sw.beads_reported[f, bead])
    assert notes == [f"view {sw.view}, validation plane, frame {f}: 5 of 5 blob(s) identify "
                     "beads by the calibration's X-ray paths (within 3.6 mm)"]
    assert cal.distances(xy, robot).max() < 0.1

    three = identify_by_paths(hide_all_but(seen[:3]), cal.distances, [f])
    assert len(three[1]) == 0 and "4 needed; row dropped" in three[4][0]

    rod = sw.beads_reported[f, -1] - sw.beads_reported[f, 0]
    across = np.cross(carm.axis_robot, rod)
    across /= np.linalg.norm(across)
    split = sw.beads_reported[f, seen[3]] @ rod   # beads past the fourth: misplaced

    def one_end(xy_px, pts):
        return cal.distances(xy_px, pts + 5.0 * across * (pts @ rod > split + 1e-6)[:, None])

    bad = identify_by_paths(hide_all_but(seen[:6]), one_end, [f])
    assert len(bad[1]) == 0 and "2 other blob(s) on the row match no bead" in bad[4][0]

    def off(xy_px, pts):
        return cal.distances(xy_px, pts + 10.0 * across)

    assert len(identify_by_paths(five, off, [f])[1]) == 0


def test_an_unreachable_sweep_names_the_view_and_pose():
    fl = FluoroscopeSpec(distortion=False, noise=False).ideal()
    far = ViewSpec(name="far-away", isocenter_mm=(3000.0, 0.0, 200.0))
    carm = make_carm(fl, far)
    with Robot(_spec(), rng=0) as robot:
        with pytest.raises(WorkspaceError, match=r"view 'far-away': sweep pose 0 "
                                                 r"\(reference frame\): .*unreachable.*the "
                                                 r"robot cannot hold the rod there") as err:
            run_sweep(robot, carm, fl, rng=0)
    assert "-1" not in str(err.value).split(":")[1]      # no raw plane code


# --------------------------------------------------------------------------- workspace
def test_workspace_names_the_colliding_bodies_of_a_sweep():
    from reglib.geometry import RigidTransform
    from testbed.workspace import Workspace, check_sweep

    fl = FluoroscopeSpec(distortion=False, noise=False).ideal()
    # low enough for the intensifier to pass under the robot's links
    carm = make_carm(fl, ViewSpec(name="low", isocenter_mm=(800.0, 0.0, -100.0)))
    spec = _spec()
    poses = plan_sweep(carm, spec)
    with Robot(spec, rng=0) as robot:
        ws = Workspace(robot)
        free = check_sweep(ws, carm, poses)
        assert not any(p.contacts for p in free.poses)
        assert all(p.unreachable is None for p in free.poses)
        # a block where the near plane's rod lies: every near-plane pose hits it
        centre = carm.source_robot + spec.sweep.near_fraction * carm.sid_mm * carm.axis_robot
        ws.add_box("instrument_tray", (30.0, 30.0, 10.0), RigidTransform(np.eye(3), centre))
        rep = check_sweep(ws, carm, poses)
        hit = [p for p in rep.poses if any(c.b == "instrument_tray" for c in p.contacts)]
        assert hit and {p.plane for p in hit} == {0}
        assert all(c.distance_mm < 0 for p in hit for c in p.contacts)
        assert ("rod", "instrument_tray") in rep.colliding_pairs()
        assert not rep.ok and "rod-instrument_tray" in rep.summary()
        # the C-arm was added for the check and removed after it
        assert set(ws.obstacles) == {"instrument_tray"}
        # a table through the source housing: the view itself cannot be taken
        ws.add_table(carm.source_robot - np.r_[0.0, 0.0, 60.0])
        rep = check_sweep(ws, carm, poses)
        assert ("carm_source", "table") in {(c.a, c.b) for c in rep.carm_contacts}


@pytest.mark.slow
def test_an_instrument_moved_into_the_field_is_a_stray_blob(clean_sweep):
    carm, sw = clean_sweep
    f = int(np.flatnonzero(sw.plane == 0)[1])
    x, y = np.rint(carm.project(sw.beads_true[f, 4][None])[0]).astype(int)
    frames = sw.frames.copy()
    frames[f:, y + 50:y + 63, x - 6:x + 7] = 3     # appears in frame f, beside the rod's row
    m = find_markers(SweepData(**(sw.for_calibration() | {"frames": frames})))
    clean = find_markers(SweepData(**sw.for_calibration()))
    assert sorted(m.bead[m.frame == f]) == sorted(clean.bead[clean.frame == f])
    assert any(f"frame {f}:" in p and "stray blob" in p for p in m.problems)


@pytest.mark.parametrize("seed", range(4))
def test_compiled_hull_culling_equals_the_numpy_reference(seed):
    """The rays a rod can meet (points within the margin of a convex hull, compiled) against
    the numpy selection, on random point clouds and hulls, a flat hull (a rod seen end-on)
    and a thin slanted one included, with and without the block culling."""
    from testbed.fluoroscope import SweepRenderer

    rng = np.random.default_rng(seed)
    uv = rng.uniform(0, 640, (20000, 2))
    centre = rng.uniform(100, 540, 2)
    pts = centre + rng.normal(0, 1, (40, 2)) @ np.diag(rng.uniform(2, 150, 2))
    flat = centre + np.outer(rng.uniform(-100, 100, 12), [1.0, 0.5])
    # a thin rod across the frame at a slant: its hull's box is mostly outside the hull
    # (blocks there are skipped by the hull's half-planes, not by its box)
    ang = rng.uniform(0.3, 1.2)
    rod = centre + rng.normal(0, 1, (40, 2)) @ np.diag([200.0, 6.0]) @ np.array(
        [[np.cos(ang), np.sin(ang)], [-np.sin(ang), np.cos(ang)]])
    from testbed._fan_numba import block_boxes

    rows = uv[np.lexsort((uv[:, 0], uv[:, 1] // 8))]     # coherent blocks, as rays of a frame
    for p in (pts, flat, rod):
        got = SweepRenderer._inside_hull(uv, p)
        ref = SweepRenderer._inside_hull(uv, p, reference=True)
        np.testing.assert_array_equal(got, ref)
        for pts_uv in (uv, rows):    # the block-culled path: the same indices
            blocks = (*block_boxes(pts_uv, 64), 64)
            np.testing.assert_array_equal(
                SweepRenderer._inside_hull(pts_uv, p, blocks=blocks),
                SweepRenderer._inside_hull(pts_uv, p, reference=True))
    assert len(SweepRenderer._inside_hull(uv, pts)) > 10
    # a many-sided hull (a rod's rounded outline) with points on and about its margin:
    # the block path tests only the half-planes a block's box straddles, and keeps
    # exactly the points the all-half-plane test keeps with the same half-planes
    from testbed._fan_numba import hull_equations, points_in_hull, points_in_hull_blocks

    t = np.linspace(0, 2 * np.pi, 60, endpoint=False)
    oval = centre + np.c_[220 * np.cos(t), 9 * np.sin(t)] @ np.array(
        [[np.cos(ang), np.sin(ang)], [-np.sin(ang), np.cos(ang)]])
    order = np.lexsort((oval[:, 1], oval[:, 0]))
    eq = np.ascontiguousarray(hull_equations(np.ascontiguousarray(oval[order]), 1e-6))
    assert len(eq) > 40
    m = SweepRenderer.HULL_MARGIN_PX
    e = eq[rng.integers(0, len(eq), 4000)]       # points at the margin of random edges
    along = rng.uniform(-300, 300, (4000, 1)) * np.c_[-e[:, 1], e[:, 0]]
    foot = (m - e[:, 2] + rng.choice([-1e-9, 0.0, 1e-9], 4000))[:, None] * e[:, :2]
    near = np.vstack([centre + rng.normal(0, 1, (8000, 2)) @ np.diag([150.0, 20.0]),
                      foot + along])
    near = near[np.lexsort((near[:, 0], near[:, 1] // 4))]
    lo, hi = oval.min(axis=0) - m, oval.max(axis=0) + m
    for block in (16, 64):
        got = points_in_hull_blocks(near, *block_boxes(near, block), block, lo, hi, eq, m)
        ref = points_in_hull(near, lo, hi, eq, m)
        np.testing.assert_array_equal(got, ref)
        assert 100 < len(ref) < len(near)


def test_compiled_hull_equations_equal_scipys_convex_hull():
    """The monotone chain's half-planes against scipy's ConvexHull on random clouds (many
    points inside, collinear points on an edge, a few points), and none for a flat cloud."""
    from scipy.spatial import ConvexHull

    from testbed._fan_numba import hull_equations

    rng = np.random.default_rng(21)
    for trial in range(30):
        k = int(rng.integers(3, 300))
        pts = rng.normal(0, 1, (k, 2)) @ rng.normal(0, 50, (2, 2)) + rng.uniform(0, 640, 2)
        if trial % 3 == 0:     # a square's corners and points on its edges
            t = rng.uniform(0, 1, (k, 1))
            pts = np.vstack([[[0.0, 0], [10, 0], [10, 10], [0, 10]], t * [[10.0, 0]],
                             [0.0, 10] + t * [[10.0, 0]]]) + 100.0
        order = np.lexsort((pts[:, 1], pts[:, 0]))
        got = hull_equations(np.ascontiguousarray(pts[order]), 1e-6)
        ref = ConvexHull(pts).equations
        assert len(got) == len(ref), trial
        key = lambda e: np.round(e, 9).tolist()   # noqa: E731
        np.testing.assert_allclose(sorted(got, key=key), sorted(ref, key=key),
                                   rtol=0, atol=1e-9)
    line = 50.0 + np.outer(rng.uniform(-100, 100, 12), [1.0, 0.5])
    order = np.lexsort((line[:, 1], line[:, 0]))
    assert hull_equations(np.ascontiguousarray(line[order]), 1e-6).shape == (0, 3)


def test_compiled_rod_hull_equals_its_numpy_twin():
    """The sweep renderer's rod set-up in one compiled call (the source's check filtered,
    the projection, the hull's bounds and half-planes) against the numpy steps it replaces
    (_check_source_outside, _hull_px, the lexsort and hull_equations), bit for bit: random
    poses of a rod-like cloud with repeated points, and a source inside a body's bounds (the
    exact check then runs: inside the mesh it raises) or behind the points (raises)."""
    import trimesh

    from testbed._fan_numba import hull_equations, projected_hull, source_near_bodies
    from testbed.bodies import Body
    from testbed.fluoroscope import SweepRenderer, _check_source_outside

    fl = FluoroscopeSpec(distortion=False, noise=False).ideal()
    carm = make_carm(fl, VIEW)
    sr = SweepRenderer(carm, fl, [])
    src = carm.source_robot
    rng = np.random.default_rng(5)
    for _ in range(40):
        centre = src + carm.axis_robot * rng.uniform(300, 900) + rng.normal(0, 40, 3)
        cyl = trimesh.creation.cylinder(radius=rng.uniform(1, 6), height=rng.uniform(20, 200),
                                        sections=int(rng.integers(6, 40)))
        cyl.apply_transform(trimesh.transformations.random_rotation_matrix(rng.random(3)))
        cyl.apply_translation(centre)
        tip = cyl.copy()
        tip.vertices[: len(tip.vertices) // 2] = tip.vertices[0]     # repeated points
        beads = rng.normal(0, 20, (int(rng.integers(1, 9)), 3)) + centre
        rod = [Body(name="rod", material="ultem", mesh=cyl),
               Body(name="beads", material="steel", sphere_centers=beads,
                    sphere_radii=np.full(len(beads), rng.uniform(0.5, 2.0))),
               Body(name="tip", material="steel", mesh=tip)]
        pts, lo, hi, eq = sr._rod_hull(rod)
        ref = sr._hull_px(rod)
        np.testing.assert_array_equal(pts, ref)
        m = SweepRenderer.HULL_MARGIN_PX
        np.testing.assert_array_equal(lo, ref.min(axis=0) - m)
        np.testing.assert_array_equal(hi, ref.max(axis=0) + m)
        order = np.lexsort((ref[:, 1], ref[:, 0]))
        np.testing.assert_array_equal(
            eq, hull_equations(np.ascontiguousarray(ref[order]), SweepRenderer.FLAT_HULL_PX2))
        p3, seg, c, r = sr._rod_points(rod)
        assert not source_near_bodies(p3, seg, c, r, src)
        # the filter flags a source within a mesh's bounds or near a bead: never a miss
        for probe in (cyl.vertices.mean(axis=0), beads[0] + 0.999 * r[0] * np.eye(3)[0],
                      beads[0] + 1.001 * r[0] * np.eye(3)[1]):
            inside = False
            try:
                _check_source_outside(type(carm)(carm2robot=_at(carm, probe), sid_mm=1000.0,
                                                 width_px=8, height_px=8), rod)
            except ValueError:
                inside = True
            assert source_near_bodies(p3, seg, c, r, probe) or not inside
    ok = projected_hull(np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]), 0.0, 0.0, 1.0, 1.0,
                        0.5, 1e-6)[0]
    assert not ok


def _at(carm, point):
    """The pose ``carm.carm2robot`` moved to put its source at ``point``."""
    from reglib.geometry import RigidTransform

    return RigidTransform(carm.carm2robot.R, np.asarray(point, dtype=np.float64))


@pytest.mark.slow
@pytest.mark.parametrize("oversample", [1, 2])
def test_sweep_renderer_gives_the_frames_of_a_full_render(oversample):
    """The fast sweep path (static bodies cast once, per frame only the rays in the rod's
    projected hull) against render() with every body, the patient and table in the beam
    and the clinic's distortion: transmission equal to float32 rounding, the noise-free
    video equal, and with noise the same draws (video equal but for rounding ties)."""
    from testbed.detector import form_image
    from testbed.fluoroscope import SweepRenderer, render
    from testbed.scene import find_scene, load_scene
    from testbed.world import build_world

    scene = load_scene(find_scene("experiment2"))
    fl = scene.fluoroscope.model_copy(update={"oversample": oversample})
    bodies = build_world(scene, np.random.default_rng(0)).bodies
    carm = make_carm(fl, scene.views[0], view_index=0, stage="calibration")
    fast = SweepRenderer(carm, fl, bodies)
    rng = np.random.default_rng(5)
    with Robot(scene.robot, rng=0) as robot:
        plan = plan_sweep(carm, robot.spec)
        picks = [0, *rng.choice(np.arange(1, len(plan)), 3, replace=False)]
        for i in picks:   # the parked reference pose and three rows
            robot.place_rod(plan[i].point_robot, plan[i].direction_robot)
            rod = robot.rod_bodies()
            ref = render(carm, bodies + rod, fluoro=fl, rng=0, noise=False)
            t_fast = fast.transmission(rod)
            if oversample == 1:
                t_ref = np.where(ref.fov, np.exp(-ref.attenuation.astype(np.float64)), 0.0)
                assert np.abs(t_fast - t_ref).max() < 1e-6, i
            assert np.array_equal(fast.render(rod, rng=0, noise=False), ref.image_u8), i
            noisy = render(carm, bodies + rod, fluoro=fl, rng=7, noise=True).image_u8
            got = fast.render(rod, rng=7, noise=True)
            # the sources redone only near the rod: the frame of the whole chain, exactly
            whole = form_image(t_fast, carm.fov_mask(), carm._field()[2], fl,
                               magnification=fast._magnification, noise=True, rng=7)[1]
            assert np.array_equal(got, whole), i
            diff = np.abs(got.astype(int) - noisy.astype(int))
            assert diff.max() <= 1 and np.mean(diff > 0) < 1e-3, i
            if plan[i].plane >= 0:   # the rod is in the field: its rays were cast
                rod_px = ref.mask({"ultem", "steel"})
                assert rod_px.sum() > 500


def test_one_validation_bead_reported_off_fails_the_view(clean_sweep):
    """A validation bead the robot reports 1.5 mm across the beam from where it was: the
    view fails on its largest distance, however small the others (a mutation audit: a
    test of the median distance passed every test)."""
    from reglib.pipeline import calibrate_view

    carm, sw = clean_sweep
    arrays = {"plane": sw.plane, "beads_reported": sw.beads_reported.copy(),
              "bead_positions_mm": sw.bead_positions_mm}
    good = calibrate_view("v", sw.frames, arrays)
    across = np.cross(carm.axis_robot, [1.0, 0.0, 0.0])
    f = int(np.flatnonzero(sw.plane == 2)[0])
    arrays["beads_reported"][f, 3] += 1.5 * across / np.linalg.norm(across)
    bad = calibrate_view("v", sw.frames, arrays)
    assert good.ok and good.validation_mm.max() < 0.1
    assert not bad.ok and "largest distance" in bad.message, bad.message
    assert np.median(bad.validation_mm) < 0.1 < bad.validation_mm.max()
    # the bead lies amid both planes' markers: the cause is named as the sweep's geometry,
    # not the rows lacking beads (a review: a robot's error was blamed on them)
    assert "the 1 marker(s) beyond it lie where both calibration planes have markers" \
        in bad.message and "the rod poses the robot reports" in bad.message, bad.message


def test_a_validation_row_that_fits_two_labellings_is_identified_by_the_paths(clean_sweep):
    """Beads 0, 2, 4 and 7 of the validation row hidden (the previous frame pasted over
    them): the four left, beads 1, 3, 5 and 6, fit two labellings of the rod, so the row
    cannot be identified alone; the calibration's X-ray paths identify them, and the view is
    validated on those four beads with the distances the whole row gave them (a mutation
    audit, h99: with the paths' identification never called, every test passed; the view
    then fails as not validated)."""
    from reglib.pipeline import calibrate_view

    carm, sw = clean_sweep
    arrays = {"plane": sw.plane, "beads_reported": sw.beads_reported,
              "bead_positions_mm": sw.bead_positions_mm}
    whole = calibrate_view("v", sw.frames, arrays)
    f = int(np.flatnonzero(sw.plane == 2)[0])
    frames = sw.frames.copy()
    for b in (0, 2, 4, 7):
        x, y = np.rint(carm.project(sw.beads_true[f, b][None])[0]).astype(int)
        frames[f, y - 6:y + 7, x - 6:x + 7] = frames[f - 1, y - 6:y + 7, x - 6:x + 7]
    cal = calibrate_view("v", frames, arrays)
    assert whole.ok and len(whole.validation_mm) == 8
    assert cal.ok, cal.message
    assert np.allclose(np.sort(cal.validation_mm), np.sort(whole.validation_mm[[1, 3, 5, 6]]),
                       atol=1e-6)
    notes = [p for p in cal.problems if "validation plane" in p]
    assert any("ambiguous" in p for p in notes), notes
    assert any("4 of 4 blob(s) identify beads by the calibration's X-ray paths" in p
               for p in notes), notes


def test_a_validation_failure_beyond_the_calibrated_region_names_the_missing_beads():
    """The markers beyond the limit lie where one plane's markers do not reach: the spline
    extrapolates there, and the rows lacking beads are named as the cause."""
    from types import SimpleNamespace

    from reglib.markers import FAR, NEAR
    from reglib.pipeline import _validation_cause

    g = np.stack(np.meshgrid(np.linspace(100, 500, 9), np.linspace(100, 380, 7)), -1)
    grid = g.reshape(-1, 2)
    planes = {NEAR: grid, FAR: grid[grid[:, 0] < 400]}   # the far plane misses x >= 400

    def select(plane):
        return planes[plane], np.zeros((len(planes[plane]), 3))

    markers = SimpleNamespace(select=select)
    xy = np.array([[300.0, 200.0], [450.0, 200.0], [200.0, 300.0]])
    lacking = ("view v, far plane, frame 3: beads [6, 7] not found (outside the field)",)
    out = _validation_cause(markers, xy, np.array([0.2, 1.4, 1.2]), 1.0, lacking)
    assert out.startswith("1 of the 2 marker(s) beyond it lie where the calibration planes' "
                          "markers do not reach"), out
    assert "1 sweep row(s) lack beads" in out and "keep the rod's beads inside" in out, out
    inside = _validation_cause(markers, xy, np.array([0.2, 0.4, 1.2]), 1.0, lacking)
    assert inside.startswith("the 1 marker(s) beyond it lie where both calibration planes "
                             "have markers"), inside
    # a plane with too few markers to cover anything: nothing is inside
    planes[FAR] = grid[:2]
    assert "do not reach" in _validation_cause(markers, xy, np.array([0.2, 0.4, 1.2]), 1.0, ())
