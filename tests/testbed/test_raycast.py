"""Per-body path lengths: embree fast path vs the numpy reference, and analytic chords."""

import numpy as np
import pytest
import trimesh

from testbed.bodies import Body
from testbed.raycast import (
    RayScene,
    attenuation_weights,
    body_path_lengths,
    mesh_chords,
    ray_box_hits,
    sphere_chords,
)


def _rays_towards(rng, n, target_box, distance=400.0):
    """Rays from a sphere of radius ``distance`` towards random points of a box (mm)."""
    o = rng.normal(size=(n, 3))
    o *= distance / np.linalg.norm(o, axis=1, keepdims=True)
    tgt = rng.uniform(-target_box, target_box, (n, 3))
    d = tgt - o
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def _meshes(rng):
    blob = trimesh.convex.convex_hull(rng.normal(scale=30.0, size=(60, 3)))
    torus = trimesh.creation.torus(major_radius=40.0, minor_radius=12.0,
                                   major_sections=24, minor_sections=10)
    box = trimesh.creation.box(extents=(50.0, 30.0, 70.0))
    return {"convex blob": blob, "torus": torus, "box": box}


@pytest.mark.parametrize("name", ["convex blob", "torus", "box"])
def test_embree_matches_numpy_reference_on_random_rays(name):
    rng = np.random.default_rng(11)
    mesh = _meshes(rng)[name]
    assert mesh.is_watertight
    o, d = _rays_towards(rng, 400, 60.0)
    t_max = rng.uniform(300.0, 700.0, len(o))  # some segments end inside the mesh
    fast = mesh_chords(mesh, o, d, t_max, engine="embree")
    via_trimesh = mesh_chords(mesh, o, d, t_max, engine="trimesh")
    ref = mesh_chords(mesh, o, d, t_max, engine="numpy")
    assert (ref > 0).sum() > 100
    assert np.abs(fast - ref).max() < 1e-3
    assert np.abs(via_trimesh - ref).max() < 1e-3


def test_rays_through_edges_and_vertices_are_counted_once():
    """Axis-aligned rays through a box's edges and vertices, and a cube grid."""
    box = trimesh.creation.box(extents=(40.0, 40.0, 40.0))  # faces split along diagonals
    s = np.linspace(-19.0, 19.0, 39)  # includes 0, on the faces' diagonals
    x, y = np.meshgrid(s, s)
    o = np.c_[x.ravel(), y.ravel(), np.full(x.size, -100.0)]
    d = np.tile([0.0, 0.0, 1.0], (len(o), 1))
    for engine in ("embree", "trimesh", "numpy"):
        assert np.allclose(mesh_chords(box, o, d, 500.0, engine=engine), 40.0, atol=1e-3)
    # diagonal rays through opposite vertices
    v = np.array([[-20.0, -20.0, -20.0]])
    dv = np.ones((1, 3)) / np.sqrt(3.0)
    for engine in ("embree", "trimesh", "numpy"):
        got = mesh_chords(box, v - 100 * dv, dv, 500.0, engine=engine)
        assert got[0] == pytest.approx(40.0 * np.sqrt(3.0), abs=1e-3)


def test_cylinder_chords_match_the_analytic_chord():
    """A 256-gon prism lies between the inscribed and the circumscribed circle."""
    R, n = 20.0, 256
    cyl = trimesh.creation.cylinder(radius=R, height=200.0, sections=n)  # axis along z
    rng = np.random.default_rng(3)
    s = rng.uniform(-0.95 * R, 0.95 * R, 500)  # offset of the ray from the axis
    z = rng.uniform(-90.0, 90.0, 500)
    phi = rng.uniform(0, 2 * np.pi, 500)  # direction in the xy plane
    d = np.c_[np.cos(phi), np.sin(phi), np.zeros(500)]
    perp = np.c_[-np.sin(phi), np.cos(phi), np.zeros(500)]
    o = perp * s[:, None] - 300.0 * d + np.c_[np.zeros((500, 2)), z]
    got = mesh_chords(cyl, o, d, 1000.0)
    outer = 2 * np.sqrt(R**2 - s**2)
    r_in = R * np.cos(np.pi / n)
    inner = 2 * np.sqrt(r_in**2 - s**2)
    tol = 2e-4  # Embree works in float32
    assert np.all(got <= outer + tol) and np.all(got >= inner - tol)
    assert np.abs(got - outer).max() < 0.05
    # an oblique ray through the axis: the chord of an ellipse, 2R / sin(angle)
    a = np.radians(50.0)
    d1 = np.array([[np.sin(a), 0.0, np.cos(a)]])
    got = mesh_chords(cyl, -300.0 * d1, d1, 1000.0)[0]
    assert got == pytest.approx(2 * R / np.sin(a), rel=1e-4)


