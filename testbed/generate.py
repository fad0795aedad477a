"""``testbed generate``: a synthetic dataset with perfect ground truth, case by case.

Case ``i`` of a dataset of seed ``S`` is :func:`testbed.simulate.simulate` of the scene with
the case seed ``(S, i)`` (child ``i`` of ``numpy.random.SeedSequence(S)``): the same case as
``testbed run --seed S`` for ``i = 0``, and as a study's case of that seed. It is written with
:func:`testbed.dataset.write_case` into ``out/case_0000``, ``out/case_0001``, ...; an
existing complete case folder is kept (rerunning the command resumes), and a folder that
holds a dataset of another scene, seed or format is refused. The entries of a case, their
roles (observation / truth), units and frames are listed in :data:`ENTRY_DOC` and in
``docs/dataset-format.md`` (section "What `testbed generate` writes").

The observation holds everything reglib's one call needs (``reglib.estimate``): the CT and
its slice geometry, the operator's clicks on CT slices and X-ray frames, the X-ray frames,
the calibration sweeps with the robot-reported rod and bead positions. Only the simulator
runs here: the dataset holds no estimate of reglib's.
"""

from __future__ import annotations

import hashlib
import json
import re
import shutil
import sys
from pathlib import Path

import numpy as np

__all__ = ["ENTRY_DOC", "GENERATOR_VERSION", "case_entries", "case_seed", "generate_command",
           "scene_digest"]

#: the hidden folder of a case being written (testbed.dataset.write_case: mkdtemp with
#: the prefix ".case_NNNN.")
_WRITING = re.compile(r"\.case_\d{4,}\.[A-Za-z0-9_]+")
#: what the generator writes: 3 since 2026-11-26 (the truth's points/pins_robot_digitized),
#: 4 since its seventh session (the scene file's path in the truth's meta only, the
#: patient's placement drawn per case where the scene asks), 5 since its tenth (the CT in
#: whole HU, stored as int16), 6 since its twenty-third (the case's index and the
#: dataset's seed in the truth's meta only: with them a method simulated the case again and
#: scored 0 mm); a dataset resumed by another version is refused, so its cases are never
#: mixed
GENERATOR_VERSION = 6

