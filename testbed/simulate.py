"""The one simulation driver: a scene and a seed in, a case's ``(Observation, Truth)`` out.

:func:`simulate_case` is what ``testbed run``, every study and ``testbed generate`` call, so
that a dataset case and a study case of the same scene and seed are the same case. Stages:

1. the world (:mod:`testbed.world`): the phantom (its femur shape drawn from the case's seed
   when ``[phantom] shape_variation > 0``), placed in the robot frame, the table and the
   instruments;
2. the CT scan (:mod:`testbed.ct`) and the operator's clicks on its slices
   (:mod:`testbed.operator`);
3. per view: the calibration sweep (:mod:`testbed.sweep`; the robot moves the rod through
   the beam with the patient, table and instruments in it, as in a clinic), the patient's
   X-ray frame (:mod:`testbed.fluoroscope`) and the operator's clicks on it.

The observation holds what a clinic has (see ``docs/dataset-format.md`` for every entry):
the CT volume and its slice geometry, the operator's CT clicks per region, per view the
8-bit X-ray frame, its field of view, the operator's clicks, the calibration sweep's frames
and the robot-reported rod and bead positions. The truth holds the rest. ``reglib`` reads
the observation only (``reglib.estimate``).

Seeds: the case seed of ``(seed, index)`` is ``SeedSequence(seed, spawn_key=(index,))``,
i.e. child ``index`` of ``SeedSequence(seed).spawn(n)`` for any ``n > index``; ``testbed
run --seed S`` simulates case 0 of ``S``, the same case as ``case_0000`` of ``testbed
generate --seed S``. Each stream of a case (:data:`SEED_STREAMS`: the femur's shape, the
world, the CT scanner, the operator, the robot (one child per view: arm errors, then sweep
image noise), the X-ray frames (one child per view), the patient's placement where the
scene draws one, the femur's motion between views where the scene asks for it) is the case
seed's child of spawn key :data:`STREAM_KEYS` ``[name]``, built directly
(:func:`case_streams`): a case seed is never spawned from, so the same seed gives the same
streams however often and in whatever order the stages ask for them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from testbed.dataset import Observation, Truth, Volume
from testbed.instruments import file_key
from testbed.seeds import keyed_seed

__all__ = [
    "CtCase",
    "SEED_STREAMS",
    "STREAM_KEYS",
    "case_streams",
    "FEMUR_BODIES",
    "Simulation",
    "case_seed",
    "case_world",
    "checked_world",
    "placement_note",
    "simulate",
    "simulate_case",
    "simulate_ct",
    "view_bodies",
    "view_poses",
]

#: the streams of a case
SEED_STREAMS = ("shape", "world", "ct", "operator", "robot", "xray", "placement", "motion")
#: the child (spawn key) of the case seed behind each stream. The numbers are those the
#: streams had when the stages drew them by successive ``spawn()`` calls on the case seed
#: (robot and X-ray from the first 6 children, shape and world from the second 6, CT and
#: operator from the third), kept so that every case and dataset stays what it was; the
#: placement's (2026-11-26) and the motion's (2026-11-27) new keys, so that no earlier stream
#: moved.
STREAM_KEYS = {"shape": 6, "world": 7, "ct": 14, "operator": 15, "robot": 4, "xray": 5,
               "placement": 16, "motion": 17}
#: a case's placement draw is clipped at this many standard deviations ([patient]
#: position_sd_mm, rotation_sd_deg)
PLACEMENT_CLIP_SD = 2.5
#: the phantom bodies whose outline is the femur's outline on an X-ray frame
FEMUR_BODIES = ("femur",)


def case_streams(seed, index: int = 0) -> dict[str, np.random.SeedSequence]:
    """Stream name -> SeedSequence of case ``index`` of ``seed`` (see :data:`STREAM_KEYS`);
    the case seed itself is not modified."""
    css = case_seed(seed, index)
    return {name: keyed_seed(css, k) for name, k in STREAM_KEYS.items()}


def case_seed(seed, index: int = 0) -> np.random.SeedSequence:
    """The SeedSequence of case ``index`` of ``seed`` (an int >= 0, or a SeedSequence,
    returned as it is when ``index`` is 0 and it is already a case seed)."""
    if isinstance(seed, np.random.SeedSequence):
        return seed
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"seed: expected an integer >= 0, got {seed!r}")
    if isinstance(index, bool) or not isinstance(index, int | np.integer) or index < 0:
        raise ValueError(f"index: expected an integer >= 0, got {index!r}")
    return np.random.SeedSequence(int(seed), spawn_key=(int(index),))


@dataclass
class Simulation:
    """A simulated case: what the clinic has, the truth, and the world objects behind them.

    ``observation`` and ``truth`` are what :func:`simulate_case` returns (and what a dataset
    holds); ``world`` (:class:`testbed.world.World`), ``carms`` (view name -> the C-arm of
    the patient's frame) and ``frames`` (view name -> :class:`testbed.fluoroscope.Frame`)
    are kept for the judge's oracles and figures; ``sweeps`` view name -> the recorded
    :class:`testbed.sweep.Sweep` (empty with ``sweeps=False``); ``scene`` the case's scene
    (its femur shape seed set); ``timings`` stage -> wall time (s).
    """

    observation: Observation
    truth: Truth
    scene: object
    world: object
    carms: dict
    frames: dict
    sweeps: dict
    timings: dict = field(default_factory=dict)

    @property
    def pair(self) -> tuple[Observation, Truth]:
        return self.observation, self.truth


def _case_scene(scene, shape_ss: np.random.SeedSequence):
    """The case's scene: the femur's shape seed drawn from the scene's ``[phantom]
    shape_seed`` and the case (used when ``shape_variation > 0``), so that every case of a
    run has its own femur and another ``shape_seed`` gives other femurs."""
    mixed = np.random.SeedSequence([int(scene.phantom.shape_seed),
                                    *shape_ss.generate_state(2, dtype=np.uint32).tolist()])
    shape_seed = int(mixed.generate_state(1, dtype=np.uint32)[0])
    phantom = scene.phantom.model_copy(update={"shape_seed": shape_seed})
    return scene.model_copy(update={"phantom": phantom})


def _case_placement(scene, placement_ss: np.random.SeedSequence):
    """The case's scene with its patient's placement drawn ([patient] ``position_sd_mm``,
    ``rotation_sd_deg``: normal per robot axis, clipped at :data:`PLACEMENT_CLIP_SD`; the
    turn about the femur's middle, ``phantom.length_mm / 2`` up the ct frame's z axis), its
    standard deviations then 0: the resolved scene is the case's, and simulating it again
    gives the same case. The scene as it is when both are 0."""
    from scipy.spatial.transform import Rotation

    p = scene.patient
    if not p.varies:
        return scene
    z = np.clip(np.random.default_rng(placement_ss).standard_normal(6),
                -PLACEMENT_CLIP_SD, PLACEMENT_CLIP_SD)
    shift = z[:3] * np.asarray(p.position_sd_mm, dtype=np.float64)
    turn = Rotation.from_rotvec(np.radians(z[3:] * np.asarray(p.rotation_sd_deg,
                                                               dtype=np.float64)))
    T = _moved(p.ct2robot(), turn, shift, float(scene.phantom.length_mm))
    patient = p.model_copy(update={
        "position_mm": tuple(float(x) for x in T.t),
        "rotation_deg": tuple(float(x) for x in Rotation.from_matrix(T.R).as_euler(
            "xyz", degrees=True)),
        "position_sd_mm": (0.0, 0.0, 0.0), "rotation_sd_deg": (0.0, 0.0, 0.0)})
    return scene.model_copy(update={"patient": patient})


def _moved(ct2robot, turn, shift_mm, length_mm: float):
    """``ct2robot`` (a RigidTransform) after the femur turns by ``turn`` (a scipy Rotation,
    robot frame) about its middle, ``length_mm / 2`` up the ct frame's z axis, and shifts
    by ``shift_mm`` (robot frame)."""
    from reglib.geometry import RigidTransform

    middle = ct2robot.apply(np.array([0.0, 0.0, 0.5 * length_mm]))
    return RigidTransform(turn.as_matrix() @ ct2robot.R,
                          turn.apply(ct2robot.t - middle) + middle + shift_mm)


def placement_note(given, case) -> str:
    """``""``, or, when ``given`` (a scene) draws each case's patient placement (``[patient]
    position_sd_mm``, ``rotation_sd_deg``), a clause to add to a refusal of the case
    ``case`` (its resolved scene): how far the draw moved the patient, so that a line blaming
    a view or the soft tissue does not send the user to fields that are right for the
    scene's own placement (a review: ``generate`` stopped at a case, naming neither)."""
    p = given.patient
    if not p.varies:
        return ""
    length = float(case.phantom.length_mm)
    mid = np.array([0.0, 0.0, 0.5 * length])
    a, b = p.ct2robot(), case.patient.ct2robot()
    shift = float(np.linalg.norm(b.apply(mid) - a.apply(mid)))
    turn = float(np.degrees((b @ a.inverse()).angle_rad))
    return (f" (this case's patient lies where [patient] position_sd_mm = "
            f"{tuple(p.position_sd_mm)} and rotation_sd_deg = {tuple(p.rotation_sd_deg)} drew "
            f"it for the case's seed: the femur's middle {shift:.0f} mm and {turn:.1f} deg from "
            "where position_mm and rotation_deg put it; other seeds may be feasible, and "
            "smaller standard deviations keep every case's anatomy in the views)")


