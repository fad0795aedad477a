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


def test_npz_members_deflate_only_when_it_pays(tmp_path):
    """Noise-like float64 (the ray directions' kind) is stored as it is, regular data is
    deflated; np.load reads both back exactly."""
    import zipfile

    from testbed import dataset

    rng = np.random.default_rng(0)
    arrs = {"noise": rng.normal(size=(400, 600)), "flat": np.zeros((400, 600)),
            "small": rng.normal(size=10)}
    path = tmp_path / "x.npz"
    dataset._savez_fast(path, arrs)
    kinds = {i.filename: i.compress_type for i in zipfile.ZipFile(path).infolist()}
    assert kinds == {"noise.npy": zipfile.ZIP_STORED, "flat.npy": zipfile.ZIP_DEFLATED,
                     "small.npy": zipfile.ZIP_DEFLATED}
    with np.load(path) as z:
        for k, a in arrs.items():
            np.testing.assert_array_equal(z[k], a)
    # no write time inside: the same arrays give the same bytes (a stored member carried
    # the time it was written, so a case simulated again from its seed differed)
    assert {i.date_time for i in zipfile.ZipFile(path).infolist()} == {(1980, 1, 1, 0, 0, 0)}
    again = tmp_path / "y.npz"
    dataset._savez_fast(again, arrs)
    assert again.read_bytes() == path.read_bytes()


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

    # a newer version asks for a newer testbed, an older one for the dataset made again
    for version, advice in ((FORMAT_VERSION + 1, "update the testbed"),
                            (FORMAT_VERSION - 1, "generate the dataset again")):
        (case_dir / "case.json").write_text(json.dumps({**doc, "format_version": version}))
        with pytest.raises(ValueError, match=rf"case\.json: format_version {version} is not "
                                             rf"supported .*{advice}"):
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


def _generated(tmp_path, seed=0):
    """A case as testbed generate leaves it: generator meta, truth meta, a dataset index
    holding the SHA-256 of its case.json."""
    import hashlib

    root = tmp_path / "ds"
    case = small_case(seed)
    case["meta"] = {"generator": "testbed generate", "views": ["view0"],
                    "truth": {"scene": {"name": "s"}, "seed": {"entropy": 1}}}
    truth = TRUTH + [f"{g}/{n}" for g in ("transforms", "meshes", "points")
                     for n in case.get(g, {}) if f"{g}/{n}" not in TRUTH]
    write_case(root / "case_0000", case, truth=truth)
    digest = hashlib.sha256((root / "case_0000" / "case.json").read_bytes()).hexdigest()
    (root / "dataset.json").write_text(json.dumps({"case_json_sha256": {"case_0000": digest}}))
    return root / "case_0000"


def test_generated_case_loads_and_keeps_truth_meta_out_of_the_observation(tmp_path):
    case_dir = _generated(tmp_path)
    obs, truth = load(case_dir)
    assert "truth" not in obs.meta and obs.meta["views"] == ["view0"]
    assert truth.meta["truth"]["scene"] == {"name": "s"}
    assert "ct2robot" in truth.transforms and not obs.transforms


def test_tampered_cases_are_refused_naming_the_file(tmp_path):
    case_dir = _generated(tmp_path)
    doc_path = case_dir / "case.json"
    doc = json.loads(doc_path.read_text())

    def put(d):
        doc_path.write_text(json.dumps(d))

    # an edit of case.json itself (here its meta) is seen through the dataset's index
    put({**doc, "meta": {**doc["meta"], "views": ["other"]}})
    with pytest.raises(ValueError, match=r"case\.json: SHA-256 differs from .*dataset\.json"):
        load(case_dir)
    # a truth entry flipped to observation: refused even without the index check
    flipped = json.loads(json.dumps(doc))
    flipped["entries"]["transforms/ct2robot"]["role"] = "observation"
    put(flipped)
    with pytest.raises(ValueError, match="ground truth but is marked 'observation'"):
        load(case_dir, verify=False)
    # a file's checksum deleted, and the file replaced by NaNs: refused, naming the file
    npy = next(k for k, r in doc["entries"].items() if r["files"][0].endswith(".npy"))
    rel = doc["entries"][npy]["files"][0]
    np.save(case_dir / rel, np.full((2, 12, 10), np.nan, dtype=np.float32))
    unhashed = json.loads(json.dumps(doc))
    del unhashed["sha256"][rel]
    put(unhashed)
    with pytest.raises(ValueError, match=rf"{rel}: no SHA-256"):
        load(case_dir, verify=False)
    # the dataset index without this case
    put(doc)
    (case_dir.parent / "dataset.json").write_text(json.dumps({"case_json_sha256": {}}))
    with pytest.raises(ValueError, match="holds no checksum of this case"):
        load(case_dir)
    # an index that is not an object (a review: a list was said to lack the case's checksum)
    (case_dir.parent / "dataset.json").write_text("[1, 2, 3]")
    with pytest.raises(ValueError, match=r"dataset\.json: expected a JSON object .* got a list"):
        load(case_dir)


