"""The simulated operator: the clicks a user places on the CT slices and on the X-ray frames.

In the paper the user clicks a few points near the bone on a CT slice or an X-ray image; a
snake does the rest (NOTES.md s2), and the same clicks are reused from slice to slice. This
module is that user. It works from what the user sees:

- **CT**: the bone is what is bright on each slice. The operator thresholds the slice
  (``ct_bone_threshold_hu``), fills the marrow, keeps the outlines of the bone's cross-sections
  (one for the shaft and the proximal femur, two at the condyles) and places ``ct_clicks``
  points along each, evenly spaced with a random phase, each moved by a seeded Gaussian error
  of ``ct_click_noise_px``. Clicks are placed again when the number of cross-sections
  changes, after ``ct_reclick_every_mm`` along the slices, or where the bone has moved more
  than ``ct_reclick_off_px`` off the clicks a slice would reuse (the user sees them off the
  bone); the slices between reuse them.
  In the proximal region the operator stops where the femoral head separates from the neck
  (two cross-sections): the head is left out, as in the paper.
- **X-ray**: the femur's outline as it shows in the frame, *only where it is visible*: parts
  of the outline under an instrument's shadow (dilated by ``instrument_margin_px``) or within
  ``xray_edge_margin_px`` of the field's rim are never clicked. Each visible run of the
  outline longer than ``xray_min_trace_px`` becomes one trace of ``xray_clicks`` clicks with
  a Gaussian error of ``xray_click_noise_px``.

The X-ray outline is read from the rendered frame's per-body path lengths (what a trained
user perceives as the femur's edge), never from the method's models. Everything random is
drawn from the ``rng`` passed in.

Outputs are plain arrays, stored in the case's observation (``arrays/ct_clicks_{region}``
and ``arrays/xray_clicks_{view}``, see ``docs/dataset-format.md``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import numpy as np
from pydantic import Field, field_validator

from reglib.geometry import arc_length, polygon_distances
from testbed.seeds import keyed_seed, seed_sequence_of
from testbed.spec import NonNegative, Spec

__all__ = [
    "OperatorSpec",
    "CtClicks",
    "XrayClicks",
    "click_distances",
    "clicks_along",
    "clicks_off_outline",
    "ct_clicks",
    "reuse_source",
    "xray_clicks",
]


class OperatorSpec(Spec):
    """``[operator]``: the simulated user's clicks (see the module docstring).

    ``ct_clicks``: clicks per cross-section on a CT slice; ``ct_click_noise_px``: standard
    deviation of each click's error (px, CT pixels); ``ct_reclick_every_mm``: the user clicks
    again after this distance along the slices (0: on every slice); ``ct_reclick_off_px``:
    and on any slice where the bone has moved more than this off the clicks it would reuse
    (px; a click's distance from the slice's outlines less its distance from the outlines
    it was placed on): the user sees the clicks off the bone (larger than the image:
    never);
    ``ct_bone_threshold_hu``: what the user sees as bone on a slice (HU);
    ``ct_min_section_mm2``: smaller bright islands are ignored. ``ct_ignore_spurs_mm``: bright
    spurs narrower than this that join the bone (a metal streak through a pin crossing the
    threshold) are not seen as bone: the section is opened by a disc of that diameter
    before it is outlined (0: the thresholded section as it is, the ideal profile).
    ``xray_clicks``: clicks per visible run of the femur's outline on an X-ray frame;
    ``xray_click_noise_px``: error of each click (px); ``xray_edge_margin_px``: no click this
    close to the field's rim; ``instrument_margin_px``: no click this close to an
    instrument's shadow; ``xray_min_trace_px``: shorter visible runs are not traced.

    Clinic defaults (``docs/error-model.md``, section 5): clicks 1.5 px (CT) and 2 px (X-ray)
    off the outline, CT clicks reused for 10 mm of slices (the paper reuses them from slice to
    slice) while the bone moves less than 4.5 px off them (an assumption of what a user
    notices, set at 3 standard deviations of the clinic's click error; the drift does not
    count the user's own scatter); the ideal profile clicks within 1 px on every slice.
    """

    ct_clicks: Annotated[int, Field(ge=3, le=200)] = 10
    ct_click_noise_px: Annotated[float, Field(ge=0.0, le=50.0)] = 1.5
    ct_reclick_every_mm: NonNegative = 10.0
    ct_reclick_off_px: Annotated[float, Field(gt=0.0, le=10_000.0)] = 4.5
    ct_bone_threshold_hu: Annotated[float, Field(ge=-500.0, le=3000.0)] = 400.0
    ct_min_section_mm2: Annotated[float, Field(gt=0.0, le=1000.0)] = 20.0
    ct_ignore_spurs_mm: Annotated[float, Field(ge=0.0, le=20.0)] = 3.0

    @field_validator("ct_bone_threshold_hu")
    @classmethod
    def _between_tissue_and_bone(cls, v: float) -> float:
        # what the user sees as bone must lie between the simulated CT's soft tissue and
        # cortical bone (a review: -300 HU outlined the thigh, 2500 HU found no bone, and
        # both were refused later by the registration's verdict, blaming the views)
        from testbed.materials import material

        lo, hi = material("soft_tissue").hu, material("cortical_bone").hu
        if not lo < v < hi:
            raise ValueError(f"the user's bone threshold must lie between the CT's soft "
                             f"tissue ({lo:g} HU) and cortical bone ({hi:g} HU), got {v:g} HU")
        return v
    xray_clicks: Annotated[int, Field(ge=2, le=200)] = 8
    xray_click_noise_px: Annotated[float, Field(ge=0.0, le=50.0)] = 2.0
    xray_edge_margin_px: Annotated[float, Field(ge=0.0, le=200.0)] = 6.0
    instrument_margin_px: Annotated[float, Field(ge=0.0, le=200.0)] = 4.0
    xray_min_trace_px: Annotated[int, Field(ge=5, le=100_000)] = 40


# --------------------------------------------------------------------------- shared
def clicks_along(chain_xy, n_clicks: int, noise_px: float, rng, *, closed: bool) -> np.ndarray:
    """A user's clicks along a polyline: ``n_clicks`` points evenly spaced by arc length,
    plus a Gaussian error of ``noise_px`` each.

    Parameters
    ----------
    chain_xy : (K, 2) (x, y) px, the outline in order.
    closed : a closed outline (clicks start at a random phase) or an open one (clicks from
        end to end).

    Returns
    -------
    (n_clicks, 2) float64 (x, y) px.
    """
    p, s = arc_length(chain_xy, closed=closed)
    if closed:
        at = (rng.uniform() + np.arange(n_clicks)) / n_clicks * s[-1]
    else:
        at = np.linspace(0.0, s[-1], n_clicks)
    pts = np.column_stack([np.interp(at, s, p[:, 0]), np.interp(at, s, p[:, 1])])
    return pts + rng.normal(0.0, noise_px, size=pts.shape)


# --------------------------------------------------------------------------- CT
#: a bright island smaller than this share of the slice's largest one is not taken for bone
MIN_SECTION_SHARE = 0.1


@dataclass(frozen=True)
class CtClicks:
    """The operator's work on one CT region.

    ``slices`` (S,) int: the slices to contour, increasing z; ``clicks`` slice index -> list
    of (n, 2) (x, y) px click polygons, one per cross-section, ordered by mean x (only the
    slices where the user clicked; the others reuse the nearest).
    """

    region: str
    slices: np.ndarray
    clicks: dict

    def to_arrays(self) -> dict:
        """Flat arrays for the dataset: ``slices`` (S,), ``clicks_xy`` (P, 2) px,
        ``slice`` (P,) the slice of each click, ``contour`` (P,) its polygon on that slice."""
        xy, sl, co = [np.zeros((0, 2))], [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
        for k in sorted(self.clicks):
            for j, poly in enumerate(self.clicks[k]):
                xy.append(np.asarray(poly, dtype=np.float64))
                sl.append(np.full(len(poly), k, dtype=np.int64))
                co.append(np.full(len(poly), j, dtype=np.int64))
        return {"slices": np.asarray(self.slices, dtype=np.int64), "clicks_xy": np.vstack(xy),
                "slice": np.concatenate(sl), "contour": np.concatenate(co)}


def bone_sections(slice_hu, *, threshold_hu: float, min_area_px: float,
                  whole_slice: bool = False, spur_px: float = 0.0) -> list[np.ndarray]:
    """Outlines of the bright cross-sections of a CT slice, as a user sees them.

    The slice is thresholded, holes (marrow) filled, and each connected part of at least
    ``min_area_px`` pixels and :data:`MIN_SECTION_SHARE` of the largest part outlined.
    Returns a list of (K, 2) (x, y) px closed polygons (last point not repeated), ordered
    by mean x. ``spur_px`` > 0: the filled section is first opened by a disc of that
    diameter (px), so that spurs narrower than it (a metal streak above the threshold, joined
    to the bone) are not outlined. The work is done on the bright pixels' box;
    ``whole_slice=True`` does it on the whole slice (the reference, compared in tests).
    """
    from scipy import ndimage
    from skimage.measure import find_contours

    above = np.asarray(slice_hu) > threshold_hu
    rows, cols = np.flatnonzero(above.any(axis=1)), np.flatnonzero(above.any(axis=0))
    if len(rows) == 0:
        return []
    # work on the bright pixels' box with a 1-pixel margin: the outside of the box is all
    # background connected to the margin, so the holes, parts and outlines are the whole
    # slice's (outline points lie on half pixels: the offset adds exactly)
    r0, c0 = (0, 0) if whole_slice else (max(rows[0] - 1, 0), max(cols[0] - 1, 0))
    if not whole_slice:
        above = above[r0:rows[-1] + 2, c0:cols[-1] + 2]
    offset = np.array([c0, r0], dtype=np.float64)
    bright = ndimage.binary_fill_holes(above)
    if spur_px > 0:
        r = 0.5 * float(spur_px)
        k = int(np.ceil(r))
        yy, xx = np.mgrid[-k:k + 1, -k:k + 1]
        # beyond the box all is background, as the opening's border value (0) takes it
        bright = ndimage.binary_opening(bright, structure=xx * xx + yy * yy <= r * r)
    labels, n = ndimage.label(bright)
    areas = np.bincount(labels.ravel())[1:] if n else np.zeros(0)
    # islands much smaller than the bone's section (a streak, a pin's head) are not bone
    keep_px = max(min_area_px, MIN_SECTION_SHARE * (areas.max() if n else 0.0))
    out = []
    for lab in range(1, n + 1):
        if areas[lab - 1] < keep_px:
            continue
        part = labels == lab
        cs = find_contours(np.pad(part, 1).astype(np.float64), 0.5)
        if not cs:
            continue
        c = max(cs, key=len)[:-1] - 1.0  # undo the padding; (row, col)
        out.append(c[:, ::-1] + offset)
    return sorted(out, key=lambda p: float(np.mean(p[:, 0])))


def _polygon_area(p) -> float:
    """Area of a closed (K, 2) polygon (shoelace), px^2."""
    x, y = p[:, 0], p[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def _one_section_run(sections: dict, slice_z_mm) -> dict:
    """The longest run (in mm along the slices) of consecutive slices that show one section
    each.

    On the proximal femur the user outlines the shaft, trochanters and neck as one bone and
    leaves out the femoral head where it separates from the neck, as in the paper. A slice
    of two or more sections ends a run: the head above the neck, and, on some femurs, a
    lesser trochanter whose tip shows as an island beside the shaft near the region's lower
    end. In the lower half of the slices that show bone (the trochanters' side; the head
    separates in the upper half), a slice of several sections between two slices of one
    (an island of one slice) keeps its largest section, as a user outlines the bone and
    passes over the island. Elsewhere, and wherever sections persist over two or more
    slices, they end the run (with 6 mm slices the head's separation may show on one
    slice only). The longest run is the bone proper wherever the islands fall, with one
    exception: the topmost run, when it begins above the lower third of the slices that
    show bone, just above a slice of several sections, is the head (or the greater
    trochanter's tip) above its separation, which the user leaves out however long it is.
    (A held-out study: on a femur of valgus neck, 144 deg, and long neck, 79 mm, the
    greater trochanter separates from the neck on two 6 mm slices and the run above them,
    neck and head, was 54 mm against the shaft's 50 mm; the CT surface was the head alone,
    out of the proximal views, and every registration of the case was refused.)
    """
    ks = sorted(sections)
    if not ks:
        return {}
    z = np.asarray(slice_z_mm, dtype=np.float64)
    z_mid = 0.5 * (z[ks[0]] + z[ks[-1]])
    sections = dict(sections)
    for a, k, b in zip(ks[:-2], ks[1:-1], ks[2:]):
        if (len(sections[k]) > 1 and a == k - 1 and b == k + 1 and z[k] < z_mid
                and len(sections[a]) == 1 and len(sections[b]) == 1):
            sections[k] = [max(sections[k], key=_polygon_area)]
    runs, run, last = [], [], None
    for k in sorted(sections):
        if len(sections[k]) == 1 and (last is None or k == last + 1):
            run.append(k)
        else:
            if run:
                runs.append(run)
            run = [k] if len(sections[k]) == 1 else []
        last = k
    if run:
        runs.append(run)
    # the head above its separation from the neck: never the run outlined
    z_third = z[ks[0]] + (z[ks[-1]] - z[ks[0]]) / 3.0
    if len(runs) > 1 and runs[-1][-1] == ks[-1] and z[runs[-1][0]] > z_third:
        below = ks[ks.index(runs[-1][0]) - 1]
        if len(sections[below]) > 1:
            runs = runs[:-1]
    # the longest in mm (slices of 1 mm near a pin, 6 mm elsewhere: a count favours the fine
    # part); of equal extents the one of more slices
    best = max(runs, key=lambda r: (z[r[-1]] - z[r[0]], len(r))) if runs else []
    return {k: sections[k] for k in best}


def _too_few_sections(region: str, vol, slices, spec, n_bone: int) -> str:
    """The message of a CT region whose slices show bone on fewer than 2 (``n_bone``): the
    fields that decide it, with the region's brightest CT number."""
    idx = np.asarray(slices, dtype=np.int64)
    brightest = float(vol[idx].max()) if len(idx) else float("nan")
    how = " as one section" if region == "proximal" else ""
    return (f"operator.ct_bone_threshold_hu = {spec.ct_bone_threshold_hu:g} HU: bone above it "
            f"shows{how} on {n_bone} of the {len(idx)} slice(s) of CT region {region!r}, need 2 "
            f"(the region's brightest pixel is {brightest:.0f} HU): lower the threshold, or "
            "scan the region with more slices ([ct] schedule and spacing, or slice_z_mm)")


def click_distances(click_polygons, outlines) -> np.ndarray:
    """Each click's distance (px) to its nearest point on any of ``outlines`` (list of
    closed (K, 2) px polygons): ``(n,)`` for the clicks of ``click_polygons`` (list of
    (n_i, 2) px) in order."""
    return polygon_distances(np.vstack(click_polygons), outlines)


def clicks_off_outline(click_polygons, outlines, placed_on=None) -> float:
    """How far the bone has moved from reused clicks (px): the largest distance of a click
    of ``click_polygons`` from ``outlines`` (:func:`click_distances`), less its distance
    from the outlines it was placed on (``placed_on``; None: the plain distance). A user
    judges reused clicks by where they sit now against where they put them: clicks placed
    1 px off that sit 6 px off have drifted 5 px; clicks placed 4 px off (a sloppier user)
    that still sit 4 px off have not drifted (a fixed limit on the plain distance re-clicked
    nearly every slice at 3-4 px of click error, a review, h88)."""
    d = click_distances(click_polygons, outlines)
    if placed_on is not None:
        d = d - click_distances(click_polygons, placed_on)
    return float(d.max())


def reuse_source(clicked, k: int) -> int:
    """The clicked slice whose clicks a slice ``k`` reuses, as the dataset format reads
    them (docs/dataset-format.md, ``arrays/ct_clicks_{region}``): the nearest clicked slice
    (ties: the lower), but between two clicked slices of different contour counts the
    lower one, and below the lowest the lowest. ``clicked``: slice -> click polygons."""
    keys = sorted(clicked)
    below = [j for j in keys if j <= k]
    above = [j for j in keys if j > k]
    if not below:
        return above[0]
    lo = below[-1]
    if lo == k or not above:
        return lo
    hi = above[0]
    if len(clicked[lo]) != len(clicked[hi]):
        return lo
    return hi if hi - k < k - lo else lo


#: the spawn-key element of the CT clicks' per-slice streams (apart from spawn()'s children)
_CT_CLICK_KEY = 0xC7C1


def _place_ct_clicks(sections: dict, z, spec: OperatorSpec, seq, hi_xy) -> dict:
    """A region's clicks: slice -> click polygons, for ``sections`` (slice -> outlines).

    Going up the slices the user clicks anew where the count of sections changes, after
    ``ct_reclick_every_mm``, or where the bone has moved off the clicks reused from below by
    more than ``ct_reclick_off_px`` (:func:`clicks_off_outline`); then every slice is looked
    at with the clicks it reuses as the dataset is read (:func:`reuse_source`, the nearest
    clicked slice, which may lie above it: a review, h88, found slices seeded 12-18 px off
    by a re-click above them), and clicked anew where the bone has moved off them, until
    none is."""
    slices = sorted(sections)
    clicks: dict = {}

    def click(k):
        # each slice's clicks from a stream of its own (keyed by the slice): a CT that
        # changes which slices are clicked (thickness, noise, streaks) leaves the others'
        # clicks as they were (the error budget's pairs)
        k_rng = np.random.default_rng(keyed_seed(seq, _CT_CLICK_KEY, k))
        clicks[k] = [np.clip(clicks_along(p, spec.ct_clicks, spec.ct_click_noise_px, k_rng,
                                          closed=True), 0.0, hi_xy) for p in sections[k]]

    judged: dict = {}   # (slice, its clicks' slice) -> drifted: a slice's clicks never change

    def drifted(k, j):
        # clicks for another count of sections are off too (the pass up clicks anew where
        # the count changes, so the reuse never meets one; were it to, the slice is clicked,
        # not exempt: a review, h90)
        if (k, j) not in judged:
            judged[k, j] = (len(clicks[j]) != len(sections[k]) or clicks_off_outline(
                clicks[j], sections[k], placed_on=sections[j]) > spec.ct_reclick_off_px)
        return judged[k, j]

    last_z, last_k = -np.inf, None
    for k in slices:
        if (last_k is None or z[k] - last_z >= spec.ct_reclick_every_mm
                or drifted(k, last_k)):
            click(k)
            last_z, last_k = z[k], k
    # after each click only the slices whose nearest clicked slice changed are judged anew
    while True:
        off = next((k for k in slices if k not in clicks
                    and drifted(k, reuse_source(clicks, k))), None)
        if off is None:
            return clicks
        click(off)


def ct_clicks(volume_hu, slice_z_mm, region_slices: dict, *, pixel_mm: float,
              spec: OperatorSpec, rng) -> dict[str, CtClicks]:
    """The operator's clicks on every CT region.

    Parameters
    ----------
    volume_hu : (n_slices, rows, cols) HU, indexed [slice, row, col].
    slice_z_mm : (n_slices,) slice positions (ct mm, increasing).
    region_slices : region name -> slice indices of that scanned region (``CTScan.regions``).
    pixel_mm : in-plane pixel size (mm).
    spec : OperatorSpec.
    rng : numpy Generator.

    Raises ``ValueError`` naming the region when fewer than 2 of its slices show bone.
    """
    vol = np.asarray(volume_hu)
    z = np.asarray(slice_z_mm, dtype=np.float64)
    min_area_px = spec.ct_min_section_mm2 / pixel_mm**2
    seq = seed_sequence_of(rng)
    out = {}
    for region in sorted(region_slices):
        sections = {}
        for k in np.sort(np.asarray(region_slices[region], dtype=np.int64)):
            sec = bone_sections(vol[k], threshold_hu=spec.ct_bone_threshold_hu,
                                min_area_px=min_area_px,
                                spur_px=spec.ct_ignore_spurs_mm / pixel_mm)
            if sec:
                sections[int(k)] = sec
        if region == "proximal":
            sections = _one_section_run(sections, z)
        slices = sorted(sections)
        if len(slices) < 2:
            raise ValueError(_too_few_sections(region, vol, region_slices[region], spec,
                                               len(slices)))
        # a click lands on the slice's image: the error model's tail cannot leave it
        hi_xy = np.array([vol.shape[2] - 1, vol.shape[1] - 1], dtype=np.float64)
        clicks = _place_ct_clicks(sections, z, spec, seq, hi_xy)
        out[region] = CtClicks(region, np.asarray(slices, dtype=np.int64), clicks)
    return out


# --------------------------------------------------------------------------- X-ray
@dataclass(frozen=True)
class XrayClicks:
    """The operator's traces on one X-ray frame: ``traces`` a list of (n, 2) (x, y) px
    click arrays, each along a visible run of the femur's external outline."""

    view: str
    traces: list

    def to_arrays(self) -> dict:
        """Flat arrays for the dataset: ``clicks_xy`` (P, 2) px, ``trace`` (P,) the trace of
        each click, ``external`` (T,) bool (True: the bone's external outline), ``closed``
        (T,) bool."""
        xy = [np.zeros((0, 2))] + [np.asarray(t, dtype=np.float64) for t in self.traces]
        tr = [np.zeros(0, np.int64)] + [np.full(len(t), i, dtype=np.int64)
                                        for i, t in enumerate(self.traces)]
        n = len(self.traces)
        return {"clicks_xy": np.vstack(xy), "trace": np.concatenate(tr),
                "external": np.ones(n, dtype=bool), "closed": np.zeros(n, dtype=bool)}


def visible_outline(femur_mask, fov, *, occluder_mask=None, edge_margin_px: float,
                    occluder_margin_px: float, min_len_px: int) -> list[np.ndarray]:
    """Runs of the femur's outline that a user can see: (K, 2) (x, y) px chains.

    The outline of ``femur_mask`` (H, W) bool is cut where it comes within
    ``edge_margin_px`` of the field's rim (``fov`` (H, W) bool; beyond the frame is outside
    the field too, as where a zoomed intensifier's circle is cut by the video's rectangle)
    or within ``occluder_margin_px`` of ``occluder_mask`` (instruments' shadows); runs
    shorter than ``min_len_px`` points are dropped.
    """
    from scipy.ndimage import distance_transform_edt
    from skimage.measure import find_contours

    ok = distance_transform_edt(np.pad(np.asarray(fov, bool), 1))[1:-1, 1:-1] > edge_margin_px
    if occluder_mask is not None and np.any(occluder_mask):
        ok &= distance_transform_edt(~np.asarray(occluder_mask, bool)) > occluder_margin_px
    H, W = ok.shape
    chains = []
    for c in find_contours(np.asarray(femur_mask, dtype=np.float64), 0.5):
        rc = np.rint(c).astype(int)
        good = ok[np.clip(rc[:, 0], 0, H - 1), np.clip(rc[:, 1], 0, W - 1)]
        idx = np.flatnonzero(good)
        if idx.size == 0:
            continue
        for run in np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1):
            if len(run) >= min_len_px:
                chains.append(c[run][:, ::-1].copy())  # (row, col) -> (x, y)
    return chains


def xray_clicks(frame, *, femur_bodies, instrument_bodies, spec: OperatorSpec, rng,
                view: str = "") -> XrayClicks:
    """The operator's traces on a rendered frame (``testbed.fluoroscope.Frame``).

    ``femur_bodies``: names of the bodies that make up the femur (its outline is traced);
    ``instrument_bodies``: names of the instruments (their shadows hide the outline).
    """
    femur = np.zeros(frame.fov.shape, dtype=bool)
    for name in femur_bodies:
        femur |= frame.path_mm[name] > 0
    femur &= frame.fov
    occluder = np.zeros(frame.fov.shape, dtype=bool)
    for name in instrument_bodies:
        occluder |= frame.path_mm[name] > 0
    chains = visible_outline(femur, frame.fov, occluder_mask=occluder,
                             edge_margin_px=spec.xray_edge_margin_px,
                             occluder_margin_px=spec.instrument_margin_px,
                             min_len_px=spec.xray_min_trace_px)
    H, W = frame.fov.shape
    # a click lands on the screen's image, whatever its error
    traces = [np.clip(clicks_along(c, spec.xray_clicks, spec.xray_click_noise_px, rng,
                                   closed=False), 0.0, [W - 1.0, H - 1.0]) for c in chains]
    return XrayClicks(view, traces)