def test_sphere_chords_analytic_and_clipped():
    rng = np.random.default_rng(8)
    c = np.array([[10.0, -5.0, 300.0]])
    r = 7.0
    o = np.zeros((2000, 3))
    tgt = c + rng.uniform(-9.0, 9.0, (2000, 3))
    d = tgt / np.linalg.norm(tgt, axis=1, keepdims=True)
    got = sphere_chords(c, [r], o, d, 1000.0)[:, 0]
    dist = np.linalg.norm(np.cross(d, c), axis=1)  # distance from centre to the line
    want = np.where(dist < r, 2 * np.sqrt(np.clip(r**2 - dist**2, 0, None)), 0.0)
    assert np.abs(got - want).max() < 1e-9
    assert (want > 0).sum() > 500
    # the same sphere as a fine mesh agrees to the mesh's facet error
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=r)
    mesh.apply_translation(c[0])
    inner = dist < 0.9 * r
    assert np.abs(mesh_chords(mesh, o, d, 1000.0)[inner] - want[inner]).max() < 0.02
    # a segment ending at the centre holds half the chord through the centre
    half = sphere_chords(c, [r], [[0.0, 0.0, 0.0]], c / np.linalg.norm(c),
                         np.linalg.norm(c))
    assert half[0, 0] == pytest.approx(r)


def test_box_culling_is_exact():
    rng = np.random.default_rng(2)
    o, d = _rays_towards(rng, 3000, 45.0)
    t_max = rng.uniform(360.0, 440.0, len(o))  # some segments stop short of the box
    lo, hi = np.array([-30.0, -20.0, -10.0]), np.array([30.0, 20.0, 10.0])
    hit = ray_box_hits(o, d, t_max, lo, hi)
    # reference: the box as a mesh, cast with the numpy reference
    box = trimesh.creation.box(bounds=np.stack([lo, hi]))
    meets = mesh_chords(box, o, d, t_max, engine="numpy") > 1e-9
    assert meets.sum() > 300 and (~meets).sum() > 300
    assert np.all(hit[meets])  # never culls a segment that meets the box
    assert (hit & ~meets).sum() <= 3  # only segments grazing the box


def test_nesting_and_source_inside():
    outer = trimesh.creation.icosphere(subdivisions=3, radius=50.0)
    inner = trimesh.creation.icosphere(subdivisions=3, radius=20.0)
    bodies = [Body("tissue", "soft_tissue", mesh=outer),
              Body("bone", "cortical_bone", mesh=inner, inside="tissue")]
    w = attenuation_weights(bodies)
    assert w == pytest.approx([0.0206, 0.0600 - 0.0206])
    o = np.array([[0.0, 0.0, -200.0]])
    d = np.array([[0.0, 0.0, 1.0]])
    L = body_path_lengths(bodies, o, d, 400.0)
    # a ray through the centre: 60 mm of tissue then 40 mm of bone then 60 mm of tissue
    assert float(L[0] @ w) == pytest.approx(0.0206 * 60 + 0.06 * 40, rel=2e-3)
    with pytest.raises(ValueError, match="'tissue'.*inside the mesh"):
        mesh_chords(outer, [[0.0, 0.0, 0.0]], d, 400.0, name="tissue")
    with pytest.raises(ValueError, match="unique"):
        attenuation_weights([bodies[0], bodies[0]])
    # bodies weighed inside others that are not (a sweep's rod in its static world): the
    # same weights and refusals as the whole list's
    rod = [Body("rod", "soft_tissue", mesh=inner, inside="tissue"),
           Body("bead", "cortical_bone", mesh=inner, inside="rod")]
    whole = attenuation_weights(bodies + rod)[len(bodies):]
    part = attenuation_weights(rod, enclosing={b.name: b for b in bodies})
    assert np.array_equal(part, whole)
    for bad in ([Body("bone", "steel", mesh=inner)], [rod[0], rod[0]],
                [Body("bead", "steel", mesh=inner, inside="nowhere")]):
        with pytest.raises(ValueError) as want:
            attenuation_weights(bodies + bad)
        with pytest.raises(ValueError) as got:
            attenuation_weights(bad, enclosing={b.name: b for b in bodies})
        assert str(got.value) == str(want.value)