def _mutations(doc):
    """(name, function editing a copy of case.json's dict) for structural tampering."""
    k_img = next(k for k in doc["entries"] if k.startswith("images/"))
    k_npy = next(k for k, r in doc["entries"].items() if r["files"][0].endswith(".npy"))
    k_vol = next(k for k in doc["entries"] if k.startswith("volumes/"))
    return [
        ("entries not a table", lambda d: d.__setitem__("entries", [])),
        ("meta not a table", lambda d: d.__setitem__("meta", [1])),
        ("sha256 not a table", lambda d: d.__setitem__("sha256", "x")),
        ("a digest not a digest", lambda d: d["sha256"].__setitem__(next(iter(d["sha256"])), 5)),
        ("record not a table", lambda d: d["entries"].__setitem__(k_img, "x")),
        ("files not a list", lambda d: d["entries"][k_img].__setitem__("files", "abc")),
        ("a file name not a string", lambda d: d["entries"][k_img].__setitem__("files", [3])),
        ("image dtype changed", lambda d: d["entries"][k_img].__setitem__("dtype", "float64")),
        ("image shape dropped", lambda d: d["entries"][k_img].pop("shape")),
        ("array dtype changed", lambda d: d["entries"][k_npy].__setitem__("dtype", "int8")),
        ("array shape changed", lambda d: d["entries"][k_npy].__setitem__("shape", [1, 2])),
        ("array dtype dropped", lambda d: d["entries"][k_npy].pop("dtype")),
        ("volume affine dropped", lambda d: d["entries"][k_vol].pop("voxel2ct")),
        ("volume affine not numbers", lambda d: d["entries"][k_vol].__setitem__("voxel2ct",
                                                                                  "bogus")),
        ("role missing", lambda d: d["entries"][k_img].pop("role")),
    ]


def test_malformed_case_json_is_refused_naming_the_file_even_unverified(tmp_path):
    """Edits of case.json's structure (caught by the dataset's checksum when verified) are
    also refused, naming the file, when loaded with verify=False outside any dataset: no
    AttributeError/KeyError, and no entry read with another dtype or shape than recorded."""
    import copy

    case_dir = tmp_path / "c"
    write_case(case_dir, small_case(3), truth=TRUTH)
    doc_path = case_dir / "case.json"
    doc = json.loads(doc_path.read_text())
    load(case_dir, verify=False)  # the untouched case loads
    for name, edit in _mutations(doc):
        d = copy.deepcopy(doc)
        edit(d)
        doc_path.write_text(json.dumps(d))
        with pytest.raises(ValueError) as exc:
            load(case_dir, verify=False)
        assert str(case_dir) in str(exc.value), (name, str(exc.value))
    # a corrupt transforms.json (listed with its checksum, so verify finds it first)
    doc_path.write_text(json.dumps(doc))
    (case_dir / "transforms.json").write_text("{not json")
    with pytest.raises(ValueError, match=r"transforms\.json: not valid JSON"):
        load(case_dir, verify=False)
    with pytest.raises(ValueError, match=r"transforms\.json: SHA-256 differs"):
        load(case_dir)