def view_bodies(world, ct2robot) -> list:
    """The world's bodies (robot frame) with the patient's at ``ct2robot`` (the table and
    the instruments where they are): ``world.bodies`` when that is the world's own pose."""
    if ct2robot is world.ct2robot:
        return world.bodies
    return [*(b.transformed(ct2robot) for b in world.phantom.bodies()), *world.table,
            *world.instruments]


def view_poses(scene, ct2robot, motion_ss: np.random.SeedSequence) -> list:
    """The femur's pose (ct -> robot, RigidTransform) at each view of the case: ``ct2robot``
    (its pose at the pin digitisation) for every view when the bone holds still, else the
    random walk of ``[patient] motion_mm`` / ``motion_deg`` (one step before each view,
    each a normal draw per robot axis clipped at :data:`PLACEMENT_CLIP_SD`; see
    :class:`testbed.scene.PatientSpec`)."""
    from scipy.spatial.transform import Rotation

    p = scene.patient
    if not p.moves:
        return [ct2robot] * len(scene.views)
    rng = np.random.default_rng(motion_ss)
    poses, T = [], ct2robot
    for _ in scene.views:
        z = np.clip(rng.standard_normal(6), -PLACEMENT_CLIP_SD, PLACEMENT_CLIP_SD)
        turn = Rotation.from_rotvec(np.radians(z[3:] * float(p.motion_deg)))
        T = _moved(T, turn, z[:3] * float(p.motion_mm), float(scene.phantom.length_mm))
        poses.append(T)
    return poses


