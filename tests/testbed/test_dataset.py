"""Dataset format: a small seeded case written and read back round-trips every array,
image, mesh, transform and point exactly; bad cases fail with errors that name the file."""

from __future__ import annotations

import json

import nibabel as nib
import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from reglib.geometry import RigidTransform
from testbed.dataset import (
    FORMAT_VERSION,
    Observation,
    Truth,
    Volume,
    list_cases,
    load,
    load_case,
    write_case,
)

TRUTH = ["arrays/xray_float", "arrays/raymap_view0", "meshes/femur", "transforms/ct2robot",
         "points/pins_ct", "points/surface_samples"]


def small_case(seed: int = 0) -> dict:
    """A seeded case with one entry of every kind (values chosen to exercise all bits)."""
    rng = np.random.default_rng(seed)
    voxel2ct = np.diag([0.7 + rng.random() * 1e-3, 0.7, 1.25, 1.0])
    voxel2ct[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) * 0.1).as_matrix() @ \
        voxel2ct[:3, :3]
    voxel2ct[:3, 3] = rng.normal(size=3) * 100
    xray_float = rng.random((2, 12, 10), dtype=np.float32)
    mesh = trimesh.creation.icosphere(subdivisions=1, radius=20.0)
    verts = mesh.vertices + rng.normal(size=mesh.vertices.shape) * 1e-3
    dirs = rng.normal(size=(12, 10, 3))
    return {
        "meta": {"scene": "femur-basic", "seed": seed, "views": [0, 1], "note": "tiny case"},
        "volumes": {"ct": Volume(rng.integers(-1000, 2000, (16, 16, 8)).astype(np.int16),
                                 voxel2ct),
                    "ct_float": Volume(rng.normal(size=(16, 16, 8)).astype(np.float32),
                                       voxel2ct)},
        "images": {"xray": np.round(xray_float * 255).astype(np.uint8),
                   "sweep_view0": rng.integers(0, 256, (3, 12, 10), dtype=np.uint8),
                   "single": rng.integers(0, 256, (5, 7), dtype=np.uint8)},
        "arrays": {"xray_float": xray_float,
                   "rod2robot_reported_view0": np.stack(
                       [RigidTransform.from_rotvec(rng.normal(size=3), rng.normal(size=3) * 50)
                        .as_matrix() for _ in range(3)]),
                   "raymap_view0": {"origins": rng.normal(size=(12, 10, 3)) * 1000,
                                    "directions": dirs / np.linalg.norm(dirs, axis=-1,
                                                                        keepdims=True)},
                   "flags": rng.random(5) > 0.5},
        "meshes": {"femur": trimesh.Trimesh(verts, mesh.faces, process=False)},
        "transforms": {"ct2robot": RigidTransform.from_rotvec(rng.normal(size=3),
                                                              rng.normal(size=3) * 300),
                       "carm2robot_view0": RigidTransform.from_rotvec(
                           rng.normal(size=3), rng.normal(size=3) * 300).as_matrix()},
        "points": {"pins_ct": {p: rng.normal(size=3) * 50
                               for p in ("proximal", "distal_1", "distal_2")},
                   "surface_samples": rng.normal(size=(4, 3))},
    }


def _same(a, b) -> bool:
    """Bitwise equality with the same dtype and shape."""
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def test_case_round_trips_exactly(tmp_path):
    case = small_case(3)
    write_case(tmp_path / "case_0000", case, truth=TRUTH)
    back = load_case(tmp_path / "case_0000")
    assert back["meta"] == case["meta"]
    for name, vol in case["volumes"].items():
        assert _same(back["volumes"][name].data, vol.data)
        assert _same(back["volumes"][name].voxel2ct, vol.voxel2ct)
    for name, img in case["images"].items():
        assert _same(back["images"][name], img), name
    for name, arr in case["arrays"].items():
        if isinstance(arr, dict):
            assert back["arrays"][name].keys() == arr.keys()
            assert all(_same(back["arrays"][name][k], arr[k]) for k in arr)
        else:
            assert _same(back["arrays"][name], arr), name
    m, m0 = back["meshes"]["femur"], case["meshes"]["femur"]
    assert _same(m.vertices, m0.vertices)
    assert np.array_equal(m.faces, m0.faces)
    for name, T in case["transforms"].items():
        T = T.as_matrix() if isinstance(T, RigidTransform) else T
        assert isinstance(back["transforms"][name], RigidTransform)
        assert _same(back["transforms"][name].as_matrix(), T)
    for p, x in case["points"]["pins_ct"].items():
        assert _same(back["points"]["pins_ct"][p], x)
    assert _same(back["points"]["surface_samples"], case["points"]["surface_samples"])
    # the NIfTI file is a valid volume on its own, with the affine in its header
    img = nib.load(tmp_path / "case_0000" / "volumes" / "ct.nii.gz")
    np.testing.assert_allclose(img.affine, case["volumes"]["ct"].voxel2ct, atol=1e-4)
    assert img.header.get_sform(coded=True)[1] == 1  # scanner
    # another library reads the PNG frames identically
    import cv2
    frame = cv2.imread(str(tmp_path / "case_0000" / "images" / "xray" / "0001.png"),
                       cv2.IMREAD_UNCHANGED)
    assert _same(frame, case["images"]["xray"][1])


