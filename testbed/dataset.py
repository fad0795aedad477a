"""The on-disk format of a synthetic dataset: one folder per case, read back exactly.

A *case* is a dict of named entries in six groups, plus free metadata::

    case = {
        "meta":       {...},                          # JSON-able dict (scene, seed, ...)
        "volumes":    {name: Volume},                 # CT volumes -> NIfTI-1 (.nii.gz)
        "images":     {name: uint8 (H, W) or (N, H, W)},   # 8-bit frames -> one PNG each
        "arrays":     {name: ndarray or {key: ndarray}},   # any numeric array -> .npy / .npz
        "meshes":     {name: trimesh.Trimesh},        # -> binary PLY, float64 vertices
        "transforms": {name: RigidTransform or (4, 4)},    # -> transforms.json
        "points":     {name: {label: (3,)} or (N, 3)},     # e.g. pins -> points.json
    }

Every entry is either *observation* (what a clinic would have: the CT volume, the 8-bit
X-ray and calibration-sweep frames, the robot-reported rod poses) or *truth* (what only the
simulator knows); the writer is told which entries are truth (``truth=["arrays/xray_float",
...]``), records the role of every entry in ``case.json``, and :func:`load` splits a case into
an :class:`Observation` and a :class:`Truth` accordingly.

Everything round-trips exactly: arrays bitwise with their dtype (``.npy``/``.npz``),
transforms and points bitwise (JSON floats are written with ``repr``, which round-trips a
float64), uint8 frames exactly (PNG is lossless), mesh vertices bitwise (PLY with ``double``
properties), the CT voxels bitwise in their dtype (NIfTI without scaling). The NIfTI header
holds the voxel->ct affine only in float32; the exact float64 affine is in ``case.json`` and
the header is checked against it on load.

``case.json`` holds ``format`` (:data:`FORMAT_NAME`), ``format_version``
(:data:`FORMAT_VERSION`), ``meta``, one record per entry (``role``, ``files``, ``dtype``,
``shape``, ...) and the SHA-256 of every file; :func:`load_case` refuses an unknown format
version, a missing file or a file whose checksum differs, naming the file. See
``docs/dataset-format.md`` for the full description and the entry names of the generator.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import tempfile
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from reglib.geometry import RigidTransform, as_points

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "GROUPS",
    "CasePart",
    "Observation",
    "Truth",
    "Volume",
    "list_cases",
    "load",
    "load_case",
    "write_case",
]

FORMAT_NAME = "xray-reg-testbed-case"
FORMAT_VERSION = 2
#: version 1 (before the operator's clicks were part of the observation) is not read: its
#: cases lack what reglib.estimate needs; generate them again
SUPPORTED_VERSIONS = (2,)
#: entry names that are always truth in the cases of ``testbed generate``, whatever
#: case.json says (fnmatch patterns): such a case calling one an observation is refused
TRUTH_ENTRIES = ("arrays/xray_float_*", "arrays/sweep_truth_*", "arrays/rays_*",
                 "transforms/*", "meshes/*", "points/*")
#: keys of meta that only the truth may see: ``truth`` (the resolved scene, seeds) and,
#: at the top level where generator versions before 6 wrote them, the case's index and the
#: dataset's seed (with which a method simulated the case again)
TRUTH_META_KEYS = ("truth", "case_index", "dataset_seed")
INDEX_FILE = "dataset.json"
GROUPS = ("volumes", "images", "arrays", "meshes", "transforms", "points")
ROLES = ("observation", "truth")
CASE_FILE = "case.json"
_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-]*$")
_NIFTI_DTYPES = {np.dtype(t) for t in ("uint8", "int8", "uint16", "int16", "uint32", "int32",
                                       "int64", "uint64", "float32", "float64")}


# --------------------------------------------------------------------------- types
@dataclass(frozen=True, eq=False)
class Volume:
    """A scanned volume.

    Parameters
    ----------
    data : (I, J, K) ndarray
        Voxel values (HU for a CT), indexed ``data[i, j, k]``; stored in its own dtype.
    voxel2ct : (4, 4) ndarray, float64
        Affine map from voxel indices ``(i, j, k, 1)`` (the centre of voxel ``[i, j, k]``) to
        ``ct`` frame coordinates in mm. It includes the voxel spacing, so it is not rigid.
    """

    data: np.ndarray
    voxel2ct: np.ndarray

    def __post_init__(self):
        data = np.asarray(self.data)
        aff = np.array(self.voxel2ct, dtype=np.float64)
        if data.ndim != 3:
            raise ValueError(f"Volume.data: expected an (I, J, K) array, got shape {data.shape}")
        if data.dtype not in _NIFTI_DTYPES:
            raise ValueError(f"Volume.data: dtype {data.dtype} cannot be stored in NIfTI "
                             f"without loss; use one of {sorted(str(d) for d in _NIFTI_DTYPES)}")
        if aff.shape != (4, 4) or not np.all(np.isfinite(aff)):
            raise ValueError(f"Volume.voxel2ct: expected a finite (4, 4) affine, got {aff.shape}")
        if not np.array_equal(aff[3], [0.0, 0.0, 0.0, 1.0]):
            raise ValueError(f"Volume.voxel2ct: last row must be [0, 0, 0, 1], got {aff[3]}")
        if abs(np.linalg.det(aff[:3, :3])) < 1e-12:
            raise ValueError("Volume.voxel2ct: the 3x3 part is singular")
        object.__setattr__(self, "data", data)
        object.__setattr__(self, "voxel2ct", aff)


@dataclass(frozen=True)
class CasePart:
    """The entries of one role of a case, by group (see the module docstring for types)."""

    volumes: dict[str, Volume] = field(default_factory=dict)
    images: dict[str, np.ndarray] = field(default_factory=dict)
    arrays: dict[str, Any] = field(default_factory=dict)
    meshes: dict[str, Any] = field(default_factory=dict)
    transforms: dict[str, RigidTransform] = field(default_factory=dict)
    points: dict[str, Any] = field(default_factory=dict)
    meta: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Observation(CasePart):
    """What a clinic would have (the entries of role ``observation``) and the case's meta."""


