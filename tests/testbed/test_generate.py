"""``testbed generate``: one small simulated case written and loaded back exactly."""

import json
import re

import numpy as np
import pytest

from testbed.scene import parse_scene

# a cheap operating room: one distal view of a small detector, a coarse uniform CT, a short
# sweep; the femur shape varies per case
SMALL = {
    "scene": {"name": "gen-test", "kind": "operating_room", "seed": 4},
    "patient": {"position_mm": [810.0, 225.0, 200.0], "rotation_deg": [90.0, 0.0, 0.0],
                "on_table": True},
    "phantom": {"shape_variation": 1.0, "segments": 32},
    "ct": {"pixel_mm": 2.0, "schedule": "uniform", "coarse_spacing_mm": 10.0},
    "fluoroscope": {"width_px": 160, "height_px": 120, "pixel_mm": 2.0},
    "views": [{"name": "distal_ap", "region": "distal", "isocenter_mm": [805.0, 170.0, 200.0],
               "source_to_isocenter_mm": 650.0}],
    "robot": {"sweep": {"rows_per_plane": 3}},
}


def _same(a, b, what):
    a, b = np.asarray(a), np.asarray(b)
    assert a.dtype == b.dtype, what
    assert a.shape == b.shape, what
    assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), what


def _rigid_matrix(t):
    return t.as_matrix() if hasattr(t, "as_matrix") else np.asarray(t)