def test_load_splits_observation_and_truth(tmp_path):
    case = small_case(4)
    write_case(tmp_path / "c", case, truth=TRUTH)
    obs, truth = load(tmp_path / "c" / "case.json")
    assert isinstance(obs, Observation) and isinstance(truth, Truth)
    assert set(obs.volumes) == {"ct", "ct_float"} and not truth.volumes
    assert set(obs.images) == {"xray", "sweep_view0", "single"}
    assert set(obs.arrays) == {"rod2robot_reported_view0", "flags"}
    assert set(truth.arrays) == {"xray_float", "raymap_view0"}
    assert set(truth.meshes) == {"femur"} and not obs.meshes
    assert set(truth.transforms) == {"ct2robot"}
    assert set(obs.transforms) == {"carm2robot_view0"}
    assert set(truth.points) == {"pins_ct", "surface_samples"} and not obs.points
    assert obs.meta == truth.meta == case["meta"]
    assert _same(truth.arrays["xray_float"], case["arrays"]["xray_float"])
    assert list_cases(tmp_path) == [tmp_path / "c"]


def test_bad_files_and_versions_are_named(tmp_path):
    case_dir = tmp_path / "case_0001"
    write_case(case_dir, small_case(5), truth=TRUTH)
    doc = json.loads((case_dir / "case.json").read_text())

    doc2 = {**doc, "format_version": FORMAT_VERSION + 1}
    (case_dir / "case.json").write_text(json.dumps(doc2))
    with pytest.raises(ValueError, match=r"case\.json: format_version 2 is not supported"):
        load_case(case_dir)
    (case_dir / "case.json").write_text(json.dumps(doc))

    (case_dir / "images" / "sweep_view0" / "0002.png").unlink()
    with pytest.raises(FileNotFoundError, match=r"sweep_view0/0002\.png: missing"):
        load(case_dir)

    write_case(case_dir, small_case(5), truth=TRUTH, overwrite=True)
    arr = case_dir / "arrays" / "xray_float.npy"
    raw = bytearray(arr.read_bytes())
    raw[-1] ^= 1
    arr.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match=r"xray_float\.npy: SHA-256 differs"):
        load_case(case_dir)

    with pytest.raises(FileNotFoundError, match=r"nowhere/case\.json: missing"):
        load_case(tmp_path / "nowhere")
    with pytest.raises(FileExistsError, match="case exists"):
        write_case(case_dir, small_case(5))


def test_bad_entries_are_refused_before_writing(tmp_path):
    case = small_case(6)
    with pytest.raises(ValueError, match=r"images/xray: expected a uint8"):
        write_case(tmp_path / "a", {**case, "images": {"xray": case["arrays"]["xray_float"]}})
    with pytest.raises(ValueError, match=r"truth: entries \['arrays/nope'\]"):
        write_case(tmp_path / "b", case, truth=["arrays/nope"])
    bad_T = np.eye(4)
    bad_T[0, 0] = 2.0
    with pytest.raises(ValueError, match=r"transforms/bad: not a rigid transform"):
        write_case(tmp_path / "c", {"transforms": {"bad": bad_T}})
    with pytest.raises(ValueError, match=r"Volume.data: expected an \(I, J, K\) array"):
        Volume(np.zeros((4, 4)), np.eye(4))
    with pytest.raises(ValueError, match="unknown keys"):
        write_case(tmp_path / "d", {"frames": {}})
    assert not any(tmp_path.iterdir())  # nothing half-written is left behind
