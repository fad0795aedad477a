"""The end-to-end job: simulate the operating room, estimate with reglib, score at the pins.

Stages (each timed):

1. ``world``: the phantom, placed in the robot frame (:mod:`testbed.world`).
2. ``ct``: the CT scan (:func:`testbed.ct.scan`), then ``surfaces``: the proximal and distal
   bone surfaces from snake contours on its slices, the user's clicks simulated from the
   truth (:func:`studies.surfaces.reconstruct_surfaces`).
3. per view, ``calibration``: the robot sweeps the rod, ``reglib.calibration`` detects the
   beads and fits the two-plane TPS; ``xray``: the patient's frame is rendered;
   ``contours``: bone contours on it from simulated clicks (``reglib.xray_contours``), their
   X-ray paths from the calibration.
4. ``registration``: ``reglib.register.register`` from a perturbed start.

Oracle switches (for the error budget) replace one estimated input by its truth: ``"calibration"``
(the true pixel -> ray map instead of the TPS), ``"surfaces"`` (the true femur surface over
the scanned regions instead of the reconstructed one), ``"contours"`` (the true apparent
contour of the femur, projected exactly, instead of the snake's). The truth never reaches
reglib otherwise.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from reglib.geometry import RigidTransform

PIN_NAMES = ("proximal", "distal_1", "distal_2")
ORACLES = ("calibration", "surfaces", "contours")


@dataclass
class ViewData:
    """Everything about one view: the estimated and the true path maps and contours."""

    name: str
    region: str
    carm: object
    calibration: object | None
    contour_xy: np.ndarray          # (N, 2) px, from the snake (what reglib has)
    contour_external: np.ndarray    # (N,) bool
    true_contour_xy: np.ndarray     # (M, 2) px, the exact apparent contour of the femur
    true_external: np.ndarray       # (M,) bool
    frame: object
    sweep_time_s: float = 0.0
    dose_mrem: float = 0.0
    problems: tuple = ()


@dataclass
class CaseData:
    """A simulated case: the world's truth and what the estimation stages produced."""

    scene: object
    seed: int
    world: object
    surfaces: dict            # region -> (vertices (V, 3), faces (F, 3)), ct frame, estimated
    true_surfaces: dict       # region -> (vertices, faces), the phantom's femur cut alike
    views: list
    timings: dict = field(default_factory=dict)

    @property
    def ct2robot(self) -> RigidTransform:
        return self.world.ct2robot

    @property
    def pins_ct(self) -> dict:
        return {k: np.asarray(v, dtype=float) for k, v in self.world.phantom.pins.items()}


# --------------------------------------------------------------------------- truth helpers
def _silhouette_points(mesh, source, *, step_mm: float = 1.0) -> np.ndarray:
    """Points on the true apparent contour of a closed mesh seen from ``source`` (mm).

    Edges between a face turned towards the source and one turned away, sampled every
    ``step_mm``. Independent of ``reglib.apparent`` (this is the truth).
    """
    normals = mesh.face_normals
    to_face = mesh.triangles_center - source
    front = np.einsum("ij,ij->i", normals, to_face) < 0
    adj = mesh.face_adjacency
    sil = front[adj[:, 0]] != front[adj[:, 1]]
    edges = mesh.face_adjacency_edges[sil]
    a, b = mesh.vertices[edges[:, 0]], mesh.vertices[edges[:, 1]]
    n = np.maximum(1, np.ceil(np.linalg.norm(b - a, axis=1) / step_mm)).astype(int)
    pts = [a[i] + (b[i] - a[i]) * (np.arange(n[i])[:, None] / n[i]) for i in range(len(a))]
    return np.vstack(pts) if pts else np.zeros((0, 3))


def _mask_outline(mask, fov, *, edge_margin_px: float = 6.0, min_len_px: int = 40):
    """Chains (K, 2) of (x, y) px along the outline of ``mask``, away from the field edge."""
    from scipy.ndimage import distance_transform_edt
    from skimage.measure import find_contours

    inside_fov = distance_transform_edt(fov) > edge_margin_px
    chains = []
    for c in find_contours(mask.astype(float), 0.5):
        rc = np.rint(c).astype(int)
        ok = inside_fov[np.clip(rc[:, 0], 0, fov.shape[0] - 1), np.clip(rc[:, 1], 0,
                                                                        fov.shape[1] - 1)]
        # split into runs of consecutive good points
        idx = np.flatnonzero(ok)
        if idx.size == 0:
            continue
        breaks = np.flatnonzero(np.diff(idx) > 1)
        for run in np.split(idx, breaks + 1):
            if len(run) >= min_len_px:
                chains.append(c[run][:, ::-1].copy())  # (row, col) -> (x, y)
    return chains