def test_ray_scene_matches_reference_with_shared_surfaces():
    """A world whose meshes share a surface (a marrow core inside a bone shell that is the
    difference of two cylinders): the prepared scene agrees with the numpy reference."""
    outer = trimesh.creation.cylinder(radius=20.0, height=120.0, sections=48)
    core = trimesh.creation.cylinder(radius=9.0, height=80.0, sections=48)
    shell = trimesh.boolean.difference([outer, core], engine="manifold")
    tissue = trimesh.creation.icosphere(subdivisions=3, radius=90.0)
    bodies = [Body("tissue", "soft_tissue", mesh=tissue),
              Body("shell", "cortical_bone", mesh=shell, inside="tissue"),
              Body("core", "marrow", mesh=core, inside="tissue"),
              Body("beads", "steel", sphere_centers=[[0.0, 0.0, 70.0], [5.0, 5.0, -70.0]],
                   sphere_radii=3.0)]
    rng = np.random.default_rng(6)
    o, d = _rays_towards(rng, 600, 30.0, distance=300.0)
    scene = RayScene(bodies)
    fast = scene.path_lengths(o, d, 500.0)
    ref = body_path_lengths(bodies, o, d, 500.0, engine="numpy")
    assert (ref[:, 2] > 0).sum() > 50 and (ref[:, 3] > 0).sum() > 0
    assert np.abs(fast - ref).max() < 1e-3
    assert np.allclose(body_path_lengths(bodies, o, d, 500.0), fast)


@pytest.mark.parametrize("seed", range(3))
def test_convex_clipping_in_a_ray_scene_matches_the_numpy_reference(seed):
    """Small convex meshes (a box like the table, a random hull of few faces, a turned
    box) are clipped by their half-spaces instead of cast: against trimesh's brute-force
    ray-triangle reference on random rays, some ending inside, some missing, and rays
    parallel to a box's faces."""
    from testbed.raycast import CONVEX_CLIP_MAX_FACES, _ConvexMesh

    rng = np.random.default_rng(seed)
    box = trimesh.creation.box(extents=rng.uniform(20.0, 90.0, 3))
    turned = trimesh.creation.box(extents=rng.uniform(20.0, 60.0, 3))
    turned.apply_transform(trimesh.transformations.random_rotation_matrix(rng.random(3)))
    turned.apply_translation(rng.normal(0.0, 10.0, 3))
    hull = trimesh.convex.convex_hull(rng.normal(scale=25.0, size=(12, 3)))
    assert len(hull.faces) <= CONVEX_CLIP_MAX_FACES
    bodies = [Body("box", "soft_tissue", mesh=box), Body("turned", "steel", mesh=turned),
              Body("hull", "cortical_bone", mesh=hull)]
    scene = RayScene(bodies)
    assert all(isinstance(scene._convex[j], _ConvexMesh) for j in range(3))
    o, d = _rays_towards(rng, 800, 60.0)
    axis = np.zeros((50, 3))
    axis[:, 0] = 1.0                                   # parallel to two faces of the box
    o = np.vstack([o, np.column_stack([np.full(50, -300.0), rng.uniform(-50, 50, (50, 2))])])
    d = np.vstack([d, axis])
    t_max = rng.uniform(300.0, 700.0, len(o))
    fast = scene.path_lengths(o, d, t_max)
    ref = body_path_lengths(bodies, o, d, t_max, engine="numpy")
    assert np.all((ref > 0).sum(axis=0) > 100)
    assert np.abs(fast - ref).max() < 1e-6


# --------------------------------------------------------------------------- fan rasterisation
def _fan(rng, n, source, target, half_width):
    """Unit directions (n, 3) from ``source`` to random points of a box around ``target``."""
    tgt = target + rng.uniform(-half_width, half_width, (n, 3))
    d = tgt - source
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _bumpy_sphere(rng, radius=35.0):
    """A star-shaped, non-convex closed mesh (a sphere with random radial bumps)."""
    m = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    r = radius * (1.0 + 0.25 * rng.uniform(-1, 1, len(m.vertices)))
    return trimesh.Trimesh(m.vertices * r[:, None], m.faces, process=False)