#: the spawn key, under the robot stream, of the case's one robot (its imperfections and
#: every move's encoder error); the views' children take keys 0, 1, ... (their frames' noise)
ROBOT_KEY = 1 << 20


def _no_trace_message(i: int, vspec, frame, scene) -> str:
    """Why the operator traced nothing on a view's frame, with the fields that decide it: the
    femur outside the field (the view, the patient), or shown but every run of its outline
    too short or too near the rim or an instrument (the detector, the operator's margins)."""
    femur_px = int(sum(np.count_nonzero((frame.path_mm[n] > 0) & frame.fov)
                       for n in FEMUR_BODIES if n in frame.path_mm))
    fl, op = scene.fluoroscope, scene.operator
    where = f"views[{i}] ({vspec.name!r}): the femur's outline is nowhere traceable in the frame"
    if femur_px == 0:
        return (f"{where}: the femur is outside the field; check views[{i}].isocenter_mm and "
                "its angles, and where [patient] position_mm and rotation_deg put the femur")
    return (f"{where}: the femur covers {femur_px} px of the field, but no run of its outline "
            f"is operator.xray_min_trace_px = {op.xray_min_trace_px} px long, farther than "
            f"xray_edge_margin_px = {op.xray_edge_margin_px:g} px from the field's rim and "
            f"instrument_margin_px = {op.instrument_margin_px:g} px from an instrument; the "
            f"detector is fluoroscope.width_px x height_px = {fl.width_px} x {fl.height_px} of "
            f"pixel_mm = {fl.pixel_mm:g} (check those, the view's aim and the instruments)")