@pytest.mark.slow
def test_generated_case_round_trips_exactly_and_splits_truth(tmp_path):
    from testbed.dataset import list_cases, load
    from testbed.generate import ENTRY_DOC, case_seed, generate_command, simulate_entries

    scene = parse_scene(SMALL)
    out = tmp_path / "ds"
    dirs = generate_command(scene, scene_path="small.toml", cases=1, out=out, seed=3,
                            progress=False)
    assert list_cases(out) == dirs and [d.name for d in dirs] == ["case_0000"]
    summary = json.loads((out / "dataset.json").read_text())
    assert summary["seed"] == 3 and summary["cases"] == ["case_0000"]

    obs, truth = load(dirs[0])
    # the same seed simulates the same case again (deterministic), in memory
    case, truth_keys, _ = simulate_entries(scene, case_seed(3, 0, 1))

    # meta: format, the resolved scene of the case (its own femur shape seed) and the seed
    meta = obs.meta
    assert meta == truth.meta
    assert meta["scene"] == case["meta"]["scene"]
    assert meta["seed"] == {"entropy": 3, "spawn_key": [0]}
    assert meta["case_index"] == 0 and meta["dataset_seed"] == 3
    assert meta["scene"]["phantom"]["shape_seed"] != scene.phantom.shape_seed

    # roles: nothing of the truth in the observation
    roles = {"observation": obs, "truth": truth}
    for group in ("volumes", "images", "arrays", "meshes", "transforms", "points"):
        for name in case[group]:
            key = f"{group}/{name}"
            role = "truth" if key in truth_keys else "observation"
            other = "observation" if role == "truth" else "truth"
            assert name in getattr(roles[role], group), key
            assert name not in getattr(roles[other], group), key
    obs_keys = {f"{g}/{n}" for g in ("volumes", "images", "arrays", "meshes", "transforms",
                                     "points") for n in getattr(obs, g)}
    assert obs_keys == {"volumes/ct", "arrays/ct_slices", "images/xray_distal_ap",
                        "arrays/xray_fov_distal_ap", "images/sweep_distal_ap",
                        "arrays/sweep_distal_ap"}
    assert not obs.meshes and not obs.transforms and not obs.points
    # every entry is documented with the role it has
    def documented_role(key):
        # the most specific documented pattern ({view}, {body} stand for any name)
        hits = [(len(pat), r) for pat, (r, _) in ENTRY_DOC.items()
                if re.fullmatch(re.sub(r"\\{\w+\\}", ".+", re.escape(pat)), key)]
        assert hits, f"{key} is not documented in ENTRY_DOC"
        return max(hits)[1]

    for key in obs_keys:
        assert documented_role(key) == "observation", key
    for key in truth_keys:
        assert documented_role(key) == "truth", key

    # every array and transform round-trips exactly
    v0, v1 = case["volumes"]["ct"], obs.volumes["ct"]
    _same(v1.data, v0.data, "ct data")
    _same(v1.voxel2ct, v0.voxel2ct, "voxel2ct")
    for name, img in case["images"].items():
        _same(obs.images[name], img, name)
    for name, arr in case["arrays"].items():
        got = (obs if f"arrays/{name}" not in truth_keys else truth).arrays[name]
        if isinstance(arr, dict):
            assert set(got) == set(arr), name
            for k in arr:
                _same(got[k], arr[k], f"{name}[{k}]")
        else:
            _same(got, arr, name)
    for name, m in case["meshes"].items():
        _same(truth.meshes[name].vertices, np.asarray(m.vertices, np.float64), name)
        assert np.array_equal(truth.meshes[name].faces, m.faces), name
    for name, t in case["transforms"].items():
        _same(_rigid_matrix(truth.transforms[name]), _rigid_matrix(t), name)
    for name, pts in case["points"].items():
        assert set(truth.points[name]) == set(pts), name
        for k in pts:
            _same(np.asarray(truth.points[name][k]), np.asarray(pts[k]), f"{name}[{k}]")

    # the content is what it claims: truth is consistent with itself
    t = truth.transforms["ct2robot"]
    for k, p in truth.points["pins_ct"].items():
        assert np.allclose(t.apply(np.asarray(p)), truth.points["pins_robot"][k], atol=1e-9)
    sw, swt = obs.arrays["sweep_distal_ap"], truth.arrays["sweep_truth_distal_ap"]
    F = len(obs.images["sweep_distal_ap"])
    assert sw["rod2robot_reported"].shape == (F, 4, 4) == swt["rod2robot_true"].shape
    on = sw["plane"] >= 0
    assert on.any() and np.all(np.isnan(sw["beads_reported"][~on]))
    # reported and true rod poses differ by the robot's small errors only (< 1 mm)
    d = np.linalg.norm(sw["beads_reported"][on] - swt["beads_true"][on], axis=-1)
    assert 0 < d.max() < 1.0
    rays = truth.arrays["rays_distal_ap"]
    assert rays["origins"].shape == (120, 160, 3)
    assert np.allclose(np.linalg.norm(rays["directions"], axis=-1), 1.0)
    # voxel (i, j, k) = (col, row, slice): the affine puts slice k at its z
    sl = obs.arrays["ct_slices"]
    assert bool(sl["uniform"])
    k = np.arange(len(sl["z_mm"]))
    zk = (v1.voxel2ct @ np.column_stack([0 * k, 0 * k, k, 1 + 0 * k]).T)[2]
    assert np.allclose(zk, sl["z_mm"])
    assert v1.data.shape[2] == len(sl["z_mm"])

    # a rerun keeps the complete case (resume) and bad input is refused clearly
    mtime = (dirs[0] / "case.json").stat().st_mtime_ns
    generate_command(scene, scene_path="small.toml", cases=1, out=out, seed=3, progress=False)
    assert (dirs[0] / "case.json").stat().st_mtime_ns == mtime
    with pytest.raises(ValueError, match="--cases"):
        generate_command(scene, scene_path="x", cases=0, out=out, seed=3, progress=False)


def test_case_seeds_and_shapes_differ_per_case():
    from testbed.generate import _case_scene, case_seed

    scene = parse_scene(SMALL)
    a, b = case_seed(7, 0, 2), case_seed(7, 1, 2)
    assert (a.entropy, a.spawn_key, b.spawn_key) == (7, (0,), (1,))
    sa = _case_scene(scene, a.spawn(5)[0]).phantom.shape_seed
    sb = _case_scene(scene, b.spawn(5)[0]).phantom.shape_seed
    assert sa != sb
    with pytest.raises(ValueError, match="case index"):
        case_seed(7, 2, 2)