@pytest.mark.parametrize("seed", range(4))
def test_fan_rasterisation_matches_the_numpy_reference(seed):
    """Rays from one point (an X-ray frame) through concave, nested and convex meshes, some
    rays ending inside a mesh, some aimed exactly at vertices and edge midpoints (where two
    or more triangles meet): the rasterised chords against trimesh's brute-force ray-triangle
    test, body by body."""
    from testbed.raycast import FanRays

    rng = np.random.default_rng(seed)
    torus = trimesh.creation.torus(major_radius=40.0, minor_radius=12.0,
                                   major_sections=24, minor_sections=10)
    torus.apply_transform(trimesh.transformations.random_rotation_matrix(rng.random(3)))
    n_random = 3000
    bumpy = _bumpy_sphere(rng)
    bumpy.apply_translation(rng.normal(0.0, 15.0, 3))
    cyl = trimesh.creation.cylinder(radius=3.0, height=80.0, sections=32)  # a pin: 128 faces
    cyl.apply_transform(trimesh.transformations.random_rotation_matrix(rng.random(3)))
    bodies = [Body("torus", "soft_tissue", mesh=torus),
              Body("bumpy", "cortical_bone", mesh=bumpy),
              Body("pin", "steel", mesh=cyl)]
    source = rng.normal(size=3)
    source *= 600.0 / np.linalg.norm(source)
    d = _fan(rng, n_random, source, np.zeros(3), 60.0)
    # rays exactly through vertices and through edge midpoints of each mesh
    for m in (torus, bumpy, cyl):
        pick = rng.choice(len(m.vertices), 60, replace=False)
        e = m.edges_unique[rng.choice(len(m.edges_unique), 60, replace=False)]
        for p in (m.vertices[pick], m.vertices[e].mean(axis=1)):
            q = p - source
            d = np.vstack([d, q / np.linalg.norm(q, axis=1, keepdims=True)])
    o = np.broadcast_to(source, d.shape).copy()
    t_max = rng.uniform(560.0, 700.0, len(d))            # some end inside a mesh
    scene = RayScene(bodies)
    fan = FanRays.of(source, d, t_max)
    assert fan is not None and all(fan.can_rasterise(b.mesh) for b in bodies)
    fast = scene.fan_path_lengths(fan)
    assert np.array_equal(scene.path_lengths(o, d, t_max), fast)  # detected as a fan
    ref = body_path_lengths(bodies, o, d, t_max, engine="numpy")
    assert np.all((ref > 0).sum(axis=0) > 100)
    assert np.abs(fast[:n_random] - ref[:n_random]).max() < 1e-7
    # through a vertex or an edge the chord may jump (a ray grazing the silhouette), and
    # either side is right: the rasterised value must be that of a ray moved a hair's
    # breadth in some direction (between the chords of four parallel neighbours)
    ties = np.arange(n_random, len(d))
    near = []
    for u in (fan.e1, -fan.e1, fan.e2, -fan.e2):
        near.append(body_path_lengths(bodies, o[ties] + 1e-6 * u, d[ties], t_max[ties],
                                      engine="numpy"))
    near = np.stack(near)
    # (1e-5 mm: the neighbours' own spread at grazing incidence; a crossing missed or
    # counted twice is millimetres)
    assert np.all(fast[ties] >= near.min(axis=0) - 1e-5)
    assert np.all(fast[ties] <= near.max(axis=0) + 1e-5)