@dataclass
class CtCase:
    """The CT side of a case: the case's ``scene`` (its femur shape seed set), the ``world``,
    the ``ct`` scan (:class:`testbed.ct.CTScan`), the operator's ``clicks`` (region ->
    :class:`testbed.operator.CtClicks`) and the operator's generator for the X-ray frames."""

    scene: object
    world: object
    ct: object
    clicks: dict
    xray_operator_rng: np.random.Generator


def case_world(scene, seed=0, *, index: int = 0):
    """The case's scene (its femur shape seed set) and world, exactly as :func:`simulate`
    makes them: ``(scene, world)``."""
    from testbed.scene import require_scene
    from testbed.world import build_world

    require_scene(scene)
    streams = case_streams(seed, index)
    scene = _case_placement(_case_scene(scene, streams["shape"]), streams["placement"])
    return scene, build_world(scene, np.random.default_rng(streams["world"]))


def checked_world(scene, seed=0, *, index: int = 0):
    """:func:`case_world` and its workspace check (``testbed.workspace.require_feasible``,
    which raises for a view that cannot be taken): ``(scene, world, reports)``, as
    :func:`simulate` makes them; pass it to :func:`simulate` as ``prepared``."""
    from testbed.workspace import WorkspaceError, require_feasible

    given = scene
    scene, world = case_world(scene, seed, index=index)
    try:
        return scene, world, require_feasible(scene, world)
    except WorkspaceError as exc:
        note = placement_note(given, scene)
        if not note:
            raise
        raise WorkspaceError(f"{exc}{note}") from None


def simulate_ct(scene, seed=0, *, index: int = 0, world=None) -> CtCase:
    """The world, the CT scan and the operator's CT clicks of a case, exactly as
    :func:`simulate` makes them (same seed streams), without fluoroscopy. ``world``: the
    case's world when already built (:func:`case_world`; ``scene`` is then the case's)."""
    from testbed.ct import scan
    from testbed.operator import ct_clicks

    css = case_seed(seed, index)
    streams = case_streams(css)
    if world is None:
        scene, world = case_world(scene, css)
    ct = scan(world.phantom, scene.ct, np.random.default_rng(streams["ct"]))
    ct_rng, xray_op_rng = np.random.default_rng(streams["operator"]).spawn(2)
    clicks = ct_clicks(ct.volume_hu, ct.slice_z_mm, ct.regions, pixel_mm=ct.pixel_mm,
                       spec=scene.operator, rng=ct_rng)
    return CtCase(scene, world, ct, clicks, xray_op_rng)


#: the memory a case's simulation holds at its peak (bytes): a base, and per view so much per
#: pixel and per ray (pixels x oversample^2). Measured (2026-11-29): experiment2 0.73 GB at
#: 640 x 480, 1.17 GB with oversample 2, 1.90 GB at 1024 x 1024, 6.25 GB at 2048 x 2048 (a
#: held-out review, h95: 4096 x 4096 grew past the machine's 23 GB and would have been
#: killed without a word); these figures lie 15-36 % above each
MEMORY_BASE_BYTES = 0.5e9
MEMORY_PER_PIXEL_BYTES = 300.0
MEMORY_PER_RAY_BYTES = 100.0


