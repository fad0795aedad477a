"""Rigid transforms, the Cayley rotation parameterisation, and 3-D lines.

Conventions (see DESIGN.md):

- Lengths in mm, angles in rad.
- A rigid transform is named ``source2target``; ``x_target = R @ x_source + t``.
  Composition reads right to left: ``ct2carm = robot2carm @ ct2robot``.
- Points are ``(N, 3)`` float64 arrays. A bundle of lines is a pair ``origins (N, 3)``,
  ``directions (N, 3)`` with unit directions.

The Cayley map used by the paper (Guéziec et al. 1998, eq. 4) is
``Q = (I - U)(I + U)^-1`` with ``U = skew(u)``. For a rotation of angle ``theta`` about the
unit axis ``n`` it gives ``u = -tan(theta / 2) n``, so ``Q ~ I - 2U`` for small ``u`` and the
components of ``-2u`` are the small rotation angles about x, y, z. Rotations of exactly 180
degrees have no Cayley parameters (``I + Q`` is singular); :func:`cayley_from_matrix` raises
``ValueError`` for them. Solvers therefore parameterise *increments* about the current
estimate, which stay far from 180 degrees.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = [
    "line_segment_distance",
    "MAD_TO_SIGMA",
    "arc_length",
    "robust_scale",
    "RigidTransform",
    "as_rigid_transform",
    "as_points",
    "as_lines",
    "assert_transform_close",
    "cayley",
    "cayley_from_matrix",
    "closest_point_to_lines",
    "closest_points_on_lines",
    "lines_through",
    "point_line_distances",
    "point_line_residuals",
    "polygon_distances",
    "skew",
    "transform_difference",
]


# --------------------------------------------------------------------------- input checks
def _one_line(exc: Exception) -> str:
    return str(exc).splitlines()[0][:120] if str(exc) else type(exc).__name__


#: no coordinate of a scene in millimetres comes near this (1000 km); beyond it the linear
#: algebra overflows (1e300 made an eigensolver fail instead of a clear error)
MAX_COORDINATE_MM = 1e9


def _holds_text(raw: np.ndarray) -> bool:
    """Whether an array of strings, bytes or Python objects holds any text."""
    if raw.dtype.kind in "US":
        return True
    return any(isinstance(v, str | bytes) for v in raw.ravel().tolist())


def as_points(points, name: str = "points", *, min_count: int = 0) -> np.ndarray:
    """Return ``points`` as a C-contiguous float64 ``(N, 3)`` array, or raise ``ValueError``.

    The message names the argument (``name``) and says what was expected.
    """
    try:
        raw = np.asarray(points)
        if raw.dtype.kind == "c":
            raise ValueError(f"{name}: complex values; expected real coordinates")
        if raw.dtype.kind == "b":
            raise ValueError(f"{name}: booleans; expected real coordinates (mm)")
        if raw.dtype.kind in "USO" and _holds_text(raw):
            # numpy reads "800" as 800.0: a number written as text is a damaged file or a
            # wrong column, not a coordinate (a review: a pin given as ["1", 2, 3] was scored)
            raise ValueError(f"{name}: expected an (N, 3) array of numbers, got text "
                             f"({raw.dtype}; numbers written as text are not read)")
        arr = np.asarray(raw, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        if str(exc).startswith(name):
            raise
        raise ValueError(f"{name}: expected an (N, 3) array of numbers, got "
                         f"{type(points).__name__} ({_one_line(exc)})") from None
    if arr.ndim == 1 and arr.shape[0] == 3:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name}: expected an (N, 3) array, got shape {arr.shape}")
    if arr.shape[0] < min_count:
        raise ValueError(f"{name}: expected at least {min_count} rows, got {arr.shape[0]}")
    if not np.all(np.isfinite(arr)):
        bad = np.flatnonzero(~np.all(np.isfinite(arr), axis=1))
        raise ValueError(f"{name}: contains NaN or inf (rows {bad[:10].tolist()})")
    if arr.size and np.max(np.abs(arr)) > MAX_COORDINATE_MM:
        raise ValueError(f"{name}: coordinates up to {np.max(np.abs(arr)):.3g}; expected "
                         f"millimetres of a scene (|x| <= {MAX_COORDINATE_MM:g})")
    return np.ascontiguousarray(arr)


def as_flags(values, name: str) -> np.ndarray:
    """Return ``values`` as a bool array of its own shape, or raise ``ValueError`` naming
    the argument: booleans, or numbers that are 0 or 1 (not text: ``"no"`` is no False,
    nor NaN)."""
    a = np.asarray(values)
    if a.dtype == bool:
        return a
    if a.dtype.kind not in "iuf" or not np.all(np.isin(a, (0, 1))):
        raise ValueError(f"{name}: expected booleans (or 0 and 1), got {a.dtype} values "
                         f"such as {a.ravel()[:5].tolist()}")
    return a.astype(bool)


def as_whole(values, name: str) -> np.ndarray:
    """Return ``values`` as an int64 array of its own shape, or raise ``ValueError`` naming
    the argument: integers, or real numbers without a fractional part (0.7 is no index)."""
    a = np.asarray(values)
    if a.dtype.kind in "iu":
        return a.astype(np.int64)
    if a.dtype.kind != "f" or not (np.all(np.isfinite(a)) and np.all(a == np.round(a))):
        raise ValueError(f"{name}: expected whole numbers, got {a.dtype}"
                         + (" with a fractional part" if a.dtype.kind == "f" else ""))
    return a.astype(np.int64)


def as_faces(faces, n_vertices: int, name: str = "faces") -> np.ndarray:
    """Return triangle ``faces`` as a C-contiguous int64 ``(F, 3)`` array of indices into
    ``n_vertices`` vertices, or raise ``ValueError`` naming the argument: not numbers
    (text, complex, ragged rows), not whole, not (F, 3) with F >= 1, or out of range."""
    try:
        raw = np.asarray(faces)
    except ValueError as exc:     # ragged rows
        raise ValueError(f"{name}: expected an (F, 3) array of vertex indices "
                         f"({_one_line(exc)})") from None
    if raw.dtype.kind not in "iuf":
        raise ValueError(f"{name}: expected integer vertex indices, got an array of "
                         f"{raw.dtype}")
    if raw.ndim != 2 or raw.shape[1] != 3 or raw.shape[0] == 0:
        raise ValueError(f"{name}: expected a non-empty (F, 3) integer array, got shape "
                         f"{raw.shape}")
    if raw.dtype.kind == "f" and not (np.all(np.isfinite(raw))
                                      and np.all(np.equal(np.mod(raw, 1), 0))):
        raise ValueError(f"{name}: expected integer vertex indices")
    f = np.ascontiguousarray(raw, dtype=np.int64)
    if f.min() < 0 or f.max() >= n_vertices:
        raise ValueError(f"{name}: vertex indices must be in [0, {n_vertices - 1}], got "
                         f"[{f.min()}, {f.max()}]")
    return f


def as_lines(origins, directions, *, unit_tol: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """Check a bundle of lines: ``origins (N, 3)``, unit ``directions (N, 3)`` (float64).

    Raises ``ValueError`` for shape mismatch, NaN/inf, zero directions, or directions whose
    norm differs from 1 by more than ``unit_tol`` (normalise them first with
    :func:`lines_through` or ``d / np.linalg.norm(d, axis=1, keepdims=True)``).
    """
    o = as_points(origins, "origins")
    d = as_points(directions, "directions")
    if o.shape != d.shape:
        raise ValueError(f"origins {o.shape} and directions {d.shape} must have the same shape")
    norms = np.linalg.norm(d, axis=1)
    zero = np.flatnonzero(norms < 1e-12)
    if zero.size:
        raise ValueError(f"directions: zero-length direction in rows {zero[:10].tolist()}")
    off = np.flatnonzero(np.abs(norms - 1.0) > unit_tol)
    if off.size:
        raise ValueError(
            f"directions: expected unit vectors; rows {off[:10].tolist()} have norms "
            f"{np.round(norms[off[:3]], 6).tolist()}"
        )
    return o, d


# --------------------------------------------------------------------------- rotations
def skew(v) -> np.ndarray:
    """Skew-symmetric matrix of ``v``: ``skew(v) @ x == cross(v, x)``.

    ``v`` of shape ``(..., 3)`` gives ``(..., 3, 3)``.
    """
    v = np.asarray(v, dtype=np.float64)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


def cayley(u) -> np.ndarray:
    """Rotation matrix ``Q = (I - U)(I + U)^-1`` of Cayley parameters ``u`` (3,) or (..., 3).

    Closed form: ``Q = I + 2 (U^2 - U) / (1 + |u|^2)``; always a proper rotation, of angle
    ``2 atan(|u|)`` about the axis ``-u / |u|``.
    """
    u = np.asarray(u, dtype=np.float64)
    if u.ndim == 0 or u.shape[-1] != 3:
        raise ValueError(f"cayley: expected Cayley parameters of shape (3,) or (..., 3), got "
                         f"shape {u.shape}")
    U = skew(u)
    n2 = np.sum(u * u, axis=-1)[..., None, None]
    return np.eye(3) + 2.0 * (U @ U - U) / (1.0 + n2)


def cayley_from_matrix(Q, *, max_angle_deg: float = 179.0) -> np.ndarray:
    """Cayley parameters ``u`` of the rotation matrix ``Q``: ``U = (I - Q)(I + Q)^-1``.

    Raises ``ValueError`` when the rotation angle exceeds ``max_angle_deg`` (at 180 degrees
    the parameters are infinite; near it they are ill-conditioned).
    """
    Q = np.asarray(Q, dtype=np.float64)
    if Q.shape != (3, 3):
        raise ValueError(f"Q: expected a (3, 3) rotation matrix, got shape {Q.shape}")
    if not np.all(np.isfinite(Q)):
        raise ValueError("Q: contains NaN or inf; expected a rotation matrix")
    err = np.abs(Q.T @ Q - np.eye(3)).max()
    if err > 1e-6 or np.linalg.det(Q) < 0:
        raise ValueError(f"Q: not a proper rotation matrix (|QtQ - I| = {err:.2e}, "
                         f"det {np.linalg.det(Q):.3g})")
    rotvec = Rotation.from_matrix(Q).as_rotvec()
    angle = np.linalg.norm(rotvec)
    if np.degrees(angle) > max_angle_deg:
        raise ValueError(
            f"rotation of {np.degrees(angle):.3f} deg has no usable Cayley parameters "
            f"(limit {max_angle_deg} deg; exactly 180 deg is singular)"
        )
    if angle < 1e-300:
        return np.zeros(3)
    return -np.tan(angle / 2.0) * rotvec / angle


# --------------------------------------------------------------------------- transforms
@dataclass(frozen=True)
class RigidTransform:
    """A rigid transform ``x_target = R @ x_source + t`` (R: (3, 3) rotation, t: (3,) mm).

    Name instances ``source2target``. ``a @ b`` composes (apply ``b`` first), ``~a`` or
    ``a.inverse()`` inverts, ``a(points)`` or ``a.apply(points)`` maps ``(N, 3)`` points.
    """

    R: np.ndarray
    t: np.ndarray

    def __post_init__(self):
        for name in ("R", "t"):
            if np.iscomplexobj(getattr(self, name)):
                raise ValueError(f"RigidTransform: {name} has complex values; expected real "
                                 "numbers")
        try:
            R = np.array(self.R, dtype=np.float64)
            t = np.array(self.t, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"RigidTransform: R and t must be arrays of numbers "
                             f"({_one_line(exc)})") from None
        if R.shape != (3, 3) or t.shape != (3,):
            raise ValueError(
                f"RigidTransform: R must be (3, 3) and t (3,), got {R.shape}, {t.shape}"
            )
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
            raise ValueError("RigidTransform: R and t must be finite")
        if np.max(np.abs(t)) > MAX_COORDINATE_MM:
            raise ValueError(f"RigidTransform: translation up to {np.max(np.abs(t)):.3g} mm; "
                             f"expected the millimetres of a scene (|t| <= "
                             f"{MAX_COORDINATE_MM:g})")
        err = np.abs(R.T @ R - np.eye(3)).max()
        det = np.linalg.det(R)
        if err > 1e-6 or det < 0:
            raise ValueError(f"RigidTransform: R is not a proper rotation (|RtR - I| = "
                             f"{err:.2e}, det {det:.3g}" + ("; a reflection" if det < 0 else "")
                             + ")")
        R.setflags(write=False)
        t.setflags(write=False)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)

    # constructors
    @classmethod
    def identity(cls) -> RigidTransform:
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_matrix(cls, T) -> RigidTransform:
        """From a (4, 4) homogeneous matrix (its last row ``[0, 0, 0, 1]``)."""
        if np.iscomplexobj(T):
            raise ValueError("expected a real (4, 4) matrix, got complex values")
        try:
            T = np.asarray(T, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"expected a (4, 4) matrix of numbers ({_one_line(exc)})") from None
        if T.shape != (4, 4):
            raise ValueError(f"expected a (4, 4) matrix, got {T.shape}")
        if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], rtol=0.0, atol=1e-9):
            raise ValueError(f"expected a rigid (4, 4) matrix whose last row is [0, 0, 0, 1], "
                             f"got {np.round(T[3], 6).tolist()}")
        return cls(T[:3, :3], T[:3, 3])

    @classmethod
    def from_rotvec(cls, rotvec_rad, t_mm=(0.0, 0.0, 0.0)) -> RigidTransform:
        v = np.asarray(rotvec_rad)
        if v.shape != (3,) or v.dtype.kind not in "iuf":
            raise ValueError(f"RigidTransform.from_rotvec: rotvec_rad: expected 3 numbers "
                             f"(rad), got shape {v.shape} of {v.dtype}")
        return cls(Rotation.from_rotvec(v.astype(np.float64)).as_matrix(), t_mm)

    @classmethod
    def from_rotation(cls, rotation: Rotation, t_mm=(0.0, 0.0, 0.0)) -> RigidTransform:
        if not isinstance(rotation, Rotation):
            raise ValueError("RigidTransform.from_rotation: rotation: expected a "
                             f"scipy.spatial.transform.Rotation, got {type(rotation).__name__}")
        return cls(rotation.as_matrix(), t_mm)

    @classmethod
    def from_cayley(cls, u, t_mm=(0.0, 0.0, 0.0)) -> RigidTransform:
        return cls(cayley(u), t_mm)

    # conversions
    def as_matrix(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self.R
        T[:3, 3] = self.t
        return T

    def as_rotation(self) -> Rotation:
        return Rotation.from_matrix(self.R)

    def as_cayley(self) -> np.ndarray:
        return cayley_from_matrix(self.R)

    @property
    def angle_rad(self) -> float:
        """Rotation angle in rad, in [0, pi]."""
        c = (np.trace(self.R) - 1.0) / 2.0
        return float(np.arccos(np.clip(c, -1.0, 1.0)))

    @classmethod
    def _checked_already(cls, R: np.ndarray, t: np.ndarray) -> RigidTransform:
        """A transform from the product or inverse of checked ones (a proper rotation
        again, to rounding), without the checks of ``__init__`` (25 us, a registration
        composes some 300 per start)."""
        obj = object.__new__(cls)
        R = np.array(R, dtype=np.float64)
        t = np.array(t, dtype=np.float64)
        R.setflags(write=False)
        t.setflags(write=False)
        object.__setattr__(obj, "R", R)
        object.__setattr__(obj, "t", t)
        return obj

    # algebra
    #: numpy defers to this class: ``T @ array`` and ``array @ T`` raise Python's TypeError
    #: naming both types, not numpy's "matmul: Input operand 0 does not have enough
    #: dimensions" (a review); compose with ``RigidTransform.from_matrix(array)``
    __array_ufunc__ = None

    def __matmul__(self, other: RigidTransform) -> RigidTransform:
        if isinstance(other, np.ndarray):
            raise TypeError("RigidTransform @ array: compose with "
                            "RigidTransform.from_matrix(array), or map points with .apply")
        if not isinstance(other, RigidTransform):
            return NotImplemented
        return RigidTransform._checked_already(self.R @ other.R, self.R @ other.t + self.t)

    def inverse(self) -> RigidTransform:
        return RigidTransform._checked_already(self.R.T, -self.R.T @ self.t)

    def __invert__(self) -> RigidTransform:
        return self.inverse()

    def apply(self, points) -> np.ndarray:
        """Map points ``(N, 3)`` (or a single ``(3,)``, or any ``(..., 3)``) from source to
        target frame."""
        p = np.asarray(points, dtype=np.float64)
        if p.ndim == 0 or p.shape[-1] != 3:
            raise ValueError(f"RigidTransform.apply: points: expected (N, 3) or (3,) mm, got "
                             f"shape {p.shape}")
        return p @ self.R.T + self.t

    __call__ = apply

    def apply_vectors(self, vectors) -> np.ndarray:
        """Rotate direction vectors ``(N, 3)`` (or ``(..., 3)``; no translation)."""
        v = np.asarray(vectors, dtype=np.float64)
        if v.ndim == 0 or v.shape[-1] != 3:
            raise ValueError(f"RigidTransform.apply_vectors: vectors: expected (N, 3) or (3,), "
                             f"got shape {v.shape}")
        return v @ self.R.T

    def apply_lines(self, origins, directions) -> tuple[np.ndarray, np.ndarray]:
        return self.apply(origins), self.apply_vectors(directions)

    def to_dict(self) -> dict:
        return {"R": self.R.tolist(), "t": self.t.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> RigidTransform:
        """From ``{"R": (3, 3), "t": (3,) mm}`` (what :meth:`to_dict` writes)."""
        missing = [k for k in ("R", "t") if not isinstance(d, Mapping) or k not in d]
        if missing:
            raise ValueError(f"RigidTransform.from_dict: expected a mapping with keys 'R' "
                             f"(3 x 3) and 't' (3,), missing {missing}")
        return cls(np.asarray(d["R"]), np.asarray(d["t"]))

    def __repr__(self) -> str:
        rv = np.degrees(self.as_rotation().as_rotvec())
        return (
            f"RigidTransform(rotvec_deg={np.round(rv, 4).tolist()}, "
            f"t_mm={np.round(self.t, 4).tolist()})"
        )


def _significant_past(value: float, limit: float) -> str:
    """``value`` with the significant digits that tell it from ``limit`` (2 significant ones, more
    where those would print the limit: 0.0010005 against 0.001 read as "0.001")."""
    for digits in range(2, 10):
        text = f"{value:.{digits}g}"
        if float(text) != limit or value == limit:
            return text
    return repr(value)


#: largest |R^T R - I| of a (4, 4) pose read from outside that is taken as a rounded
#: rotation and made orthonormal (the nearest rotation; 1e-3 is 0.06 deg or a scale of
#: 1.0005); beyond it the matrix is refused
ROUNDED_ROTATION_TOL = 1e-3


def as_rigid_transform(value, name: str = "initial") -> RigidTransform:
    """A :class:`RigidTransform` from ``value``: one already, or a (4, 4) homogeneous
    matrix of real numbers (lists too). ``ValueError`` starting with ``name`` for anything
    else: a value that is no array of numbers (None, a string; booleans, strings and
    objects are not read as numbers, nor complex values, whose imaginary part a cast would
    drop), another shape, NaN or inf, a matrix that is no rigid transform. A rotation
    rounded (within :data:`ROUNDED_ROTATION_TOL`) is replaced by its nearest rotation. The
    one reading of a pose from outside (``reglib.estimate``'s ``initial``; ``testbed
    score``'s method results)."""
    if isinstance(value, RigidTransform):
        return value
    try:
        raw = np.asarray(value) if not isinstance(value, str | bytes) else None
    except (TypeError, ValueError):   # ragged nesting
        raw = None
    if raw is not None and raw.dtype.kind == "c":
        raise ValueError(f"{name}: the (4, 4) ct2robot matrix has complex values; expected "
                         "real numbers")
    if raw is None or raw.ndim == 0 or raw.dtype.kind not in "iuf":
        what = (type(value).__name__ if raw is None or raw.ndim == 0
                else f"an array of {raw.dtype} values")
        raise ValueError(f"{name}: expected a RigidTransform or a (4, 4) ct2robot matrix of "
                         f"numbers, got {what}")
    m = raw.astype(np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"{name}: expected a RigidTransform or a (4, 4) ct2robot matrix, got "
                         f"shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise ValueError(f"{name}: the (4, 4) ct2robot matrix holds NaN or inf")
    R = m[:3, :3]
    off = float(np.abs(R.T @ R - np.eye(3)).max())
    if not np.allclose(m[3], [0, 0, 0, 1]):
        # its own message (a review: one message for three conditions printed the row it
        # must have, not the row it had)
        row = ", ".join(f"{v:.6g}" for v in m[3])
        raise ValueError(f"{name}: the (4, 4) matrix is not a rigid transform: its last row "
                         f"is [{row}], expected [0, 0, 0, 1]")
    if off > ROUNDED_ROTATION_TOL or np.linalg.det(R) < 0:
        raise ValueError(f"{name}: the (4, 4) matrix is not a rigid transform (its 3x3 part "
                         f"must be a rotation: |R^T R - I| = "
                         f"{_significant_past(off, ROUNDED_ROTATION_TOL)}, at most "
                         f"{ROUNDED_ROTATION_TOL:g}, det {np.linalg.det(R):.4g})")
    if off > 1e-9:   # a matrix printed or stored rounded (4 decimals: 1e-5-1e-4): the
        u, _, vt = np.linalg.svd(R)   # nearest rotation (a review fed back print(estimate))
        R = u @ vt
    try:    # the class's own, stricter tests (a rotation 1e-6 off, a translation of 1e300)
        return RigidTransform(R, m[:3, 3])
    except ValueError as exc:
        raise ValueError(f"{name}: the (4, 4) matrix is not a rigid transform: {exc}") from None


def transform_difference(a: RigidTransform, b: RigidTransform) -> tuple[float, float]:
    """Return ``(translation mm, rotation deg)`` of ``a @ b.inverse()``."""
    for name, v in (("a", a), ("b", b)):
        if not isinstance(v, RigidTransform):
            raise TypeError(f"transform_difference: {name}: expected a RigidTransform, got "
                            f"{type(v).__name__} (RigidTransform.from_matrix makes one of a "
                            "(4, 4) array)")
    d = a @ b.inverse()
    return float(np.linalg.norm(d.t)), float(np.degrees(d.angle_rad))


def assert_transform_close(a: RigidTransform, b: RigidTransform, *, mm: float, deg: float,
                           points=None) -> None:
    """Assert that two transforms agree within ``mm`` and ``deg``.

    With ``points`` (N, 3), the translation test is the largest distance between the points
    mapped by ``a`` and by ``b`` (a target registration error) instead of ``|t_a - t_b|``.
    """
    if points is not None:
        p = as_points(points)
        dist = float(np.max(np.linalg.norm(a.apply(p) - b.apply(p), axis=1)))
    else:
        dist = float(np.linalg.norm(a.t - b.t))
    ang = float(np.degrees((a @ b.inverse()).angle_rad))
    if not (dist <= mm and ang <= deg):
        raise AssertionError(
            f"transforms differ by {dist:.3g} mm (limit {mm}) and {ang:.3g} deg (limit {deg})\n"
            f"  a = {a!r}\n  b = {b!r}"
        )


# --------------------------------------------------------------------------- lines
def lines_through(a, b) -> tuple[np.ndarray, np.ndarray]:
    """Lines through point pairs: origins ``a`` (N, 3), unit directions from ``a`` to ``b``."""
    a = as_points(a, "a")
    b = as_points(b, "b")
    d = b - a
    n = np.linalg.norm(d, axis=1, keepdims=True)
    if np.any(n < 1e-12):
        raise ValueError("lines_through: coincident point pairs define no line")
    return a, d / n


def point_line_residuals(points, origins, directions) -> np.ndarray:
    """Perpendicular vectors from each line to its point, ``(N, 3)`` in mm.

    ``r_i = (I - d_i d_i^T)(p_i - o_i)``; its norm is the point-line distance.
    """
    w = points - origins
    return w - np.sum(w * directions, axis=1, keepdims=True) * directions


def point_line_distances(points, origins, directions) -> np.ndarray:
    """Distance (mm) from each point ``(N, 3)`` to its line; returns ``(N,)``."""
    shapes = [np.shape(a) for a in (points, origins, directions)]
    if len(set(shapes)) != 1 or len(shapes[0]) != 2 or shapes[0][1] != 3:
        raise ValueError(f"point_line_distances: points, origins and directions must be "
                         f"(N, 3) each, one line per point; got {shapes}")
    return np.linalg.norm(point_line_residuals(points, origins, directions), axis=1)


def closest_points_on_lines(points, origins, directions) -> np.ndarray:
    """The point of each line closest to its point, ``(N, 3)``."""
    w = points - origins
    return origins + np.sum(w * directions, axis=1, keepdims=True) * directions


def closest_point_to_lines(origins, directions, weights=None) -> np.ndarray:
    """Least-squares point closest to a bundle of lines (e.g. a center of perspective).

    Minimises ``sum_i w_i |(I - d_i d_i^T)(x - o_i)|^2``. Raises ``ValueError`` if the lines
    are all parallel (the point is at infinity).
    """
    o, d = as_lines(origins, directions)
    if len(o) == 0:
        raise ValueError("closest_point_to_lines: no lines given")
    w = np.ones(len(o)) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (len(o),) or not np.all(np.isfinite(w)) or np.any(w < 0):
        raise ValueError(f"closest_point_to_lines: weights must be ({len(o)},) finite numbers "
                         f">= 0, one per line; got shape {w.shape}")
    M = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    A = np.einsum("n,nij->ij", w, M)
    b = np.einsum("n,nij,nj->i", w, M, o)
    s = np.linalg.svd(A, compute_uv=False)
    if s[-1] < 1e-9 * max(s[0], 1e-300):
        raise ValueError("closest_point_to_lines: lines are (nearly) parallel; no finite point")
    return np.linalg.solve(A, b)


#: the median of |z| for a standard normal z: median(|r|) / MAD_TO_SIGMA estimates sigma
MAD_TO_SIGMA = 0.6745


def robust_scale(residuals) -> float:
    """A robust standard deviation of residuals: ``median(|r|) / 0.6745`` (the scale of the
    paper's Tukey weights); NaN for no residuals (without numpy's empty-slice warning)."""
    r = np.abs(np.asarray(residuals, dtype=np.float64))
    if r.size == 0:
        return float("nan")
    return float(np.median(r)) / MAD_TO_SIGMA


def polygon_distances(points_xy, polygons) -> np.ndarray:
    """Each of ``points_xy`` (N, 2)'s distance (same unit) to the nearest point on any of the
    closed polygons ``polygons`` (a list of (K, 2) arrays; edges from each vertex to the
    next and from the last to the first): ``(N,)``, inf with no polygon."""
    p = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    best = np.full(len(p), np.inf)
    for poly in polygons:
        a = np.asarray(poly, dtype=np.float64)[:, :2]
        ab = np.roll(a, -1, axis=0) - a
        t = np.einsum("psk,sk->ps", p[:, None] - a[None], ab) / np.maximum(
            np.einsum("sk,sk->s", ab, ab), 1e-300)
        q = a[None] + np.clip(t, 0.0, 1.0)[..., None] * ab[None]
        best = np.minimum(best, np.linalg.norm(p[:, None] - q, axis=2).min(axis=1))
    return best


def arc_length(points, *, closed: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Cumulative arc length along a polyline of (K, D) points (any unit).

    Returns ``(P, s)``: the vertices (with the first repeated at the end when ``closed``) and
    ``s`` (len(P),), ``s[0] = 0``, ``s[-1]`` the length; ``np.interp(t, s, P[:, k])`` then
    samples the polyline at arc lengths ``t``.
    """
    P = np.asarray(points, dtype=np.float64)
    if closed:
        P = np.vstack([P, P[:1]])
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])
    return P, s


def line_segment_across(ox, oy, oz, dx, dy, dz, ax, ay, az, bx, by, bz):
    """The line ``o + t d`` (unit d) and the segment ``[a, b]`` seen across the line, in
    scalars: ``(s, px, py, pz, qx, qy, qz)`` with ``p = a - o`` and ``q = b - a`` less their
    components along ``d``, and ``s`` in [0, 1] the parameter of the segment's point
    ``a + s (b - a)`` nearest to the line (0 for a segment along the line). Plain Python,
    compiled as it is by :mod:`reglib._closest_numba`."""
    wx, wy, wz = ax - ox, ay - oy, az - oz
    ex, ey, ez = bx - ax, by - ay, bz - az
    wd = wx * dx + wy * dy + wz * dz
    ed = ex * dx + ey * dy + ez * dz
    px, py, pz = wx - wd * dx, wy - wd * dy, wz - wd * dz
    qx, qy, qz = ex - ed * dx, ey - ed * dy, ez - ed * dz
    qq = qx * qx + qy * qy + qz * qz
    s = 0.0
    if qq > 0.0:
        s = -(px * qx + py * qy + pz * qz) / qq
        s = 0.0 if s < 0.0 else (1.0 if s > 1.0 else s)
    return s, px, py, pz, qx, qy, qz


def line_segment_distance(ox, oy, oz, dx, dy, dz, ax, ay, az, bx, by, bz) -> float:
    """Distance (mm) between the line ``o + t d`` (unit d) and the segment ``[a, b]``, in
    scalars (:func:`line_segment_across`). Plain Python for the paper's capsule hierarchy
    (:mod:`reglib.closest`); :mod:`reglib._closest_numba` compiles the same two steps."""
    s, px, py, pz, qx, qy, qz = line_segment_across(ox, oy, oz, dx, dy, dz, ax, ay, az,
                                                    bx, by, bz)
    rx, ry, rz = px + s * qx, py + s * qy, pz + s * qz
    return math.sqrt(rx * rx + ry * ry + rz * rz)