@pytest.mark.parametrize("seed", range(3))
def test_fan_chords_do_not_depend_on_the_cells_shape(seed):
    """The binning's cells (square, or elongated either way, or shaped like the rays'
    extent: elongation="auto", as the sweep casts the rod) change only the work: on a long
    thin pin seen lengthwise, a torus and beads, from a strip of rays, and the rays aimed
    at vertices and edge midpoints, every chord equals the square cells' bit for bit (and
    the reference to rounding)."""
    from testbed.raycast import FanRays

    rng = np.random.default_rng(seed)
    pin = trimesh.creation.cylinder(radius=2.0, height=120.0, sections=48)
    pin.apply_transform(trimesh.transformations.rotation_matrix(   # across the beam
        np.pi / 2 + rng.uniform(-0.3, 0.3), [1, 0, 0]))
    torus = trimesh.creation.torus(major_radius=30.0, minor_radius=8.0,
                                   major_sections=16, minor_sections=8)
    torus.apply_transform(trimesh.transformations.random_rotation_matrix(rng.random(3)))
    bodies = [Body("pin", "steel", mesh=pin), Body("torus", "soft_tissue", mesh=torus),
              Body("beads", "steel", sphere_centers=rng.uniform(-20, 20, (6, 3)),
                   sphere_radii=rng.uniform(1.0, 3.0, 6))]
    source = np.array([0.0, 0.0, -600.0])
    d = _fan(rng, 6000, source, np.zeros(3), 40.0)
    d = d[np.abs(d[:, 0] / d[:, 2]) < 0.01 + 0.02 * rng.uniform()]    # a strip along y
    for p in (pin.vertices[rng.choice(len(pin.vertices), 40, replace=False)],
              pin.vertices[pin.edges_unique[:40]].mean(axis=1)):
        q = p - source
        d = np.vstack([d, q / np.linalg.norm(q, axis=1, keepdims=True)])
    tm = rng.uniform(560.0, 700.0, len(d))
    square = FanRays.of(source, d, tm)
    scene = RayScene(bodies)
    ref = scene.fan_path_lengths(square)
    assert (ref[:, 0] > 0).sum() > 50
    for kw in (dict(elongation="auto"), dict(elongation=16.0, rays_per_cell=4.0),
               dict(elongation=1 / 16)):
        fan = FanRays(source, square.directions, square.t_max, square.axis, square.e1,
                      square.e2, **kw)
        if kw["elongation"] == "auto":
            hx, hy = fan.grid[2:4]
            assert max(hx, hy) > 2 * min(hx, hy)
        assert np.array_equal(scene.fan_path_lengths(fan), ref)
    exact = body_path_lengths(bodies, np.broadcast_to(source, d.shape).copy(), d, tm,
                              engine="numpy")
    assert np.abs(ref[:-80] - exact[:-80]).max() < 1e-6


@pytest.mark.parametrize("seed", range(3))
def test_compiled_fan_binning_equals_its_numpy_twin(seed):
    """FanRays' image-plane coordinates, grid, bins and sorted arrays compiled
    (plane_coords, binned_fan) against its numpy expressions (``reference=True``), bit for
    bit, on random fans of various sizes and shapes; and the compiled gather of rays
    (gather_rays) against numpy's fancy indexing."""
    from testbed._fan_numba import gather_rays, plane_coords
    from testbed.raycast import FanRays

    rng = np.random.default_rng(seed)
    source = rng.normal(0, 100, 3)
    for n in (64, 65, 333, 5000):
        d = _fan(rng, n, source, source + rng.normal(0, 1, 3) * 600, rng.uniform(1, 40))
        tm = rng.uniform(100, 900, len(d))
        base = FanRays.of(source, d, tm)
        idx = np.sort(rng.choice(len(d), int(rng.integers(1, len(d))), replace=False))
        a = rng.normal(size=len(d))
        dd, tt, aa = gather_rays(d, tm, a, idx)
        for got, ref in ((dd, d[idx]), (tt, tm[idx]), (aa, a[idx])):
            assert np.array_equal(got, ref) and got.flags.c_contiguous
        for kw in (dict(elongation="auto"), dict(elongation=4.0, rays_per_cell=3.0), {}):
            args = (source, d, tm, base.axis, base.e1, base.e2)
            fast, ref = FanRays(*args, **kw), FanRays(*args, reference=True, **kw)
            assert fast.grid == ref.grid
            for k in ("start", "order", "rays"):
                assert np.array_equal(getattr(fast, k), getattr(ref, k)), k
    x, y, x0, y0, x1, y1 = plane_coords(np.array([1.0, 1.0]), np.array([np.nan, 2.0]),
                                        np.array([1.0, 3.0]))
    assert np.isnan(x0) and np.isnan(x1) and (y0, y1) == (1.0, 3.0)