#: entry name pattern -> (role, description); ``{view}`` is a view's name, ``{region}`` a CT
#: region's (``proximal``, ``distal``).
ENTRY_DOC = {
    "volumes/ct": ("observation", "CT volume in whole HU (int16), data[i, j, k] = (column, row, "
                   "slice), NIfTI order; reglib reads it as [slice, row, col] after "
                   "transposing; voxel2ct maps (i, j, k, 1) to ct mm (exact only when the "
                   "slices are equally spaced, see arrays/ct_slices)"),
    "arrays/ct_slices": ("observation", "npz: z_mm (K,) slice positions along ct z, "
                         "thickness_mm (K,), slice2ct (K, 4, 4) maps (col, row, 0, 1) of "
                         "slice k to ct mm (authoritative), uniform () bool"),
    "arrays/ct_clicks_{region}": ("observation", "npz, the operator's work on a CT region: "
                                  "slices (S,) the slices to contour, clicks_xy (P, 2) px "
                                  "(x, y) = (col, row), slice (P,) and contour (P,) the slice "
                                  "and the cross-section of each click; slices without clicks "
                                  "reuse the nearest clicked slice's, except between clicked "
                                  "slices of different counts: the lower one's"),
    "images/xray_{view}": ("observation", "the X-ray frame of the view, 8-bit video (H, W)"),
    "arrays/xray_fov_{view}": ("observation", "(H, W) bool, the circular field of view"),
    "arrays/xray_clicks_{view}": ("observation", "npz, the operator's traces on the frame: "
                                  "clicks_xy (P, 2) px, trace (P,) the trace of each click, "
                                  "external (T,) bool (the bone's external outline), closed "
                                  "(T,) bool"),
    "arrays/xray_float_{view}": ("truth", "(H, W) float32 detected intensity, linear, "
                                 "relative to the unattenuated beam (quantum noise, blur, "
                                 "scatter, glare, vignetting included), before the video's "
                                 "logarithmic amplifier, camera noise and 8-bit quantisation"),
    "images/sweep_{view}": ("observation", "(F, H, W) 8-bit frames of the calibration sweep, "
                            "one after each rod move"),
    "arrays/sweep_{view}": ("observation", "npz: plane (F,) int plane code (-1 reference, 0 "
                            "near, 1 far, 2 validation), beads_reported (F, n, 3) robot mm (NaN "
                            "on reference frames), rod2robot_reported (F, 4, 4) the "
                            "robot-reported rod pose, joints (F, 5) rad/mm, time_s (F,), "
                            "bead_positions_mm (n,)"),
    "arrays/sweep_truth_{view}": ("truth", "npz: beads_true (F, n, 3) robot mm, "
                                  "rod2robot_true (F, 4, 4) the true rod pose"),
    "arrays/rays_{view}": ("truth", "npz: origins (H, W, 3), directions (H, W, 3) unit, robot "
                           "frame mm: the true X-ray path of every pixel (distortion "
                           "included)"),
    "transforms/carm2robot_{view}": ("truth", "C-arm frame (source at the origin, +z the "
                                     "beam) -> robot frame"),
    "transforms/ct2robot": ("truth", "ct -> robot: x_robot = R x_ct + t (the registration's "
                            "answer; the femur's pose when the pins were digitised)"),
    "transforms/ct2robot_{view}": ("truth", "ct -> robot while the view's sweep and X-ray "
                                   "frame were taken: ct2robot unless [patient] motion_mm or "
                                   "motion_deg moves the femur between views"),
    "meshes/{body}": ("truth", "phantom bodies in the ct frame, mm: femur, canal, cancellous, "
                      "soft_tissue, pin_<name>"),
    "meshes/robot_{body}": ("truth", "the table (foam, top) and the instruments' meshes in the "
                            "robot frame, mm"),
    "points/pins_ct": ("truth", "pin centres, ct mm, by name"),
    "points/pins_robot": ("truth", "pin centres, robot mm, by name"),
    "points/pins_robot_digitized": ("truth", "where the case's robot reported each pin its "
                                    "rod's first bead touched (its own absolute error there), "
                                    "robot mm, by name; a pin it cannot reach left out"),
    "points/landmarks_ct": ("truth", "anatomical landmarks of the femur, ct mm, by name"),
}


def case_seed(seed: int, index: int, cases: int | None = None) -> np.random.SeedSequence:
    """The seed of case ``index``: child ``index`` of ``SeedSequence(seed)`` (the same for any
    number of cases; ``cases``, when given, is checked to exceed ``index``)."""
    from testbed.simulate import case_seed as _case_seed

    if cases is not None and not 0 <= index < cases:
        raise ValueError(f"case index {index}: expected 0 <= index < cases = {cases}")
    return _case_seed(seed, index)