@dataclass(frozen=True)
class Truth(CasePart):
    """What only the simulator knows (the entries of role ``truth``) and the case's meta."""


# --------------------------------------------------------------------------- helpers
def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _check_name(group: str, name) -> str:
    if not isinstance(name, str) or not _NAME.match(name):
        raise ValueError(f"{group}/{name}: entry names must be non-empty and use only letters, "
                         "digits, '_', '-' and '.' (they become file names)")
    return name


def _matrix(value, what: str) -> np.ndarray:
    if isinstance(value, RigidTransform):
        return value.as_matrix()
    T = np.asarray(value, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"{what}: expected a RigidTransform or a (4, 4) matrix, got shape "
                         f"{T.shape}")
    try:
        RigidTransform.from_matrix(T)
    except ValueError as exc:
        raise ValueError(f"{what}: not a rigid transform ({exc})") from exc
    if not np.array_equal(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise ValueError(f"{what}: last row must be [0, 0, 0, 1], got {T[3]}")
    return T


def _numeric(arr, what: str) -> np.ndarray:
    a = np.asarray(arr)
    if a.dtype.kind not in "biufc":
        raise ValueError(f"{what}: expected a numeric or boolean array, got dtype {a.dtype}")
    return a


def _write_ply(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Binary little-endian PLY with ``double`` vertex coordinates (trimesh's exporter writes
    float32, which would not round-trip) and ``int`` triangle indices."""
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"comment {FORMAT_NAME} v{FORMAT_VERSION}: vertices in mm, float64\n"
        f"element vertex {len(vertices)}\n"
        "property double x\nproperty double y\nproperty double z\n"
        f"element face {len(faces)}\n"
        "property list uchar int vertex_indices\nend_header\n"
    ).encode("ascii")
    packed = np.zeros(len(faces), dtype=[("n", "u1"), ("idx", "<i4", (3,))])
    packed["n"] = 3
    packed["idx"] = faces
    with open(path, "wb") as f:
        f.write(header)
        f.write(np.ascontiguousarray(vertices, dtype="<f8").tobytes())
        f.write(packed.tobytes())


def _png_write(path: Path, img: np.ndarray) -> None:
    import cv2

    if not cv2.imwrite(str(path), img):
        raise OSError(f"{path}: OpenCV could not write the PNG")


def _png_read(path: Path) -> np.ndarray:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{path}: not a readable PNG image")
    if img.dtype != np.uint8 or img.ndim != 2:
        raise ValueError(f"{path}: expected an 8-bit single-channel PNG, got {img.dtype} "
                         f"shape {img.shape}")
    return img


# --------------------------------------------------------------------------- writing
#: deflate level of the .npz files: 1, not numpy's 6 -- the float64 ray maps (most of a
#: case's bytes) compress to the same size (6.65 against 6.64 MB a view) in 0.6x the time
NPZ_COMPRESSLEVEL = 1


#: a member whose sample deflates to more than this fraction is stored as it is: the float64
#: ray directions (7.4 MB a view) deflate only to 0.91 of their size, in 0.25 s each
NPZ_STORE_ABOVE = 0.8
NPZ_SAMPLE_BYTES = 1 << 20


def _worth_deflating(a: np.ndarray) -> bool:
    """Whether deflate shrinks ``a`` below :data:`NPZ_STORE_ABOVE` of its size, judged on up
    to :data:`NPZ_SAMPLE_BYTES` from its middle (small arrays: always)."""
    import zlib

    if a.nbytes <= NPZ_SAMPLE_BYTES or a.dtype.hasobject:
        return True
    raw = memoryview(np.ascontiguousarray(a)).cast("B")
    start = (len(raw) - NPZ_SAMPLE_BYTES) // 2
    sample = raw[start:start + NPZ_SAMPLE_BYTES]
    return len(zlib.compress(sample, NPZ_COMPRESSLEVEL)) <= NPZ_STORE_ABOVE * len(sample)


def _savez_fast(path: Path, arrs: dict) -> None:
    """``np.savez_compressed(path, **arrs)`` at deflate level :data:`NPZ_COMPRESSLEVEL`, a
    member that deflate hardly shrinks stored as it is (:func:`_worth_deflating`): an .npz
    (a zip of ``<key>.npy`` members) that ``np.load`` reads the same way."""
    import zipfile

    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED,
                         compresslevel=NPZ_COMPRESSLEVEL) as zf:
        for key, a in arrs.items():
            a = np.asanyarray(a)
            member: str | zipfile.ZipInfo = f"{key}.npy"
            if not _worth_deflating(a):
                # the zip's own default date (1980), as the deflated members get: with the
                # write time a case written again from its seed differed from the first
                member = zipfile.ZipInfo(member)
                member.compress_type = zipfile.ZIP_STORED
            with zf.open(member, "w", force_zip64=True) as f:
                np.lib.format.write_array(f, a, allow_pickle=False)


def _write_entry(root: Path, group: str, name: str, value, rec: dict) -> list[str]:
    """Write one entry under ``root``; fill ``rec``; return the files written (relative)."""
    what = f"{group}/{name}"
    if group == "volumes":
        import nibabel as nib

        if not isinstance(value, Volume):
            raise ValueError(f"{what}: expected a testbed.dataset.Volume, got "
                             f"{type(value).__name__}")
        rel = f"volumes/{name}.nii.gz"
        img = nib.Nifti1Image(value.data, value.voxel2ct)
        img.header.set_xyzt_units(xyz="mm")
        img.header.set_sform(value.voxel2ct, code="scanner")
        img.header.set_qform(value.voxel2ct, code="scanner")
        img.set_data_dtype(value.data.dtype)
        nib.save(img, root / rel)
        rec.update(dtype=str(value.data.dtype), shape=list(value.data.shape),
                   voxel2ct=value.voxel2ct.tolist())
        return [rel]
    if group == "images":
        img = np.asarray(value)
        if img.dtype != np.uint8 or img.ndim not in (2, 3) or 0 in img.shape:
            raise ValueError(f"{what}: expected a uint8 (H, W) image or (N, H, W) stack, got "
                             f"{img.dtype} shape {img.shape}; store float frames in 'arrays'")
        stack = img[None] if img.ndim == 2 else img
        (root / "images" / name).mkdir(parents=True)
        files = [f"images/{name}/{i:04d}.png" for i in range(len(stack))]
        for rel, frame in zip(files, stack):
            _png_write(root / rel, np.ascontiguousarray(frame))
        rec.update(dtype="uint8", shape=list(img.shape))
        return files
    if group == "arrays":
        if isinstance(value, Mapping):
            arrs = {}
            for k, v in value.items():
                if not isinstance(k, str) or not k.isidentifier():
                    raise ValueError(f"{what}: keys must be identifiers, got {k!r}")
                arrs[k] = _numeric(v, f"{what}[{k!r}]")
            rel = f"arrays/{name}.npz"
            _savez_fast(root / rel, arrs)
            rec.update(keys={k: {"dtype": str(a.dtype), "shape": list(a.shape)}
                             for k, a in arrs.items()})
        else:
            a = _numeric(value, what)
            rel = f"arrays/{name}.npy"
            np.save(root / rel, a, allow_pickle=False)
            rec.update(dtype=str(a.dtype), shape=list(a.shape))
        return [rel]
    if group == "meshes":
        v = np.asarray(getattr(value, "vertices", None), dtype=np.float64)
        f = np.asarray(getattr(value, "faces", None))
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
            raise ValueError(f"{what}: expected a triangle mesh with vertices (V, 3) and faces "
                             f"(F, 3), got {v.shape} and {f.shape}")
        if f.dtype.kind not in "iu" or (f.size and (f.min() < 0 or f.max() >= len(v))):
            raise ValueError(f"{what}: faces must be integer indices into the {len(v)} "
                             "vertices")
        if not np.all(np.isfinite(v)):
            raise ValueError(f"{what}: vertices contain NaN or inf")
        rel = f"meshes/{name}.ply"
        _write_ply(root / rel, v, f)
        rec.update(n_vertices=len(v), n_faces=len(f))
        return [rel]
    raise AssertionError(group)


def _json_points(value, what: str):
    if isinstance(value, Mapping):
        out = {}
        for label, p in value.items():
            if not isinstance(label, str):
                raise ValueError(f"{what}: labels must be str, got {label!r}")
            a = np.asarray(p, dtype=np.float64)
            if a.shape != (3,) or not np.all(np.isfinite(a)):
                raise ValueError(f"{what}[{label!r}]: expected a finite (3,) point in mm, got "
                                 f"shape {a.shape}")
            out[label] = a.tolist()
        return {"kind": "named", "points": out}
    a = np.asarray(value, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or not np.all(np.isfinite(a)):
        raise ValueError(f"{what}: expected a dict label -> (3,) or a finite (N, 3) array, got "
                         f"shape {a.shape}")
    return {"kind": "array", "points": a.tolist()}


def write_case(case_dir, case: Mapping[str, Any], *, truth: Iterable[str] = (),
               overwrite: bool = False) -> Path:
    """Write one case into the folder ``case_dir``.

    Parameters
    ----------
    case_dir : path
        The case folder. It is written next to itself under a temporary name and renamed
        when complete, so a folder with a ``case.json`` is always a whole case.
    case : dict
        ``meta`` (JSON-able dict) and the groups ``volumes``, ``images``, ``arrays``,
        ``meshes``, ``transforms``, ``points`` (each a dict name -> value; all optional).
    truth : iterable of str
        The entries, as ``"group/name"``, that are ground truth; all others are observation.
    overwrite : bool
        Replace an existing case folder (one that holds a ``case.json``). An existing folder
        that is not a case is never replaced.

    Returns
    -------
    Path of the written ``case.json``.
    """
    case_dir = Path(case_dir)
    if not isinstance(case, Mapping):
        raise ValueError(f"case: expected a dict of groups, got {type(case).__name__}")
    unknown = sorted(set(case) - set(GROUPS) - {"meta"})
    if unknown:
        raise ValueError(f"case: unknown keys {unknown}; expected 'meta' and groups {GROUPS}")
    meta = dict(case.get("meta") or {})
    try:
        meta_json = json.loads(json.dumps(meta))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"case['meta']: must be JSON-serialisable ({exc})") from exc
    names = {f"{g}/{_check_name(g, n)}" for g in GROUPS for n in (case.get(g) or {})}
    truth = {truth} if isinstance(truth, str) else set(truth)
    missing = sorted(truth - names)
    if missing:
        raise ValueError(f"truth: entries {missing} are not in the case (entries are named "
                         "'group/name', e.g. 'arrays/xray_float')")
    if case_dir.exists():
        if not (case_dir / CASE_FILE).exists():
            raise FileExistsError(f"{case_dir}: exists and is not a case folder; not replacing")
        if not overwrite:
            raise FileExistsError(f"{case_dir}: case exists (pass overwrite=True to replace)")

    case_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{case_dir.name}.", dir=case_dir.parent))
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o777 & ~umask)   # a case folder as mkdir makes it (mkdtemp's is 0700)
    try:
        for sub in ("volumes", "arrays", "meshes", "images"):
            (tmp / sub).mkdir()
        entries: dict[str, dict] = {}
        transforms, points = {}, {}
        for group in GROUPS:
            for name, value in (case.get(group) or {}).items():
                key = f"{group}/{name}"
                rec = {"role": "truth" if key in truth else "observation"}
                if group == "transforms":
                    transforms[name] = _matrix(value, key).tolist()
                    rec["files"] = ["transforms.json"]
                elif group == "points":
                    points[name] = _json_points(value, key)
                    rec["files"] = ["points.json"]
                else:
                    rec["files"] = _write_entry(tmp, group, name, value, rec)
                entries[key] = rec
        (tmp / "transforms.json").write_text(json.dumps(transforms, indent=1))
        (tmp / "points.json").write_text(json.dumps(points, indent=1))
        files = sorted({f for rec in entries.values() for f in rec["files"]}
                       | {"transforms.json", "points.json"})
        doc = {
            "format": FORMAT_NAME,
            "format_version": FORMAT_VERSION,
            "meta": meta_json,
            "entries": entries,
            "sha256": {f: _sha256(tmp / f) for f in files},
        }
        (tmp / CASE_FILE).write_text(json.dumps(doc, indent=1))
        if case_dir.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{case_dir.name}.old.", dir=case_dir.parent))
            os.replace(case_dir, old / "case")
            os.replace(tmp, case_dir)
            shutil.rmtree(old)
        else:
            os.replace(tmp, case_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return case_dir / CASE_FILE


# --------------------------------------------------------------------------- reading
def _inside(rel: str) -> bool:
    """A file name relative to its case folder that stays inside it."""
    from pathlib import PurePosixPath, PureWindowsPath

    p = PurePosixPath(rel)
    return (not p.is_absolute() and ".." not in p.parts and not PureWindowsPath(rel).drive
            and "\\" not in rel)


def _read_doc(case_dir: Path) -> dict:
    path = case_dir / CASE_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing; {case_dir} is not a dataset case folder")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from exc
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not UTF-8 text, so not the JSON of a case ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT_NAME:
        got = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
        raise ValueError(f"{path}: 'format' is {got!r}, expected {FORMAT_NAME!r}")
    version = doc.get("format_version")
    if isinstance(version, bool) or not isinstance(version, int) or version not in \
            SUPPORTED_VERSIONS:
        older = (isinstance(version, int) and not isinstance(version, bool)
                 and version < min(SUPPORTED_VERSIONS))
        advice = ("an older format whose cases lack what reglib.estimate needs: generate the "
                  "dataset again with this testbed" if older else
                  "a newer or unknown format: update the testbed")
        raise ValueError(f"{path}: format_version {version!r} is not supported by this reader "
                         f"(supported: {list(SUPPORTED_VERSIONS)}); {advice}")
    for key in ("meta", "entries", "sha256"):
        if key not in doc:
            raise ValueError(f"{path}: the field {key!r} is missing")
        if not isinstance(doc[key], dict):
            raise ValueError(f"{path}: the field {key!r} must be a table (JSON object), got "
                             f"{type(doc[key]).__name__}")
    for key, rec in doc["entries"].items():
        if not isinstance(rec, dict):
            raise ValueError(f"{path}: entry {key!r} must be a table, got "
                             f"{type(rec).__name__}")
        files = rec.get("files")
        if (not isinstance(files, list) or not files
                or not all(isinstance(f, str) and f for f in files)):
            raise ValueError(f"{path}: entry {key!r}: 'files' must be a non-empty list of "
                             f"file names, got {files!r}")
    for rel in [f for rec in doc["entries"].values() for f in rec["files"]] + list(doc["sha256"]):
        if not _inside(rel):
            raise ValueError(f"{path}: file name {rel!r} leaves the case folder; a case's "
                             "files are named relative to it, without '..'")
    for rel, digest in doc["sha256"].items():
        if not isinstance(digest, str) or len(digest) != 64:
            raise ValueError(f"{path}: sha256 of {rel!r} must be 64 hex digits, got {digest!r}")
    return doc


def case_problem(case_dir) -> str | None:
    """Why the case in ``case_dir`` is not whole, or None: its ``case.json`` readable and, in
    a generated dataset, the checksum the index holds; every listed file present with its
    SHA-256 (every file is read). For a resumed ``testbed generate``, which must not call a
    damaged dataset complete."""
    case_dir = Path(case_dir)
    try:
        doc = _read_doc(case_dir)
        _check_index(case_dir)
        _check_roles(case_dir, doc)
        _check_files(case_dir, doc, verify=True)
    except (ValueError, OSError) as exc:
        return str(exc)
    return None


def _check_index(case_dir: Path) -> None:
    """A case inside a generated dataset: its ``case.json`` must have the SHA-256 that the
    dataset's index (``../dataset.json``) recorded when the case was written."""
    index = case_dir.parent / INDEX_FILE
    if not index.is_file():
        return
    try:
        idx = json.loads(index.read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"{index}: unreadable dataset index ({exc})") from None
    if not isinstance(idx, dict):     # (a list was said to hold no checksum of the case)
        raise ValueError(f"{index}: expected a JSON object (the dataset's index that testbed "
                         f"generate writes), got a {type(idx).__name__}")
    hashes = idx.get("case_json_sha256")
    if not isinstance(hashes, dict) or case_dir.name not in hashes:
        raise ValueError(f"{case_dir / CASE_FILE}: {index} holds no checksum of this case; "
                         "the case was not written by testbed generate into this dataset")
    if _sha256(case_dir / CASE_FILE) != hashes[case_dir.name]:
        raise ValueError(f"{case_dir / CASE_FILE}: SHA-256 differs from {index}; case.json "
                         "was changed after the case was written")


def _check_roles(case_dir: Path, doc: dict) -> None:
    """A case of ``testbed generate`` (by its meta or its dataset index) never has a truth
    entry (:data:`TRUTH_ENTRIES`) marked as observation; other writers name freely."""
    from fnmatch import fnmatchcase

    generated = (doc.get("meta", {}).get("generator") == "testbed generate"
                 or (case_dir.parent / INDEX_FILE).is_file())
    if not generated:
        return
    for key, rec in doc["entries"].items():
        if rec.get("role") == "observation" and any(fnmatchcase(key, p) for p in TRUTH_ENTRIES):
            raise ValueError(f"{case_dir / CASE_FILE}: entry {key!r} is ground truth but is "
                             "marked 'observation'; refusing to put truth into the Observation")


def _check_files(case_dir: Path, doc: dict, verify: bool) -> None:
    listed = {"transforms.json", "points.json"}
    for key, rec in doc["entries"].items():
        files = rec.get("files") if isinstance(rec, dict) else None
        if not isinstance(files, list) or not files:
            raise ValueError(f"{case_dir / CASE_FILE}: entry {key!r} lists no files")
        listed.update(files)
    unchecked = sorted(listed - set(doc["sha256"]))
    if unchecked:
        raise ValueError(f"{case_dir / unchecked[0]}: no SHA-256 in {CASE_FILE} (every file "
                         "of a case must have its checksum)")
    for rel, digest in doc["sha256"].items():
        path = case_dir / rel
        if not path.is_file():
            raise FileNotFoundError(f"{path}: missing (listed in {case_dir / CASE_FILE})")
        if verify and _sha256(path) != digest:
            raise ValueError(f"{path}: SHA-256 differs from {CASE_FILE}; the file was changed "
                             "or truncated")


def _same_layout(path: Path, a: np.ndarray, rec, what: str) -> None:
    """The dtype and shape of an array read from ``path`` are those ``case.json`` records."""
    if not isinstance(rec, dict) or str(a.dtype) != rec.get("dtype") \
            or list(a.shape) != rec.get("shape"):
        want = (f"{rec.get('dtype')!r} {rec.get('shape')!r}" if isinstance(rec, dict)
                else repr(rec))
        raise ValueError(f"{path}: {what} is {a.dtype} {a.shape}, {CASE_FILE} says {want}")


def _read_entry(case_dir: Path, group: str, name: str, rec: dict, transforms: dict,
                points: dict):
    what = f"{group}/{name}"
    if group == "volumes":
        import nibabel as nib

        path = case_dir / rec["files"][0]
        img = nib.load(path)
        data = np.asanyarray(img.dataobj)
        aff = np.array(rec["voxel2ct"], dtype=np.float64)
        if str(data.dtype) != rec["dtype"] or list(data.shape) != rec["shape"]:
            raise ValueError(f"{path}: holds {data.dtype} {data.shape}, {CASE_FILE} says "
                             f"{rec['dtype']} {tuple(rec['shape'])}")
        if not np.allclose(img.affine, aff, rtol=1e-6, atol=1e-4):
            raise ValueError(f"{path}: header affine disagrees with voxel2ct in {CASE_FILE}")
        return Volume(data, aff)
    if group == "images":
        if rec.get("dtype") != "uint8":
            raise ValueError(f"{case_dir / CASE_FILE}: entry {what!r}: images are uint8, "
                             f"{CASE_FILE} says {rec.get('dtype')!r}")
        frames = [_png_read(case_dir / rel) for rel in rec["files"]]
        img = np.stack(frames)
        if len(rec["shape"]) == 2:
            img = img[0]
        if list(img.shape) != rec["shape"]:
            raise ValueError(f"{what}: frames give shape {img.shape}, {CASE_FILE} says "
                             f"{tuple(rec['shape'])}")
        return img
    if group == "arrays":
        path = case_dir / rec["files"][0]
        if path.suffix == ".npz":
            with np.load(path, allow_pickle=False) as z:
                if sorted(z.files) != sorted(rec["keys"]):
                    raise ValueError(f"{path}: holds arrays {sorted(z.files)}, {CASE_FILE} "
                                     f"says {sorted(rec['keys'])}")
                out = {k: z[k] for k in rec["keys"]}
            for k, a in out.items():
                _same_layout(path, a, rec["keys"][k], f"array {k!r}")
            return out
        a = np.load(path, allow_pickle=False)
        if not isinstance(a, np.ndarray):     # an .npz archive under the .npy name
            a.close()
            raise ValueError(f"{path}: not a .npy array (numpy reads an .npz archive there); "
                             f"{CASE_FILE} says one array of {rec.get('dtype')} "
                             f"{rec.get('shape')}")
        _same_layout(path, a, rec, "array")
        return a
    if group == "meshes":
        import trimesh

        path = case_dir / rec["files"][0]
        mesh = trimesh.load(path, file_type="ply", process=False, force="mesh")
        if len(mesh.vertices) != rec["n_vertices"] or len(mesh.faces) != rec["n_faces"]:
            raise ValueError(f"{path}: {len(mesh.vertices)} vertices and {len(mesh.faces)} "
                             f"faces, {CASE_FILE} says {rec['n_vertices']} and {rec['n_faces']}")
        return mesh
    if group == "transforms":
        if name not in transforms:
            raise ValueError(f"{case_dir / 'transforms.json'}: no transform {name!r}")
        raw = transforms[name]
        try:
            m = np.asarray(raw)
        except ValueError:          # ragged lists
            m = None
        if m is None or m.dtype.kind not in "iuf":
            # numpy would read "800" as 800.0 (a review scored a damaged truth that way)
            raise ValueError(f"{case_dir / 'transforms.json'}: transform {name!r}: expected a "
                             f"4 x 4 array of numbers, got {str(raw)[:80]}")
        return RigidTransform.from_matrix(m.astype(np.float64))
    if group == "points":
        if name not in points:
            raise ValueError(f"{case_dir / 'points.json'}: no points {name!r}")
        p = points[name]
        where = f"{case_dir / 'points.json'}: points {name!r}"
        if not (isinstance(p, dict) and p.get("kind") in ("named", "array")
                and "points" in p):
            raise ValueError(f"{where}: expected an object {{\"kind\": \"named\" or "
                             f"\"array\", \"points\": ...}}, got {p!r:.80}")
        if p["kind"] == "named":
            if not isinstance(p["points"], dict):
                raise ValueError(f"{where}: kind 'named' holds an object label -> [x, y, z], "
                                 f"got {type(p['points']).__name__}")
            out = {}
            for k, v in p["points"].items():
                a = as_points(v, f"{where}, {k!r}", min_count=1)
                if len(a) != 1:
                    raise ValueError(f"{where}, {k!r}: expected one point [x, y, z] (mm), got "
                                     f"{len(a)} rows")
                out[k] = a.reshape(3)
            return out
        return as_points(p["points"], where)
    raise ValueError(f"{case_dir / CASE_FILE}: unknown group {group!r} in entry {what!r}")


def _read_json_table(path: Path) -> dict:
    try:
        out = json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(out, dict):
        raise ValueError(f"{path}: expected a JSON object, got {type(out).__name__}")
    return out


def _load(case_dir: Path, verify: bool) -> tuple[dict, dict]:
    case_dir = Path(case_dir)
    if case_dir.name == CASE_FILE:
        case_dir = case_dir.parent
    doc = _read_doc(case_dir)
    if verify:
        _check_index(case_dir)
    _check_roles(case_dir, doc)
    _check_files(case_dir, doc, verify)
    transforms = _read_json_table(case_dir / "transforms.json")
    points = _read_json_table(case_dir / "points.json")
    case: dict[str, Any] = {"meta": doc["meta"], **{g: {} for g in GROUPS}}
    roles = {}
    for key, rec in doc["entries"].items():
        group, _, name = key.partition("/")
        if group not in GROUPS or rec.get("role") not in ROLES:
            raise ValueError(f"{case_dir / CASE_FILE}: entry {key!r} has an unknown group or "
                             f"role {rec.get('role')!r}")
        try:
            case[group][name] = _read_entry(case_dir, group, name, rec, transforms, points)
        except (ValueError, FileNotFoundError) as exc:
            if str(case_dir) in str(exc):  # already names the file
                raise
            raise ValueError(f"{case_dir / CASE_FILE}: entry {key!r}: {exc}") from exc
        except Exception as exc:  # a malformed record or an unreadable file (verify=False)
            raise ValueError(f"{case_dir / CASE_FILE}: entry {key!r} (files {rec['files']}) "
                             f"cannot be read: {type(exc).__name__}: {exc}") from exc
        roles[key] = rec["role"]
    return case, roles


def load_case(case_dir, *, verify: bool = True) -> dict[str, Any]:
    """Read a case written by :func:`write_case`: the same dict (``meta`` and the groups).

    Transforms come back as ``RigidTransform``, meshes as ``trimesh.Trimesh``, images as
    uint8 arrays of the written shape, named points as dicts of (3,) float64 arrays. With
    ``verify`` the SHA-256 of every file is checked. Raises ``FileNotFoundError`` naming a
    missing file and ``ValueError`` for an unknown format version or a changed file.
    """
    return _load(Path(case_dir), verify)[0]


def load(path, *, verify: bool = True) -> tuple[Observation, Truth]:
    """Read a case and split it by role into ``(Observation, Truth)``.

    The truth's ``meta`` is the whole of it; the observation's leaves out
    :data:`TRUTH_META_KEYS` (the resolved scene and the seeds). With ``verify``, the
    SHA-256 of every file and, inside a generated dataset, of ``case.json`` itself (kept in
    ``dataset.json``) are checked; entries that are ground truth by name
    (:data:`TRUTH_ENTRIES`) are never put into the observation. Every error names the file.
    """
    case, roles = _load(Path(path), verify)
    parts = {r: {g: {} for g in GROUPS} for r in ROLES}
    for key, role in roles.items():
        group, _, name = key.partition("/")
        parts[role][group][name] = case[group][name]
    obs_meta = {k: v for k, v in case["meta"].items() if k not in TRUTH_META_KEYS}
    return (Observation(**parts["observation"], meta=obs_meta),
            Truth(**parts["truth"], meta=case["meta"]))


def list_cases(root) -> list[Path]:
    """The case folders (those holding a ``case.json``) directly under ``root``, sorted."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such dataset folder")
    return sorted(p for p in root.iterdir()
                  if p.is_dir() and not p.name.startswith(".") and (p / CASE_FILE).is_file())