def test_compiled_sphere_image_boxes_equal_their_numpy_twin():
    """FanRays.sphere_chords with the spheres' image boxes compiled (sphere_image_boxes)
    against its numpy expressions (``reference=True``), bit for bit: beads in front of the
    source, straddling it and behind it; and the boxes themselves with a NaN corner."""
    from testbed._fan_numba import sphere_image_boxes
    from testbed.raycast import FanRays

    rng = np.random.default_rng(3)
    source = np.array([0.0, 0.0, -600.0])
    d = _fan(rng, 4000, source, np.zeros(3), 40.0)
    fan = FanRays.of(source, d, rng.uniform(500.0, 800.0, len(d)))
    for _ in range(10):
        c = np.vstack([rng.uniform(-30, 30, (6, 3)),
                       source + rng.normal(0, 3, (2, 3)),        # about the source
                       source - [0, 0, 50] + rng.normal(0, 5, (2, 3))])  # behind it
        r = rng.uniform(0.5, 4.0, len(c))
        assert np.array_equal(fan.sphere_chords(c, r), fan.sphere_chords(c, r, reference=True))
    z = rng.normal(1, 1, (5, 8))
    u, v = rng.normal(size=(5, 8)), rng.normal(size=(5, 8))
    u[2, 3] = np.nan
    ok, lo, hi = sphere_image_boxes(z, u, v)
    zs = np.where(z > 1e-9, z, 1.0)
    np.testing.assert_array_equal(ok, np.all(z > 1e-9, axis=1))
    np.testing.assert_array_equal(lo, np.stack([(u / zs).min(1), (v / zs).min(1)], 1))
    np.testing.assert_array_equal(hi, np.stack([(u / zs).max(1), (v / zs).max(1)], 1))


def test_fan_rasterisation_of_an_axis_aligned_grid_through_a_box():
    """Rays from one point through a regular grid that passes exactly through a box's
    vertices, edges and face diagonals (every tie of the edge tests): each crossing is
    counted once, no cracks along shared edges."""
    from testbed.raycast import FanRays

    box = trimesh.creation.box(extents=(40.0, 40.0, 40.0))
    source = np.array([0.0, 0.0, -500.0])
    s = np.linspace(-20.0, 20.0, 41)
    x, y = np.meshgrid(s, s)
    target = np.c_[x.ravel(), y.ravel(), np.full(x.size, -20.0)]   # the near face's grid
    d = target - source
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    fan = FanRays.of(source, d, np.full(len(d), 1000.0))
    fast = fan.chords(box)
    ref = mesh_chords(box, np.broadcast_to(source, d.shape).copy(), d, 1000.0,
                      engine="numpy")
    inner = (np.abs(x.ravel()) < 20) & (np.abs(y.ravel()) < 20)
    assert np.abs(fast[inner] - ref[inner]).max() < 1e-9
    # analytic: enter at z = -20, leave through the far face or a side face
    m = np.maximum(np.abs(x.ravel()), np.abs(y.ravel()))
    z_exit = np.minimum(20.0, np.divide(480.0 * 20.0, m, out=np.full(m.shape, 1e9),
                                        where=m > 0) - 500.0)
    exact = (z_exit + 20.0) / d[:, 2]
    assert np.abs(fast[inner] - exact[inner]).max() < 1e-9
    # the outermost rays graze the box's edges (diverging from the source): length 0 here,
    # a hair's breadth of length in the reference (its parallel shifted rays)
    assert np.all(fast[~inner] < 1e-2) and np.all(ref[~inner] < 1e-2)


def test_fan_falls_back_to_casting_where_it_cannot_rasterise():
    """A mesh reaching behind the source is cast with Embree, and a fan wider than an image
    plane can hold is not binned; both still match the reference."""
    from testbed.raycast import FanRays

    rng = np.random.default_rng(5)
    near = trimesh.creation.box(extents=(30.0, 30.0, 30.0))
    near.apply_translation([0.0, 0.0, 5.0])                  # around the source at z = 0
    far = _bumpy_sphere(rng, 20.0)
    far.apply_translation([0.0, 0.0, 300.0])
    # the box contains the source, so only rays' far parts count: use a shell instead
    shell = trimesh.creation.annulus(r_min=40.0, r_max=60.0, height=30.0)
    bodies = [Body("far", "cortical_bone", mesh=far), Body("shell", "soft_tissue", mesh=shell)]
    source = np.zeros(3)
    theta = np.radians(rng.uniform(60.0, 75.0, 400))          # some through the shell
    phi = rng.uniform(0.0, 2 * np.pi, 400)
    wide_cone = np.c_[np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)]
    d = np.vstack([_fan(rng, 400, source, np.array([0.0, 0.0, 300.0]), 40.0), wide_cone])
    fan = FanRays.of(source, d, np.full(len(d), 500.0))
    assert fan.can_rasterise(far) and not fan.can_rasterise(shell)
    assert not fan.can_rasterise(near)
    scene = RayScene(bodies)
    ref = body_path_lengths(bodies, np.zeros_like(d), d, 500.0, engine="numpy")
    assert np.all((ref > 0).sum(axis=0) > 20)
    assert np.abs(scene.fan_path_lengths(fan) - ref).max() < 1e-3   # the shell by Embree
    wide = rng.normal(size=(400, 3))
    wide /= np.linalg.norm(wide, axis=1, keepdims=True)      # all directions
    assert FanRays.of(source, wide, np.full(400, 500.0)) is None
    ref = body_path_lengths(bodies, np.zeros_like(wide), wide, 500.0, engine="numpy")
    got = scene.path_lengths(np.zeros_like(wide), wide, 500.0)
    assert np.abs(got - ref).max() < 1e-3                    # Embree: float32