def scene_digest(scene) -> str:
    """SHA-256 of the resolved scene (its JSON dump), to recognise a dataset's scene."""
    text = json.dumps(scene.model_dump(mode="json"), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def case_entries(sim) -> tuple[dict, list[str]]:
    """A :class:`testbed.simulate.Simulation` as the ``case`` dict of
    :func:`testbed.dataset.write_case` and its list of truth entries."""
    obs, tru = sim.observation, sim.truth
    groups = ("volumes", "images", "arrays", "meshes", "transforms", "points")
    case = {"meta": {**obs.meta, "truth": tru.meta,
                     "generator": "testbed generate", "generator_version": GENERATOR_VERSION,
                     "entries": {k: {"role": r, "description": d}
                                 for k, (r, d) in ENTRY_DOC.items()}}}
    truth = []
    for g in groups:
        o, t = dict(getattr(obs, g)), dict(getattr(tru, g))
        both = sorted(set(o) & set(t))
        if both:
            raise ValueError(f"{g}: entries {both} are both observation and truth")
        case[g] = {**o, **t}
        truth += [f"{g}/{k}" for k in t]
    return case, truth


def _check_index(old, index: Path) -> None:
    """ValueError naming ``index`` (a ``dataset.json`` being resumed) and its field when its
    case list or checksum table has another shape than ``testbed generate`` writes: a
    string of case names was read as that many cases, a number failed with an internal
    error (a review)."""
    if not isinstance(old, dict):
        raise ValueError(f"{index}: expected a JSON object, got {type(old).__name__}; move the "
                         "folder away or choose another --out")
    cases = old.get("cases", [])
    if not isinstance(cases, list) or not all(isinstance(c, str) for c in cases):
        raise ValueError(f"{index}: 'cases' must be a list of case folder names, got "
                         f"{cases!r:.80}; move the folder away or choose another --out")
    hashes = old.get("case_json_sha256", {})
    if not isinstance(hashes, dict) or not all(
            isinstance(k, str) and isinstance(v, str) for k, v in hashes.items()):
        raise ValueError(f"{index}: 'case_json_sha256' must map case folder names to SHA-256 "
                         f"digests, got {hashes!r:.80}; move the folder away or choose another "
                         "--out")


def generate_command(scene, *, scene_path, cases: int, out, seed: int | None = None,
                     progress: bool = True, on_case=None) -> list[Path]:
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
        there are kept (a rerun resumes); ``out/dataset.json`` lists the cases with the
        SHA-256 of each ``case.json``, the scene's digest, the seed and the versions. A
        folder holding a dataset of another scene, seed or version is refused
        (``ValueError``), as is a non-empty folder without ``dataset.json``.
    seed : int, optional
        The dataset's seed (default: the scene's); case ``i`` is simulated from the case seed
        ``(seed, i)`` (:func:`testbed.simulate.case_seed`).
    progress : bool
        A tqdm progress bar over the cases.
    on_case : callable or None
        Called as ``on_case(i, sim)`` with each case this run simulates (its
        ``testbed.simulate.Simulation``), before the case is written (the command line
        takes case 0's warnings from it).

    Returns
    -------
    list of Path
        The case folders.
    """
    from tqdm import tqdm

    from testbed.dataset import CASE_FILE, FORMAT_VERSION, case_problem, write_case
    from testbed.scene import require_scene
    from testbed.simulate import simulate

    require_scene(scene)        # before dataset.json is written
    if isinstance(cases, bool) or not isinstance(cases, int | np.integer) or cases < 1:
        raise ValueError(f"--cases: expected an integer >= 1, got {cases!r}")
    seed = scene.scene.seed if seed is None else seed
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"--seed: expected an integer >= 0, got {seed!r}")
    if scene.scene.kind != "operating_room" or not scene.views:
        raise ValueError(f"scene {scene.scene.name!r} (kind {scene.scene.kind!r}): testbed "
                         "generate needs an operating_room scene with [[views]], e.g. "
                         "experiment2")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out}: exists and is not a folder")
    digest = scene_digest(scene)
    summary = {"generator": "testbed generate", "generator_version": GENERATOR_VERSION,
               "format_version": FORMAT_VERSION, "scene_path": str(scene_path),
               "scene_name": scene.scene.name, "scene_sha256": digest, "seed": int(seed)}
    index = out / "dataset.json"
    old = {}
    if index.is_file():
        try:
            old = json.loads(index.read_text())
        except (OSError, ValueError) as exc:
            raise ValueError(f"{index}: unreadable dataset index ({exc}); move the folder away "
                             "or choose another --out") from None
        _check_index(old, index)
        for key, what in (("scene_sha256", "scene"), ("seed", "seed"),
                          ("generator_version", "generator version"),
                          ("format_version", "format version")):
            if old.get(key) != summary[key]:
                held = [f"{key} {old.get(key)!r}"] + [
                    f"{k} {old.get(f)!r}" for k, f in (("scene", "scene_name"), ("seed", "seed"))
                    if f != key]
                raise ValueError(
                    f"--out {out}: holds a dataset of another {what} ({', '.join(held)}); "
                    f"this run has {key} {summary[key]!r}: choose another folder (cases of "
                    "different scenes or seeds are never mixed)")
    elif out.is_dir() and any(p.name != f".{index.name}.writing" for p in out.iterdir()):
        # (a run killed within its first index write leaves only that temporary file)
        raise ValueError(f"--out {out}: the folder is not empty and holds no dataset.json; "
                         "choose a new or empty folder")
    # an impossible acquisition is refused before anything is written (each case is checked
    # again when it is simulated: its femur may differ)
    from testbed.simulate import checked_world

    n_all = max(int(cases), len(old.get("cases", [])))
    dirs = [out / f"case_{i:04d}" for i in range(n_all)]
    # a case's place taken by something that is no case folder: said before any simulation
    # (a review's plain file 'case_0000' was found after 8 s of simulating)
    for d in dirs[:cases]:
        if d.exists() and not (d / CASE_FILE).is_file():
            raise ValueError(f"--out {out}: {d.name} exists and is not a case folder (no "
                             f"{CASE_FILE}); move it away, or choose another folder")
    first = checked_world(scene, case_seed(int(seed), 0))      # case 0 reuses it
    out.mkdir(parents=True, exist_ok=True)
    # a case is written in a hidden folder and renamed into place when complete
    # (testbed.dataset.write_case); a run killed meanwhile (SIGKILL) left that folder, one
    # per interruption, which no rerun removed (a review: 9.5 MB and 1.1 MB)
    for leftover in out.glob(".case_*"):
        if leftover.is_dir() and _WRITING.fullmatch(leftover.name):
            shutil.rmtree(leftover, ignore_errors=True)
    hashes = dict(old.get("case_json_sha256", {}))

    def write_index():   # whole or not at all: a kill within the write left an unreadable
        tmp = index.with_name(f".{index.name}.writing")     # index (a review)
        tmp.write_text(json.dumps({**summary, "cases": [d.name for d in dirs],
                                   "case_json_sha256": hashes}, indent=2))
        tmp.replace(index)

    fresh = not index.is_file()   # this run's own index: taken back if its first case fails
    write_index()
    for i in tqdm(range(cases), desc="cases", disable=not progress, unit="case"):
        case_dir = dirs[i]
        if (case_dir / CASE_FILE).is_file() and case_dir.name in hashes:
            problem = case_problem(case_dir)
            if problem is None:
                continue
            # the case's seed gives the same case again: a damaged one is made anew
            print(f"testbed generate: {case_dir.name} is damaged ({problem}); simulating it "
                  "again", file=sys.stderr)
            hashes.pop(case_dir.name)
            write_index()
        try:
            sim = simulate(scene, case_seed(int(seed), i), truth_rays=True, progress=progress,
                           prepared=first if i == 0 else None)
        except ValueError as exc:   # a case of its own femur or placement: say which (a review)
            if not hashes and fresh:
                # no case written and the index this run's own: taken back, so that the
                # retry with the scene corrected is not "a dataset of another scene" (a
                # review, h93); while a run is in its first case its index stays, and a
                # second run of another scene or seed is refused (h94)
                index.unlink(missing_ok=True)
            if type(exc).__name__ not in ("ValueError", "SceneError", "WorkspaceError"):
                raise
            done = f"; the {i} before it are written" if i else ""
            raise type(exc)(f"{exc}; in {case_dir.name} (case {i} of seed {seed}{done})") \
                from None
        if on_case is not None:
            on_case(i, sim)
        case, truth = case_entries(sim)
        case["meta"].update(timings_s=sim.timings)
        # the seed that makes the case again is truth, as the case's own seed is (in the
        # observation's meta a method simulated the case from them and scored 0 mm, a review)
        case["meta"]["truth"].update(case_index=i, dataset_seed=int(seed))
        # the scene file holds the patient's placement, i.e. the true ct2robot: truth only
        # (it was in the observation's meta: a method that parsed it scored 0 mm)
        case["meta"]["truth"]["scene_path"] = str(scene_path)
        write_case(case_dir, case, truth=truth, overwrite=True)
        hashes[case_dir.name] = hashlib.sha256((case_dir / CASE_FILE).read_bytes()).hexdigest()
        write_index()
    return dirs[:cases]