def test_values_a_case_cannot_hold_are_refused_naming_the_file(tmp_path):
    """A review's cases that loaded and were scored: a projective ct2robot, a pin at 1e300 mm,
    a float format_version; and a case.json that is not UTF-8, named as such."""
    case_dir = tmp_path / "c"
    write_case(case_dir, small_case(3), truth=TRUTH)
    doc_path = case_dir / "case.json"
    doc = json.loads(doc_path.read_text())
    doc_path.write_text(json.dumps({**doc, "format_version": float(doc["format_version"])}))
    with pytest.raises(ValueError, match=r"case\.json: format_version .*\.0 is not supported"):
        load(case_dir, verify=False)
    doc_path.write_bytes(b"\xff" + json.dumps(doc).encode())
    with pytest.raises(ValueError, match=r"case\.json: not UTF-8 text"):
        load(case_dir, verify=False)
    doc_path.write_text(json.dumps(doc))
    transforms = json.loads((case_dir / "transforms.json").read_text())
    points = json.loads((case_dir / "points.json").read_text())
    m = np.array(transforms["ct2robot"])
    m[3, 0] = 1e-3
    (case_dir / "transforms.json").write_text(json.dumps({**transforms,
                                                          "ct2robot": m.tolist()}))
    with pytest.raises(ValueError, match=r"ct2robot.*last row is \[0, 0, 0, 1\]"):
        load(case_dir, verify=False)
    # numbers written as text (a held-out review: they were read as numbers and scored)
    m = np.array(transforms["ct2robot"]).tolist()
    m[0][3] = "800"
    (case_dir / "transforms.json").write_text(json.dumps({**transforms, "ct2robot": m}))
    with pytest.raises(ValueError, match=r"transforms\.json: transform 'ct2robot': expected "
                                         r"a 4 x 4 array of numbers"):
        load(case_dir, verify=False)
    (case_dir / "transforms.json").write_text(json.dumps(transforms))
    points["pins_ct"]["points"]["distal_1"] = ["1", 2.0, 3.0]
    (case_dir / "points.json").write_text(json.dumps(points))
    with pytest.raises(ValueError, match=r"points\.json: points 'pins_ct', 'distal_1': "
                                         r"expected an \(N, 3\) array of numbers, got text"):
        load(case_dir, verify=False)
    points["pins_ct"]["points"]["distal_1"] = [1e300, 0.0, 0.0]
    (case_dir / "points.json").write_text(json.dumps(points))
    with pytest.raises(ValueError, match=r"points\.json: points 'pins_ct', 'distal_1': "
                                         r"coordinates up to 1e\+300"):
        load(case_dir, verify=False)
    # a named point of the wrong shape, and an array of points that are not triples: named
    # with the file and the entry (they were numpy's reshape errors)
    for bad, match in (([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]], r"'distal_1': expected one point "
                                                          r"\[x, y, z\] \(mm\), got 2 rows"),
                       ([1.0, 2.0], r"'distal_1': expected an \(N, 3\) array"),
                       ("pin", r"'distal_1': expected an \(N, 3\) array of numbers")):
        points["pins_ct"]["points"]["distal_1"] = bad
        (case_dir / "points.json").write_text(json.dumps(points))
        with pytest.raises(ValueError, match=r"points\.json: points 'pins_ct', " + match):
            load(case_dir, verify=False)
    # a points entry without its kind, or whose named points are a list (held-out review:
    # "cannot be read: KeyError: 'kind'")
    for bad, match in (({"points": [[1.0, 2.0, 3.0]]}, r"expected an object"),
                       ({"kind": "named", "points": [[1.0, 2.0, 3.0]]}, r"kind 'named' holds "
                                                                       r"an object")):
        (case_dir / "points.json").write_text(json.dumps({**points, "pins_ct": bad}))
        with pytest.raises(ValueError, match=r"points\.json: points 'pins_ct': " + match):
            load(case_dir, verify=False)
    (case_dir / "points.json").write_text(json.dumps(points))
    # an .npz archive under an .npy name ("AttributeError: 'NpzFile' object has no
    # attribute 'dtype'")
    npy = case_dir / "arrays" / "flags.npy"
    np.savez(npy.with_suffix(""), flags=np.zeros(5, bool))
    npy.with_suffix(".npz").replace(npy)
    with pytest.raises(ValueError, match=r"flags\.npy: not a \.npy array"):
        load(case_dir, verify=False)