@pytest.mark.parametrize("seed", range(3))
def test_convex_clipping_of_a_fan_matches_the_general_clipping(seed):
    from testbed._raycast_numba import convex_chords, convex_chords_fan
    from testbed.raycast import _ConvexMesh

    rng = np.random.default_rng(seed)
    hull = trimesh.convex.convex_hull(rng.normal(scale=25.0, size=(12, 3)))
    cm = _ConvexMesh(hull)
    source = rng.normal(size=3)
    source *= 300.0 / np.linalg.norm(source)
    d = _fan(rng, 500, source, np.zeros(3), 30.0)
    tm = rng.uniform(250.0, 400.0, len(d))                  # some end inside
    o = np.broadcast_to(source, d.shape).copy()
    general = convex_chords(o, d, tm, cm.normals, cm.offsets)
    assert (general > 0).sum() > 50
    # and rays parallel to a face (a zero divisor: harmless in the vectorised loop)
    fast = convex_chords_fan(source, *(np.ascontiguousarray(d[:, k]) for k in range(3)), tm,
                             cm.normals, cm.offsets)
    assert np.abs(fast - general).max() < 1e-9
    box = _ConvexMesh(trimesh.creation.box(extents=(40.0, 40.0, 40.0)))
    src = np.array([0.0, 0.0, -100.0])
    par = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])
    t = np.full(4, 500.0)
    o = np.broadcast_to(src, par.shape).copy()
    got = convex_chords_fan(src, *(np.ascontiguousarray(par[:, k]) for k in range(3)), t,
                            box.normals, box.offsets)
    assert np.array_equal(got, convex_chords(o, par, t, box.normals, box.offsets))
    assert got[2] == 40.0 and got[0] == 0.0


