"""``testbed generate``: a synthetic dataset with perfect ground truth, case by case.

Each case is simulated from its own seed (case ``i`` gets child ``i`` of
``numpy.random.SeedSequence(seed).spawn(cases)``) and written with
:func:`testbed.dataset.write_case` into ``out/case_0000``, ``out/case_0001``, ...; an existing
complete case folder is kept (rerunning the command resumes). The entries of a case, their
roles (observation / truth), units and frames are listed in :data:`ENTRY_DOC` and in
``docs/dataset-format.md`` (section "What `testbed generate` writes").

Only the simulator runs here (``testbed`` never uses reglib beyond ``reglib.geometry``), so
the dataset holds the raw observations (CT volume, X-ray frames, calibration sweeps with
the robot-reported rod poses) and the truth, not reglib's estimates (its surfaces or
calibration): those are what a user of the dataset computes.
"""

from __future__ import annotations

import json
import re
import time
from pathlib import Path

import numpy as np

__all__ = ["ENTRY_DOC", "GENERATOR_VERSION", "case_seed", "generate_command", "simulate_entries"]

GENERATOR_VERSION = 1

#: entry name pattern -> (role, description); ``{view}`` is the view's name.
ENTRY_DOC = {
    "volumes/ct": ("observation", "CT volume in HU (float32), data[i, j, k] = (column, row, "
                   "slice); voxel2ct maps (i, j, k, 1) to ct mm (exact only when the slices "
                   "are equally spaced, see arrays/ct_slices)"),
    "arrays/ct_slices": ("observation", "npz: z_mm (K,) slice positions along ct z, "
                         "thickness_mm (K,), slice2ct (K, 4, 4) maps (col, row, 0, 1) of "
                         "slice k to ct mm (authoritative), uniform () bool"),
    "images/xray_{view}": ("observation", "the X-ray frame of the view, 8-bit video (H, W)"),
    "arrays/xray_fov_{view}": ("observation", "(H, W) bool, the circular field of view"),
    "arrays/xray_float_{view}": ("truth", "(H, W) float32 detected intensity before 8-bit "
                                 "quantisation (noise, glare, vignetting included)"),
    "images/sweep_{view}": ("observation", "(F, H, W) 8-bit frames of the calibration sweep, "
                            "one after each rod move"),
    "arrays/sweep_{view}": ("observation", "npz: plane (F,) int plane code (-1: reference "
                            "frame), beads_reported (F, n, 3) robot mm (NaN on reference "
                            "frames), rod2robot_reported (F, 4, 4) the robot-reported rod "
                            "pose, joints (F, 5) rad/mm, time_s (F,), bead_positions_mm (n,)"),
    "arrays/sweep_truth_{view}": ("truth", "npz: beads_true (F, n, 3) robot mm, "
                                  "rod2robot_true (F, 4, 4) the true rod pose"),
    "arrays/rays_{view}": ("truth", "npz: origins (H, W, 3), directions (H, W, 3) unit, robot "
                           "frame mm: the true X-ray path of every pixel (distortion "
                           "included)"),
    "transforms/carm2robot_{view}": ("truth", "C-arm frame (source at the origin, +z the "
                                     "beam) -> robot frame"),
    "transforms/ct2robot": ("truth", "ct -> robot: x_robot = R x_ct + t (the registration's "
                            "answer)"),
    "meshes/{body}": ("truth", "phantom bodies in the ct frame, mm: femur, canal, cancellous, "
                      "soft_tissue, pin_<name>"),
    "meshes/robot_{body}": ("truth", "the table (foam, top) and the instruments' meshes in the "
                            "robot frame, mm"),
    "points/pins_ct": ("truth", "pin centres, ct mm, by name"),
    "points/pins_robot": ("truth", "pin centres, robot mm, by name"),
    "points/landmarks_ct": ("truth", "anatomical landmarks of the femur, ct mm, by name"),
}


def case_seed(seed: int, index: int, cases: int) -> np.random.SeedSequence:
    """The seed of case ``index``: child ``index`` of ``SeedSequence(seed).spawn(cases)``."""
    if not 0 <= index < cases:
        raise ValueError(f"case index {index}: expected 0 <= index < cases = {cases}")
    return np.random.SeedSequence(int(seed)).spawn(int(cases))[index]


def _case_scene(scene, shape_ss: np.random.SeedSequence):
    """The scene of one case: its own femur shape seed (used when shape_variation > 0)."""
    shape_seed = int(shape_ss.generate_state(1, dtype=np.uint32)[0])
    phantom = scene.phantom.model_copy(update={"shape_seed": shape_seed})
    return scene.model_copy(update={"phantom": phantom})