def memory_needed_bytes(scene) -> float:
    """About the most memory (bytes) simulating one case of ``scene`` holds at once (see
    :data:`MEMORY_BASE_BYTES`)."""
    f = scene.fluoroscope
    pixels = float(f.width_px) * float(f.height_px)
    rays = pixels * float(f.oversample) ** 2
    return MEMORY_BASE_BYTES + len(scene.views) * (MEMORY_PER_PIXEL_BYTES * pixels
                                                   + MEMORY_PER_RAY_BYTES * rays)


def _meminfo_bytes(key: str) -> float:
    """``key`` of ``/proc/meminfo`` (bytes; inf when it cannot be read)."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith(key + ":"):
                    return float(line.split()[1]) * 1024.0
    except (OSError, ValueError, IndexError):
        pass
    return float("inf")


def _cgroup_bytes(name: str) -> float:
    """``/sys/fs/cgroup/{name}`` (cgroup v2; bytes; inf for "max" or when absent)."""
    try:
        with open(f"/sys/fs/cgroup/{name}") as fh:
            text = fh.read().strip()
        return float("inf") if text == "max" else float(text)
    except (OSError, ValueError):
        return float("inf")


def total_memory_bytes() -> float:
    """This machine's memory (bytes): ``MemTotal``, or the container's limit when lower."""
    return min(_meminfo_bytes("MemTotal"), _cgroup_bytes("memory.max"))


def available_memory_bytes() -> float:
    """The memory (bytes) new work can take now: ``MemAvailable``, or what the container's
    limit leaves when less."""
    limit = _cgroup_bytes("memory.max")
    left = limit - _cgroup_bytes("memory.current") if np.isfinite(limit) else limit
    return min(_meminfo_bytes("MemAvailable"), left)


def check_memory(scene, *, workers: int | None = None) -> None:
    """ValueError naming ``[fluoroscope]``'s image size when simulating a case of ``scene``
    needs more memory (:func:`memory_needed_bytes`) than the machine has
    (:func:`total_memory_bytes`); with ``workers``, when that many cases simulated at once
    need more than is available now (:func:`available_memory_bytes`; a study checks this
    before its first trial: a trial refused for what other workers held would depend on the
    machine's load)."""
    f = scene.fluoroscope
    size = (f"fluoroscope.width_px x height_px = {f.width_px} x {f.height_px} (oversample "
            f"{f.oversample}) over {len(scene.views)} views")
    fix = ("give fewer pixels (pixel_mm larger for the same field; a fluoroscope's video is "
           "640 x 480 to 1024 x 1024) or a lower oversample")
    need = memory_needed_bytes(scene)
    if workers is None:
        have = total_memory_bytes()
        if need > have:
            raise ValueError(f"{size} needs about {need / 1e9:.1f} GB of memory to simulate a "
                             f"case, more than this machine's {have / 1e9:.1f} GB: {fix}")
        return
    have = available_memory_bytes()
    if workers * need > have:
        raise ValueError(f"--workers {workers}: {size} need about {workers * need / 1e9:.1f} "
                         f"GB of memory for {workers} cases at once, and this machine has "
                         f"{have / 1e9:.1f} GB available: fewer workers, or {fix}")


def simulate(scene, seed=0, *, index: int = 0, sweeps: bool = True, truth_rays: bool = False,
             progress: bool = False, prepared=None) -> Simulation:
    """Simulate one case of an operating-room scene.

    Parameters
    ----------
    scene : testbed.scene.Scene
        An ``operating_room`` scene with ``[[views]]``.
    seed : int or numpy.random.SeedSequence
        The seed (with ``index``, see :func:`case_seed`) or the case's own SeedSequence.
    index : int
        The case's index under ``seed``.
    sweeps : bool
        Simulate the calibration sweeps (False leaves them out of the observation: the
        judge then calibrates with the truth, see ``studies.oracles``).
    truth_rays : bool
        Put every pixel's true X-ray path into the truth (``arrays/rays_{view}``, 2 x 7 MB
        per 640 x 480 view; the datasets have them).
    progress : bool
        A progress bar over the stages.
    prepared : tuple or None
        This case's :func:`checked_world` when the caller has already made it (the world
        is then not built and checked again).

    Raises ``ValueError`` naming the scene, view or stage when the case cannot be simulated.
    """
    from tqdm import tqdm

    from testbed.fluoroscope import make_carm, render
    from testbed.operator import xray_clicks
    from testbed.robot import Robot
    from testbed.scene import require_scene
    from testbed.sweep import run_sweep

    require_scene(scene)
    if scene.scene.kind != "operating_room" or not scene.views:
        raise ValueError(f"scene {scene.scene.name!r} (kind {scene.scene.kind!r}): simulating a "
                         "case needs an operating_room scene with [[views]]")
    names = [v.name for v in scene.views]
    if len(set(names)) != len(names):
        raise ValueError(f"scene {scene.scene.name!r}: view names must be unique, got {names}")
    check_memory(scene)
    css = case_seed(seed, index)
    streams = case_streams(css)
    robot_ss, xray_ss = streams["robot"], streams["xray"]
    timings: dict[str, float] = {}
    obs = {g: {} for g in ("volumes", "images", "arrays", "meshes", "transforms", "points")}
    tru = {g: {} for g in obs}
    n_steps = 2 + len(scene.views) * (2 if sweeps else 1)
    bar = tqdm(total=n_steps, desc="simulate", unit="stage", disable=not progress,
               leave=False)

    def tick(stage, t0):
        timings[stage] = timings.get(stage, 0.0) + time.perf_counter() - t0
        bar.set_postfix_str(stage)
        bar.update(1)

    # 1. the world, and the check that every view and sweep pose can be taken
    t0 = time.perf_counter()
    given = scene
    scene, world, workspace = checked_world(scene, css) if prepared is None else prepared
    tick("world+workspace", t0)
    # 2. CT and the operator's clicks on it
    t0 = time.perf_counter()
    ctc = simulate_ct(scene, css, world=world)
    scene, world, ct, regions = ctc.scene, ctc.world, ctc.ct, ctc.clicks
    op_spec = scene.operator
    ph = world.phantom
    tru["transforms"]["ct2robot"] = world.ct2robot
    meshes = {"femur": ph.femur, "canal": ph.canal, "cancellous": ph.cancellous,
              "soft_tissue": ph.soft_tissue}
    meshes.update({f"pin_{k}": m for k, m in ph.pin_meshes.items()})
    tru["meshes"].update({k: m for k, m in meshes.items() if m is not None})
    for body in [*world.table, *world.instruments]:  # already in the robot frame
        if body.mesh is not None:
            tru["meshes"]["robot_" + file_key(body.name)] = body.mesh
    tru["points"]["pins_ct"] = {k: np.asarray(v, float) for k, v in ph.pins.items()}
    tru["points"]["pins_robot"] = {k: np.asarray(v, float) for k, v in world.pins_robot.items()}
    if ph.landmarks:
        tru["points"]["landmarks_ct"] = {k: np.asarray(v, float) for k, v in ph.landmarks.items()}
    z = np.asarray(ct.slice_z_mm, dtype=np.float64)
    dz = np.diff(z)
    uniform = bool(len(z) < 2 or np.ptp(dz) <= 1e-6)
    if uniform:
        voxel2ct = ct.voxel2ct
    else:  # one affine for the volume's header: the first slice and the mean spacing
        voxel2ct = np.eye(4)
        voxel2ct[0, 0] = voxel2ct[1, 1] = ct.pixel_mm
        voxel2ct[2, 2] = float(np.mean(dz))
        voxel2ct[:3, 3] = (*ct.origin_xy_mm, z[0])
    # stored (col, row, slice) = NIfTI (i, j, k); reglib.pipeline reads it back as
    # [slice, row, col]
    # whole HU within 12 bits (testbed.ct), stored as a CT image's int16 pixels: exact, and
    # half the bytes to write and compress
    data = np.asarray(ct.volume_hu).transpose(2, 1, 0).astype(np.int16, order="C")
    obs["volumes"]["ct"] = Volume(data, voxel2ct)
    obs["arrays"]["ct_slices"] = {
        "z_mm": z, "thickness_mm": np.asarray(ct.slice_thickness_mm, dtype=np.float64),
        "slice2ct": np.asarray(ct.slice2ct, dtype=np.float64), "uniform": np.array(uniform)}
    for region, cc in regions.items():
        obs["arrays"][f"ct_clicks_{file_key(region)}"] = cc.to_arrays()
    tick("ct", t0)
    xray_op_rng = ctc.xray_operator_rng

    # 3. per view: sweep, X-ray frame, clicks
    carms, frames, recorded = {}, {}, {}
    # where the femur is at each view ([patient] motion_mm / motion_deg; else where the pins
    # were digitised): the patient's bodies per view, the table and instruments staying
    poses = view_poses(scene, world.ct2robot, streams["motion"])
    robot_rngs = np.random.default_rng(robot_ss).spawn(len(scene.views))
    xray_rngs = np.random.default_rng(xray_ss).spawn(len(scene.views))
    op_rngs = xray_op_rng.spawn(len(scene.views))
    instruments = [b.name for b in world.instruments]
    # one robot holding one rod sweeps every view of the case: its imperfections (kinematic
    # offsets, the rod's mounting, its beads' placement) are drawn once, from a child of
    # the robot stream at a fixed key, and every move then draws its encoder error
    robot_gen = np.random.default_rng(keyed_seed(robot_ss, ROBOT_KEY))
    robot = Robot(scene.robot, rng=robot_gen) if sweeps else None
    try:
        for i, vspec in enumerate(scene.views):
            v = file_key(vspec.name)
            carm = make_carm(scene.fluoroscope, vspec, view_index=i)
            carms[vspec.name] = carm
            tru["transforms"][f"carm2robot_{v}"] = carm.carm2robot
            tru["transforms"][f"ct2robot_{v}"] = poses[i]
            bodies = view_bodies(world, poses[i])
            if sweeps:
                # the sweep sees the intensifier as it was during calibration: the patient's
                # frame (and the truth) as it is at the acquisition (their difference is the
                # distortion's drift, [fluoroscope] distortion_drift_mm)
                sweep_carm = make_carm(scene.fluoroscope, vspec, view_index=i, stage="calibration")
                t0 = time.perf_counter()
                # (the first child drew this view's own robot before the robot was shared)
                _, noise_rng = robot_rngs[i].spawn(2)
                rep_poses, true_poses = [], []
                frame_bar = tqdm(desc=f"sweep {vspec.name}", unit="frame", disable=not progress,
                                 leave=False)

                def record(k, n, robot=robot, rep=rep_poses, tr=true_poses, fb=frame_bar):
                    # after frame k is rendered: the robot is still at that frame's pose
                    rep.append(robot.reported_rod2robot.as_matrix())
                    tr.append(robot.true_rod2robot.as_matrix())
                    fb.total = n
                    fb.update(1)

                sweep = run_sweep(robot, sweep_carm, scene.fluoroscope, bodies=bodies,
                                  rng=noise_rng, progress=record)
                frame_bar.close()
                recorded[vspec.name] = sweep
                obs["images"][f"sweep_{v}"] = sweep.frames
                obs["arrays"][f"sweep_{v}"] = {
                    "plane": np.asarray(sweep.plane, dtype=np.int64),
                    "beads_reported": sweep.beads_reported,
                    "rod2robot_reported": np.array(rep_poses), "joints": sweep.joints,
                    "time_s": np.asarray(sweep.time_s, dtype=np.float64),
                    "bead_positions_mm": np.asarray(sweep.bead_positions_mm, dtype=np.float64)}
                tru["arrays"][f"sweep_truth_{v}"] = {"beads_true": sweep.beads_true,
                                                     "rod2robot_true": np.array(true_poses)}
                tick(f"sweep {vspec.name}", t0)
            t0 = time.perf_counter()
            try:
                frame = render(carm, bodies, fluoro=scene.fluoroscope, rng=xray_rngs[i])
            except ValueError as exc:
                raise ValueError(f"views[{i}] ({vspec.name!r}): {exc}") from None
            frames[vspec.name] = frame
            obs["images"][f"xray_{v}"] = frame.image_u8
            obs["arrays"][f"xray_fov_{v}"] = np.asarray(frame.fov, dtype=bool)
            tru["arrays"][f"xray_float_{v}"] = np.asarray(frame.image, dtype=np.float32)
            if truth_rays:
                o, d = carm.pixel_ray_map()
                tru["arrays"][f"rays_{v}"] = {"origins": o, "directions": d}
            clicks = xray_clicks(frame, femur_bodies=FEMUR_BODIES, instrument_bodies=instruments,
                                 spec=op_spec, rng=op_rngs[i], view=vspec.name)
            if not clicks.traces:
                raise ValueError(_no_trace_message(i, vspec, frame, scene)
                                 + placement_note(given, scene))
            obs["arrays"][f"xray_clicks_{v}"] = clicks.to_arrays()
            tick(f"xray {vspec.name}", t0)
        if robot is not None:
            # the pins located by the same robot, with its own error there: what the judge's
            # pin-based reference registration takes (studies.scoring.pin_reference)
            touched = {k: robot.digitize(p) for k, p in world.pins_robot.items()}
            tru["points"]["pins_robot_digitized"] = {k: v for k, v in touched.items()
                                                     if v is not None}
    finally:
        if robot is not None:
            robot.close()
    bar.close()

    obs_meta = {
        "views": [file_key(v.name) for v in scene.views],
        "view_regions": [getattr(v, "region", "") for v in scene.views],
        "regions": sorted(file_key(r) for r in regions),
        "image_size_px": [int(scene.fluoroscope.width_px), int(scene.fluoroscope.height_px)],
        # the video's nominal pixel at the intensifier's input (a device's specification,
        # as DICOM's imager pixel spacing: the same at every pose, no distortion in it)
        "xray_pixel_mm": float(scene.fluoroscope.pixel_mm),
        "ct_uniform_slices": uniform,
        "units": {"length": "mm", "angle": "rad", "pixel": "px (x, y) = (col, row)"},
        "sweeps": bool(sweeps),
    }
    truth_meta = {
        "workspace": ("not checked ([workspace] check = false)" if not scene.workspace.check
                      else f"checked: {len(workspace)} view(s), every sweep pose feasible"),
        "scene": scene.model_dump(mode="json"),
        "seed": {"entropy": int(css.entropy), "spawn_key": [int(k) for k in css.spawn_key]},
        "sweep_time_s": {k: float(s.duration_s) for k, s in recorded.items()},
        "dose_mrem": {k: float(s.dose_mrem) for k, s in recorded.items()},
    }
    return Simulation(
        observation=Observation(**obs, meta=obs_meta),
        truth=Truth(**tru, meta=truth_meta),
        scene=scene, world=world, carms=carms, frames=frames, sweeps=recorded,
        timings=timings)


def simulate_case(scene, seed=0, *, index: int = 0, sweeps: bool = True,
                  truth_rays: bool = False, progress: bool = False):
    """``(Observation, Truth)`` of one case: :func:`simulate` without the world objects."""
    return simulate(scene, seed, index=index, sweeps=sweeps, truth_rays=truth_rays,
                    progress=progress).pair