def _clicks_along(chain_xy, n_clicks: int, noise_px: float, rng) -> np.ndarray:
    """A user's clicks: ``n_clicks`` points spread along the chain, with seeded noise."""
    seg = np.linalg.norm(np.diff(chain_xy, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(seg)]
    at = np.linspace(0.0, s[-1], n_clicks)
    pts = np.column_stack([np.interp(at, s, chain_xy[:, 0]), np.interp(at, s, chain_xy[:, 1])])
    return pts + rng.normal(0.0, noise_px, size=pts.shape)


def _region_cut(mesh_vertices, mesh_faces, z_lo, z_hi):
    """The faces of a ct-frame mesh whose centroids lie in ``[z_lo, z_hi]`` (mm)."""
    cz = mesh_vertices[mesh_faces].mean(axis=1)[:, 2]
    keep = (cz >= z_lo) & (cz <= z_hi)
    faces = mesh_faces[keep]
    used, inv = np.unique(faces, return_inverse=True)
    return mesh_vertices[used], inv.reshape(-1, 3)


# --------------------------------------------------------------------------- estimation steps
FEMUR_MATERIALS = ("cortical_bone", "cancellous_bone", "marrow")


def estimate_surfaces(world, ct, click_rng):
    """CT surfaces from snake contours (clicks simulated from the truth with ``click_rng``),
    and the true femur cut to the same z ranges: two dicts region -> (vertices, faces)."""
    from studies.surfaces import reconstruct_surfaces

    recon = reconstruct_surfaces(world.phantom, ct, rng=click_rng)
    femur = world.phantom.femur
    surfaces, true_surfaces = {}, {}
    for region, (surf, _contours) in recon.items():
        surfaces[region] = (np.asarray(surf.vertices, float), np.asarray(surf.faces, np.int64))
        z = surf.vertices[:, 2]
        true_surfaces[region] = _region_cut(np.asarray(femur.vertices, float),
                                            np.asarray(femur.faces, np.int64), z.min(), z.max())
    return surfaces, true_surfaces


def snake_contours(frame, click_rng, *, n_clicks: int = 8, click_noise_px: float = 1.0,
                   femur_mask=None):
    """Bone contours on an X-ray frame by ``reglib.xray_contours`` from a simulated user's
    clicks along the true outline. Returns points (N, 2) px and their external flags (N,)."""
    from reglib.xray_contours import xray_contours

    if femur_mask is None:
        femur_mask = frame.mask(FEMUR_MATERIALS)
    traces = [{"clicks_xy": _clicks_along(c, n_clicks, click_noise_px, click_rng),
               "label": "external", "closed": False}
              for c in _mask_outline(femur_mask, frame.fov)]
    found = xray_contours(frame.image_u8, traces) if traces else []
    if not found:
        return np.zeros((0, 2)), np.zeros(0, bool)
    xy = np.vstack([c.points_xy for c in found])
    ext = np.concatenate([np.full(len(c.points_xy), c.label == "external") for c in found])
    return xy, ext


# --------------------------------------------------------------------------- simulation
def simulate_case(scene, seed: int, *, n_clicks: int = 8, click_noise_px: float = 1.0,
                  progress: bool = False) -> CaseData:
    """Simulate a case and run every estimation stage up to (not including) registration."""
    from reglib.calibration import SweepData, calibrate, find_markers
    from testbed.ct import scan
    from testbed.fluoroscope import make_carm, render
    from testbed.robot import Robot
    from testbed.sweep import run_sweep
    from testbed.world import build_world

    if scene.scene.kind != "operating_room" or not scene.views:
        raise ValueError(f"scene {scene.scene.name!r}: the end-to-end job needs an "
                         "operating_room scene with [[views]]")
    ss = np.random.SeedSequence(seed)
    world_ss, ct_ss, click_ss, robot_ss, xray_ss = ss.spawn(5)
    timings: dict[str, float] = {}

    def tick(stage, t0):
        timings[stage] = timings.get(stage, 0.0) + time.perf_counter() - t0

    t0 = time.perf_counter()
    world = build_world(scene, np.random.default_rng(world_ss))
    tick("world", t0)

    t0 = time.perf_counter()
    ct = scan(world.phantom, scene.ct, np.random.default_rng(ct_ss))
    tick("ct", t0)
    t0 = time.perf_counter()
    click_rng = np.random.default_rng(click_ss)
    surfaces, true_surfaces = estimate_surfaces(world, ct, click_rng)
    tick("surfaces", t0)
    femur = world.phantom.femur

    views = []
    robot_rngs = np.random.default_rng(robot_ss).spawn(len(scene.views))
    xray_rngs = np.random.default_rng(xray_ss).spawn(len(scene.views))
    femur_robot = femur.copy()
    femur_robot.apply_transform(world.ct2robot.as_matrix())
    for i, vspec in enumerate(scene.views):
        carm = make_carm(scene.fluoroscope, vspec, view_index=i)
        # calibration: the robot sweeps the rod before the patient is in the beam
        t0 = time.perf_counter()
        sweep_rng, noise_rng = robot_rngs[i].spawn(2)
        with Robot(scene.robot, rng=sweep_rng) as robot:
            sweep = run_sweep(robot, carm, scene.fluoroscope, rng=noise_rng)
        tick("sweeps (simulation)", t0)
        t0 = time.perf_counter()
        markers = find_markers(SweepData(**sweep.for_calibration()))
        cal = calibrate(markers, smoothing=0.01)
        tick("calibration", t0)
        # the patient's X-ray frame
        t0 = time.perf_counter()
        frame = render(carm, world.bodies, fluoro=scene.fluoroscope, rng=xray_rngs[i])
        tick("xray (simulation)", t0)
        # the user's clicks, from the true outline; the snake does the rest
        t0 = time.perf_counter()
        femur_mask = frame.mask(FEMUR_MATERIALS)
        xy, ext = snake_contours(frame, click_rng, n_clicks=n_clicks,
                                 click_noise_px=click_noise_px, femur_mask=femur_mask)
        tick("contours", t0)
        # truth: the femur's apparent contour, projected exactly
        sil = _silhouette_points(femur_robot, carm.source_robot)
        sil_xy = carm.project(sil) if len(sil) else np.zeros((0, 2))
        H, W = frame.fov.shape
        sil_xy = sil_xy[(sil_xy[:, 0] >= 0) & (sil_xy[:, 0] <= W - 1)
                        & (sil_xy[:, 1] >= 0) & (sil_xy[:, 1] <= H - 1)]
        if len(sil_xy):
            sil_xy = sil_xy[carm.fov_rho(sil_xy) < 0.95]
        from scipy.ndimage import distance_transform_edt

        edge = distance_transform_edt(~_outline_pixels(femur_mask))
        r = np.clip(np.rint(sil_xy[:, 1]).astype(int), 0, edge.shape[0] - 1)
        c = np.clip(np.rint(sil_xy[:, 0]).astype(int), 0, edge.shape[1] - 1)
        views.append(ViewData(
            name=vspec.name, region=getattr(vspec, "region", ""), carm=carm, calibration=cal,
            contour_xy=xy, contour_external=ext, true_contour_xy=sil_xy,
            true_external=edge[r, c] <= 1.5, frame=frame, sweep_time_s=sweep.duration_s,
            dose_mrem=sweep.dose_mrem, problems=tuple(markers.problems)))
    return CaseData(scene, seed, world, surfaces, true_surfaces, views, timings)


def _outline_pixels(mask):
    from scipy.ndimage import binary_erosion

    return mask & ~binary_erosion(mask)


# --------------------------------------------------------------------------- estimation
def reglib_inputs(case: CaseData, oracle=()):
    """Surfaces and ``reglib.register.View`` list, with the named inputs replaced by truth."""
    from reglib.register import View

    oracle = set(oracle)
    unknown = oracle - set(ORACLES)
    if unknown:
        raise ValueError(f"oracle: unknown {sorted(unknown)}; expected some of {ORACLES}")
    surfaces = case.true_surfaces if "surfaces" in oracle else case.surfaces
    views = []
    for v in case.views:
        if "contours" in oracle:
            xy, ext = v.true_contour_xy, v.true_external
        else:
            xy, ext = v.contour_xy, v.contour_external
        if "calibration" in oracle:
            o, d = v.carm.true_rays(xy) if len(xy) else (np.zeros((0, 3)), np.zeros((0, 3)))
            center = v.carm.source_robot
        else:
            o, d = v.calibration.paths(xy) if len(xy) else (np.zeros((0, 3)), np.zeros((0, 3)))
            center = v.calibration.center_of_perspective()
        views.append(View(center=center, origins=o, directions=d, external=ext, name=v.name))
    return [surfaces[k] for k in sorted(surfaces)], views


def perturbed_start(ct2robot: RigidTransform, pins_ct: dict, angle_deg: float, rng,
                    *, about: str | None = None) -> RigidTransform:
    """``ct2robot`` turned by ``angle_deg`` about a random axis through the pins' centroid
    (or through the pin ``about``), so that point stays where the truth puts it."""
    rng = np.random.default_rng(rng)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    centre_ct = pins_ct[about] if about else np.mean([pins_ct[k] for k in PIN_NAMES], axis=0)
    centre = ct2robot.apply(centre_ct)
    rot = RigidTransform.from_rotvec(np.radians(angle_deg) * axis)
    about_centre = RigidTransform(rot.R, centre - rot.R @ centre)
    return about_centre @ ct2robot


def pin_errors(estimate: RigidTransform, truth: RigidTransform, pins_ct: dict) -> dict:
    """Error (mm) at each pin: distance between its estimated and true robot positions."""
    return {k: float(np.linalg.norm(estimate.apply(pins_ct[k]) - truth.apply(pins_ct[k])))
            for k in PIN_NAMES if k in pins_ct}


def registration_options(spec) -> dict:
    """Keyword options of ``reglib.register.register`` from a ``[registration]`` section."""
    return dict(method=spec.method, max_iterations=spec.max_iterations, residual=spec.residual,
                tukey_a=spec.tukey_a, selection=spec.selection,
                max_stab_distance_mm=spec.max_stab_distance_mm)


def register_case(case: CaseData, start: RigidTransform, *, oracle=(), fixed_pin=None,
                  **options):
    """Register the case from ``start``; returns (RegistrationResult, pin errors dict).

    ``options`` go to ``reglib.register.register``; by default those of the scene's
    ``[registration]`` section.
    """
    from reglib.register import register

    options = {**registration_options(case.scene.registration), **options}
    surfaces, views = reglib_inputs(case, oracle)
    fixed = case.pins_ct[fixed_pin] if fixed_pin else None
    res = register(surfaces, views, start, fixed_point_ct=fixed, **options)
    return res, pin_errors(res.ct2robot, case.ct2robot, case.pins_ct)


# --------------------------------------------------------------------------- the main job
def run_case(scene, *, scene_path, seed, out=None) -> dict:
    """``testbed run`` on an operating-room scene: one case, one perturbed start."""
    t_all = time.perf_counter()
    case = simulate_case(scene, seed)
    reg = scene.registration
    fixed_pin = getattr(reg, "fixed_pin", None) or None
    start = perturbed_start(case.ct2robot, case.pins_ct, reg.start_rotation_deg,
                            np.random.SeedSequence(seed).spawn(6)[5], about=fixed_pin)
    start_err = pin_errors(start, case.ct2robot, case.pins_ct)
    t0 = time.perf_counter()
    res, errs = register_case(case, start, fixed_pin=fixed_pin)
    timings = dict(case.timings)
    timings["registration"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_all
    acq = sum(v.sweep_time_s for v in case.views)
    dose = sum(v.dose_mrem for v in case.views)
    out_files = {}
    if out is not None:
        out_files = write_overlays(case, start, res.ct2robot, Path(out))
    return {
        "scene": scene.scene.name,
        "kind": "operating_room",
        "seed": seed,
        "pins": errs,
        "mtre_mm": float(np.mean(list(errs.values()))),
        "start_pins": start_err,
        "start_mtre_mm": float(np.mean(list(start_err.values()))),
        "converged": bool(res.converged),
        "reason": res.reason,
        "iterations": int(res.iterations),
        "views": [{"name": v.name, "contour_pixels": int(len(v.contour_xy)),
                   "sweep_time_s": v.sweep_time_s, "dose_mrem": v.dose_mrem,
                   "calibration_problems": list(v.problems)} for v in case.views],
        "acquisition_time_s": acq,
        "dose_mrem": dose,
        "outputs": out_files,
        "timings": timings,
        "extra_lines": [("start mTRE (mm)", f"{np.mean(list(start_err.values())):.2f}"),
                        ("registration", f"{res.reason} after {res.iterations} iterations"),
                        ("acquisition (sweeps)", f"{acq:.1f} s, dose {dose:.1f} mrem")],
    }


def write_overlays(case: CaseData, start: RigidTransform, final: RigidTransform, out: Path):
    """One PNG per view: the frame, the snake contours, and the surfaces' apparent contours
    projected at the start (red) and after registration (green)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import trimesh

    out.mkdir(parents=True, exist_ok=True)
    files = {}
    for v in case.views:
        fig, ax = plt.subplots(figsize=(8, 6))
        ax.imshow(v.frame.image_u8, cmap="gray", vmin=0, vmax=255)
        if len(v.contour_xy):
            ax.plot(v.contour_xy[:, 0], v.contour_xy[:, 1], ".", ms=1.5, color="yellow",
                    label="X-ray contour (snake)")
        for pose, color, label in ((start, "red", "surfaces at start"),
                                   (final, "lime", "surfaces registered")):
            for k, (verts, faces) in enumerate(case.surfaces.values()):
                m = trimesh.Trimesh(pose.apply(verts), faces, process=False)
                sil = _silhouette_points(m, v.carm.source_robot, step_mm=2.0)
                if len(sil):
                    xy = v.carm.project(sil)
                    ax.plot(xy[:, 0], xy[:, 1], ",", color=color,
                            label=label if k == 0 else None)
        ax.set_xlim(0, v.frame.image_u8.shape[1])
        ax.set_ylim(v.frame.image_u8.shape[0], 0)
        ax.legend(loc="lower right", fontsize=7, markerscale=6)
        ax.set_title(f"view {v.name}")
        path = out / f"overlay_{v.name}.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        files[v.name] = str(path)
    return files


# --------------------------------------------------------------------------- study helpers
PAPER_TABLE2 = {  # Table II of the paper (mm); 5 deg #1 and #2 are unreadable in the scan
    "identity": (1.16, 2.38, 2.40),
    "rot5_3": (3.05, 2.91, 2.95), "rot5_4": (2.14, 1.61, 2.66), "rot5_5": (2.76, 3.06, 2.69),
    "rot7_1": (3.08, 3.66, 2.96), "rot7_2": (2.70, 2.52, 3.22), "rot7_3": (2.56, 2.84, 2.38),
    "rot7_4": (3.48, 4.81, 2.83), "rot7_5": (2.59, 2.32, 3.18),
}


def table2_starts(case: CaseData, seed: int, *, quick: bool = False, about=None) -> dict:
    """The paper's 11 starts: the true pose, and five 5 deg and five 7 deg rotations about
    seeded random axes through the pins' centroid (translation keeping it fixed)."""
    rngs = np.random.SeedSequence([seed, 2]).spawn(10)
    starts = {"identity": case.ct2robot}
    n = 2 if quick else 5
    for j, angle in enumerate((5.0, 7.0)):
        for k in range(n):
            starts[f"rot{int(angle)}_{k + 1}"] = perturbed_start(
                case.ct2robot, case.pins_ct, angle, rngs[5 * j + k], about=about)
    return starts


def registration_rows(case: CaseData, starts: dict, *, oracle=(), fixed_pin=None,
                      progress: bool = True, **options) -> list[dict]:
    """Register from every start; long-format rows (``pin_error`` per pin, ``mtre``,
    ``start_mtre``, ``converged``, ``iterations``, ``time``) with a ``start`` column."""
    from tqdm import tqdm

    rows = []
    label = "+".join(sorted(oracle)) or "none"
    for name, start in tqdm(list(starts.items()), desc=f"registrations (oracle {label})",
                            disable=not progress, leave=False):
        t0 = time.perf_counter()
        res, errs = register_case(case, start, oracle=oracle, fixed_pin=fixed_pin, **options)
        dt = time.perf_counter() - t0
        start_errs = pin_errors(start, case.ct2robot, case.pins_ct)
        base = {"trial": name, "start": name, "oracle": label}
        for pin, e in errs.items():
            rows.append({**base, "metric": "pin_error", "value": e, "unit": "mm", "pin": pin})
        rows += [
            {**base, "metric": "mtre", "value": float(np.mean(list(errs.values()))),
             "unit": "mm"},
            {**base, "metric": "start_mtre", "value": float(np.mean(list(start_errs.values()))),
             "unit": "mm"},
            {**base, "metric": "converged", "value": float(res.converged), "unit": ""},
            {**base, "metric": "iterations", "value": float(res.iterations), "unit": ""},
            {**base, "metric": "time", "value": dt, "unit": "s"},
        ]
    return rows