def test_bin_points_puts_every_point_in_its_cell():
    from testbed._fan_numba import bin_points

    rng = np.random.default_rng(2)
    x, y = rng.uniform(-1.0, 3.0, 1000), rng.uniform(2.0, 5.0, 1000)
    start, order = bin_points(x, y, -1.0, 2.0, 0.25, 0.25, 16, 12)
    assert sorted(order.tolist()) == list(range(1000))
    for c in range(16 * 12):
        idx = order[start[c]:start[c + 1]]
        assert np.all(np.minimum((x[idx] + 1.0) // 0.25, 15) == c % 16)
        assert np.all(np.minimum((y[idx] - 2.0) // 0.25, 11) == c // 16)
    # cells four times taller than wide
    start, order = bin_points(x, y, -1.0, 2.0, 0.125, 0.5, 32, 6)
    assert sorted(order.tolist()) == list(range(1000))
    for c in range(32 * 6):
        idx = order[start[c]:start[c + 1]]
        assert np.all(np.minimum((x[idx] + 1.0) // 0.125, 31) == c % 32)
        assert np.all(np.minimum((y[idx] - 2.0) // 0.5, 5) == c // 32)


def test_fan_narrower_than_the_meshes():
    """A narrow fan through the middle of meshes that extend far beyond it on every side
    (a bone shaft across a small field): triangles outside the rays' extent are clamped
    to the binning grid, and the chords still match the reference. (An unclamped cell
    index here once read past the bins and crashed the process.)"""
    from testbed.raycast import FanRays

    rng = np.random.default_rng(8)
    shaft = trimesh.creation.cylinder(radius=14.0, height=400.0, sections=64)
    shaft.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    slab = trimesh.creation.box(extents=(500.0, 300.0, 60.0))
    slab = trimesh.Trimesh(*trimesh.remesh.subdivide(slab.vertices, slab.faces))  # > 64 faces
    slab = trimesh.Trimesh(*trimesh.remesh.subdivide(slab.vertices, slab.faces))
    bodies = [Body("slab", "soft_tissue", mesh=slab), Body("shaft", "cortical_bone", mesh=shaft)]
    source = np.array([0.0, 0.0, -600.0])
    d = _fan(rng, 2000, source, np.zeros(3), 20.0)
    tm = np.full(len(d), 1000.0)
    fan = FanRays.of(source, d, tm)
    got = RayScene(bodies).fan_path_lengths(fan)
    ref = body_path_lengths(bodies, np.broadcast_to(source, d.shape).copy(), d, tm,
                            engine="numpy")
    assert np.all((ref > 0).sum(axis=0) > 500)
    assert np.abs(got - ref).max() < 1e-7


@pytest.mark.parametrize("seed", range(3))
def test_fan_sphere_chords_match_the_analytic_reference(seed):
    """Beads seen by a fan: only the rays near each sphere's image are visited; against
    sphere_chords over every ray (spheres in the field, outside it, one reaching behind
    the source's plane, rays ending inside a sphere)."""
    from testbed.raycast import FanRays

    rng = np.random.default_rng(seed)
    source = np.array([0.0, 0.0, -600.0])
    d = _fan(rng, 8000, source, np.zeros(3), 50.0)
    centres = np.vstack([rng.uniform(-45.0, 45.0, (10, 3)),            # in the field
                         [[300.0, 0.0, 0.0], [0.0, -400.0, 100.0]],   # outside it
                         [[5.0, 0.0, -600.5]]])                      # astride the source's plane
    radii = np.r_[rng.uniform(0.5, 8.0, 10), 5.0, 5.0, 3.0]
    centres[-1, 0] = 4.0                                    # the source itself stays outside
    tm = rng.uniform(560.0, 700.0, len(d))                  # some end inside a sphere
    fan = FanRays.of(source, d, tm)
    got = fan.sphere_chords(centres, radii)
    ref = sphere_chords(centres, radii, np.broadcast_to(source, d.shape).copy(), d,
                        tm).sum(axis=1)
    assert (ref > 0).sum() > 200
    # (1e-6 mm: the square root amplifies rounding for a ray grazing a sphere)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-6)


@pytest.mark.parametrize("seed", range(3))
def test_compiled_column_means_equal_numpys(seed):
    """The fan axis's mean of the ray directions, compiled, against ``d.mean(axis=0)``:
    the same bits on random arrays up to a field's size."""
    from testbed._fan_numba import column_means

    rng = np.random.default_rng(seed)
    for n in (1, 2, 7, int(rng.integers(10, 5000)), 200_000):
        d = rng.normal(0.0, 10.0 ** rng.uniform(-3, 3), (n, int(rng.integers(2, 5))))
        np.testing.assert_array_equal(column_means(d), d.mean(axis=0))


def test_a_ray_outside_a_face_where_its_depth_is_infinite_adds_nothing():
    """The rasteriser computes every tested ray's depth whether the ray is inside the face
    or not; outside it the interpolated inverse depth can be exactly zero (the face's plane
    seen edge-on from the ray). A review (h100) found 120 of 24,000 random rasterisations
    (boxes and annuli seen along their axis) raising ZeroDivisionError there. The face
    (0, 0), (1, 0), (0, 1) with depths 1, 2, 1 has the inverse depth 1 - x / 2 on the image
    plane, zero on the line x = 2: a ray there adds nothing, a ray inside adds its depth."""
    from testbed._fan_numba import bin_points, fan_chords

    vx, vy, vz = np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0]), np.array([1.0, 2.0, 1.0])
    faces = np.array([[0, 1, 2]])
    x, y = np.array([0.2, 2.0, 2.0]), np.array([0.2, 0.5, -3.0])
    grid = (-5.0, -5.0, 10.0, 10.0, 1, 1)            # one cell: every ray tested
    start, order = bin_points(x, y, *grid)
    rays = np.column_stack([x[order], y[order], np.full(3, 2.0), np.full(3, 100.0)])
    acc = np.zeros((3, 2))
    fan_chords(vx, vy, vz, faces, rays, start, *grid, acc)
    got = acc[np.argsort(order)]
    assert got[0, 0] == pytest.approx(2.0 / (1.0 - 0.2 / 2.0)) and got[0, 1] == 1.0
    assert np.array_equal(got[1:], np.zeros((2, 2)))