def simulate_entries(scene, case_ss: np.random.SeedSequence, *, progress: bool = False):
    """Simulate one case and return ``(case dict, truth entry list, timings)``.

    Parameters
    ----------
    scene : testbed.scene.Scene
        An operating-room scene with ``[[views]]``.
    case_ss : numpy.random.SeedSequence
        The case's seed; every random choice is drawn from its children.
    progress : bool
        Show a tqdm bar over the sweep frames of each view.

    Returns
    -------
    case : dict
        ``meta`` and the groups of :func:`testbed.dataset.write_case`.
    truth : list of str
        The truth entries (``"group/name"``).
    timings : dict
        Stage -> wall time (s).
    """
    from tqdm import tqdm

    from testbed.ct import scan
    from testbed.dataset import Volume
    from testbed.fluoroscope import make_carm, render
    from testbed.robot import Robot
    from testbed.sweep import run_sweep
    from testbed.world import build_world

    if scene.scene.kind != "operating_room" or not scene.views:
        raise ValueError(f"scene {scene.scene.name!r}: testbed generate needs an "
                         "operating_room scene with [[views]]")
    shape_ss, world_ss, ct_ss, robot_ss, xray_ss = case_ss.spawn(5)
    scene = _case_scene(scene, shape_ss)
    timings: dict[str, float] = {}
    groups = {g: {} for g in ("volumes", "images", "arrays", "meshes", "transforms", "points")}
    truth: list[str] = []

    def put(group, name, value, role):
        if name in groups[group]:
            raise ValueError(f"{group}/{name}: two entries of that name (view names must be "
                             "unique)")
        groups[group][name] = value
        if role == "truth":
            truth.append(f"{group}/{name}")

    t0 = time.perf_counter()
    world = build_world(scene, np.random.default_rng(world_ss))
    timings["world"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    ct = scan(world.phantom, scene.ct, np.random.default_rng(ct_ss))
    z = np.asarray(ct.slice_z_mm, dtype=np.float64)
    dz = np.diff(z)
    uniform = bool(len(z) < 2 or np.ptp(dz) <= 1e-6)
    if uniform:
        voxel2ct = ct.voxel2ct
    else:  # the NIfTI header needs one affine: the first slice and the mean spacing
        voxel2ct = np.eye(4)
        voxel2ct[0, 0] = voxel2ct[1, 1] = ct.pixel_mm
        voxel2ct[2, 2] = float(np.mean(dz))
        voxel2ct[:3, 3] = (*ct.origin_xy_mm, z[0])
    data = np.ascontiguousarray(np.asarray(ct.volume_hu).transpose(2, 1, 0))
    put("volumes", "ct", Volume(data, voxel2ct), "observation")
    put("arrays", "ct_slices", {"z_mm": z, "thickness_mm": np.asarray(ct.slice_thickness_mm,
                                                                      dtype=np.float64),
                                "slice2ct": np.asarray(ct.slice2ct, dtype=np.float64),
                                "uniform": np.array(uniform)}, "observation")
    timings["ct"] = time.perf_counter() - t0

    ph = world.phantom
    put("transforms", "ct2robot", world.ct2robot, "truth")
    meshes = {"femur": ph.femur, "canal": ph.canal, "cancellous": ph.cancellous,
              "soft_tissue": ph.soft_tissue}
    meshes.update({f"pin_{k}": m for k, m in ph.pin_meshes.items()})
    for name, m in meshes.items():
        if m is not None:
            put("meshes", name, m, "truth")
    for body in [*world.table, *world.instruments]:  # already in the robot frame
        if body.mesh is not None:
            put("meshes", "robot_" + re.sub(r"[^A-Za-z0-9_.\-]", "_", body.name), body.mesh,
                "truth")
    put("points", "pins_ct", {k: np.asarray(v, float) for k, v in ph.pins.items()}, "truth")
    put("points", "pins_robot", {k: np.asarray(v, float) for k, v in world.pins_robot.items()},
        "truth")
    if ph.landmarks:
        put("points", "landmarks_ct", {k: np.asarray(v, float) for k, v in ph.landmarks.items()},
            "truth")

    robot_rngs = np.random.default_rng(robot_ss).spawn(len(scene.views))
    xray_rngs = np.random.default_rng(xray_ss).spawn(len(scene.views))
    for i, vspec in enumerate(scene.views):
        v = vspec.name
        carm = make_carm(scene.fluoroscope, vspec, view_index=i)
        put("transforms", f"carm2robot_{v}", carm.carm2robot, "truth")

        t0 = time.perf_counter()
        sweep_rng, noise_rng = robot_rngs[i].spawn(2)
        rep_poses, true_poses = [], []
        with Robot(scene.robot, rng=sweep_rng) as robot:
            bar = tqdm(desc=f"sweep {v}", disable=not progress, leave=False, unit="frame")

            def record(k, n, robot=robot, bar=bar, rep=rep_poses, tru=true_poses):
                # called after frame k is rendered: the robot is still at that frame's pose
                rep.append(robot.reported_rod2robot.as_matrix())
                tru.append(robot.true_rod2robot.as_matrix())
                bar.total = n
                bar.update(1)

            sweep = run_sweep(robot, carm, scene.fluoroscope, rng=noise_rng, progress=record)
            bar.close()
        timings["sweeps"] = timings.get("sweeps", 0.0) + time.perf_counter() - t0
        put("images", f"sweep_{v}", sweep.frames, "observation")
        put("arrays", f"sweep_{v}", {
            "plane": np.asarray(sweep.plane), "beads_reported": sweep.beads_reported,
            "rod2robot_reported": np.array(rep_poses), "joints": sweep.joints,
            "time_s": np.asarray(sweep.time_s, dtype=np.float64),
            "bead_positions_mm": np.asarray(sweep.bead_positions_mm, dtype=np.float64)},
            "observation")
        put("arrays", f"sweep_truth_{v}", {"beads_true": sweep.beads_true,
                                           "rod2robot_true": np.array(true_poses)}, "truth")

        t0 = time.perf_counter()
        frame = render(carm, world.bodies, fluoro=scene.fluoroscope, rng=xray_rngs[i])
        timings["xray"] = timings.get("xray", 0.0) + time.perf_counter() - t0
        put("images", f"xray_{v}", frame.image_u8, "observation")
        put("arrays", f"xray_fov_{v}", np.asarray(frame.fov, dtype=bool), "observation")
        put("arrays", f"xray_float_{v}", np.asarray(frame.image, dtype=np.float32), "truth")
        o, d = carm.pixel_ray_map()
        put("arrays", f"rays_{v}", {"origins": o, "directions": d}, "truth")

    meta = {
        "generator": "testbed generate",
        "generator_version": GENERATOR_VERSION,
        "scene": scene.model_dump(mode="json"),
        "seed": {"entropy": int(case_ss.entropy), "spawn_key": [int(k) for k in
                                                                 case_ss.spawn_key]},
        "views": [v.name for v in scene.views],
        "ct_uniform_slices": uniform,
        "units": {"length": "mm", "angle": "rad", "pixel": "px (x, y) = (col, row)"},
        "entries": {k: {"role": r, "description": d} for k, (r, d) in ENTRY_DOC.items()},
    }
    return {"meta": meta, **groups}, truth, timings


def generate_command(scene, *, scene_path, cases: int, out, seed: int | None = None,
                     progress: bool = True) -> list[Path]:
    """Write ``cases`` simulated cases of ``scene`` into the folder ``out``.

    Parameters
    ----------
    scene : testbed.scene.Scene
        The resolved scene (operating room, with views).
    scene_path : path
        Where the scene came from (recorded in the metadata).
    cases : int
        Number of cases (>= 1).
    out : path
        The dataset folder; case ``i`` goes to ``out/case_{i:04d}``. Cases already complete
        there are kept (a rerun resumes); ``out/dataset.json`` lists the cases.
    seed : int, optional
        The dataset's seed (default: the scene's); case ``i`` is simulated from child ``i``
        of ``SeedSequence(seed).spawn(cases)``.
    progress : bool
        A tqdm progress bar over the cases.

    Returns
    -------
    list of Path
        The case folders.
    """
    from tqdm import tqdm

    from testbed.dataset import CASE_FILE, write_case

    if isinstance(cases, bool) or not isinstance(cases, int | np.integer) or cases < 1:
        raise ValueError(f"--cases: expected an integer >= 1, got {cases!r}")
    seed = scene.scene.seed if seed is None else seed
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"--seed: expected an integer >= 0, got {seed!r}")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out}: exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    children = np.random.SeedSequence(int(seed)).spawn(int(cases))
    dirs = []
    for i in tqdm(range(cases), desc="cases", disable=not progress, unit="case"):
        case_dir = out / f"case_{i:04d}"
        dirs.append(case_dir)
        if (case_dir / CASE_FILE).is_file():
            continue
        case, truth, timings = simulate_entries(scene, children[i])
        case["meta"].update(case_index=i, dataset_seed=int(seed), scene_path=str(scene_path),
                            timings_s=timings)
        write_case(case_dir, case, truth=truth)
    summary = {"generator": "testbed generate", "generator_version": GENERATOR_VERSION,
               "scene_path": str(scene_path), "scene_name": scene.scene.name,
               "seed": int(seed), "cases": [d.name for d in dirs]}
    (out / "dataset.json").write_text(json.dumps(summary, indent=2))
    return dirs

