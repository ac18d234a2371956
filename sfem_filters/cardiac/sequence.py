"""Point-wise motion sequences (DENSE, tagging, tracking): format, loader, example data.

A sequence file is an ``.npz`` with these keys (only the first two are required):

============== ================ =====================================================================
key            shape            meaning
============== ================ =====================================================================
points         (P, 2)           reference positions of the tracked material points (x, y), in pixels
                                 (or metres when ``pixel_spacing`` is absent and ``units`` = "m")
displacement   (F, P, 2)        Lagrangian displacement of each point at each frame, same unit as
                                 ``points``; NaN where a value is missing
velocity       (F, P, 2)        optional: velocity, unit per second (phase-contrast); NaN if missing
sigma          (), (P,), (F, P) optional: measurement standard deviation of each displacement, same
                                 unit as ``points`` (a scalar: one value for every point and frame)
confidence     (), (P,), (F, P) optional: confidence in [0, 1] of each displacement datum (a scalar:
                                 the same for every datum)
velocity_sigma (F, P)           optional: standard deviation of each velocity component, unit per
                                 second; NaN where there is no velocity
velocity_confidence (F, P)      optional: confidence in [0, 1] of each velocity (local phase
                                 coherence, LPC); NaN where there is no velocity
point_kind     (P,) int         optional: 0 endocardial border, 1 epicardial border, 2 mid-wall
frame_interval ()               optional: time between frames in seconds
pixel_spacing  ()               optional: size of a pixel in metres
pressure       (F,)             optional: cavity (blood) pressure at each frame in Pa
reference_mask (H, W) bool      optional: myocardium pixels of the reference frame (row = y, col = x)
frame_masks    (F, H, W) bool   optional: myocardium mask of each frame
units          ()               optional: "px" (default) or "m"
provenance     ()               optional: free text on where the data come from
============== ================ =====================================================================

Other keys are kept as ``extra`` (for example ``frame_times_s`` (F,), each frame's time in
seconds, which the ``strain`` command reads where the frames are not evenly spaced from 0; without
``frame_interval``, evenly spaced ``frame_times_s`` give it their spacing).

Image convention: x grows to the right (columns), y grows downwards (rows); point ``i`` is at
``points[i] + displacement[t, i]`` in frame ``t``.
"""
from __future__ import annotations

import os
import zipfile
from dataclasses import dataclass, field, fields

import numpy as np
from scipy.ndimage import binary_dilation

from .._validate import as_float_array, as_mask, positive
from ..datasets import dataset_path

FORMAT_KEYS = ("points", "displacement", "velocity", "sigma", "confidence", "velocity_sigma",
               "velocity_confidence", "point_kind", "frame_interval",
               "pixel_spacing", "pressure", "reference_mask", "frame_masks", "units", "provenance")


@dataclass(frozen=True, eq=False)
class Sequence:
    """A validated motion sequence; see the module docstring for every field."""

    points: np.ndarray
    displacement: np.ndarray
    velocity: np.ndarray | None = None
    sigma: np.ndarray | None = None
    confidence: np.ndarray | None = None
    velocity_sigma: np.ndarray | None = None
    velocity_confidence: np.ndarray | None = None
    point_kind: np.ndarray | None = None
    frame_interval: float | None = None
    pixel_spacing: float | None = None
    pressure: np.ndarray | None = None
    reference_mask: np.ndarray | None = None
    frame_masks: np.ndarray | None = None
    units: str = "px"
    provenance: str = ""
    extra: dict = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        """Number of frames F."""
        return self.displacement.shape[0]

    @property
    def n_points(self) -> int:
        """Number of tracked points P."""
        return self.points.shape[0]

    def to_dict(self) -> dict:
        """The format's keys that are set, key -> value in the sequence's own units (``extra`` left out;
        :func:`save_sequence` writes both)."""
        out = {}
        for f in fields(self):
            if f.name == "extra":
                continue
            v = getattr(self, f.name)
            if v is not None:
                out[f.name] = v
        return out


def make_sequence(points, displacement, **optional) -> Sequence:
    """Validate arrays into a :class:`Sequence` (errors name the key and what was expected)."""
    unknown = set(optional) - set(FORMAT_KEYS)
    pts = as_float_array("points", points, (None, 2), numeric_only=True)
    P = len(pts)
    if P < 3:
        raise ValueError(f"points: expected at least 3 points, got {P}")
    disp = as_float_array("displacement", displacement, (None, P, 2), allow_nan=True, numeric_only=True)
    F = disp.shape[0]
    if F < 2:
        raise ValueError(f"displacement: expected at least 2 frames, got {F}")
    if np.all(np.isnan(disp)):
        raise ValueError("displacement: every value is NaN; nothing was measured")
    extent = float(np.max(np.ptp(pts, axis=0)))
    largest = float(np.nanmax(np.linalg.norm(disp, axis=-1)))
    if largest > extent:
        # no point of a heart moves by more than the whole tissue's size: other units than the
        # points', or failed tracking (mark such values NaN)
        raise ValueError(f"displacement: expected displacements in the points' units and within the tissue's extent "
                         f"({extent:.4g}), got values up to {largest:.4g}; a displacement larger than the whole slice is "
                         "in other units or a tracking failure (mark such values NaN)")
    kw = {}
    if optional.get("velocity") is not None:
        kw["velocity"] = as_float_array("velocity", optional["velocity"], (F, P, 2), allow_nan=True,
                                        numeric_only=True)
    for key in ("sigma", "confidence"):
        v = optional.get(key)
        if v is not None:
            arr = np.asarray(v)
            if arr.ndim == 0:                                  # one value for every point and frame
                arr = np.full(P, float(as_float_array(key, arr, (), numeric_only=True)))
            arr = as_float_array(key, arr, (P,) if arr.ndim == 1 else (F, P), numeric_only=True)
            if key == "sigma" and np.any(arr <= 0):
                raise ValueError("sigma: expected standard deviations > 0")
            if key == "confidence" and np.any((arr < 0) | (arr > 1)):
                raise ValueError("confidence: expected values in [0, 1]")
            kw[key] = arr
    for key in ("velocity_sigma", "velocity_confidence"):
        if optional.get(key) is not None:
            if "velocity" not in kw:
                raise ValueError(f"{key}: given without 'velocity'")
            arr = as_float_array(key, optional[key], (F, P), allow_nan=True, numeric_only=True)
            has_v = ~np.isnan(kw["velocity"]).any(axis=2)
            if np.any(np.isnan(arr[has_v])):
                raise ValueError(f"{key}: expected a value wherever 'velocity' has one, got NaN")
            ok = arr[~np.isnan(arr)]
            if key == "velocity_sigma" and np.any(ok <= 0):
                raise ValueError("velocity_sigma: expected standard deviations > 0")
            if key == "velocity_confidence" and np.any((ok < 0) | (ok > 1)):
                raise ValueError("velocity_confidence: expected values in [0, 1]")
            kw[key] = arr
    if optional.get("point_kind") is not None:
        pk = np.asarray(optional["point_kind"])
        if pk.shape != (P,) or pk.dtype.kind not in "iu" or not np.isin(pk, [0, 1, 2]).all():
            raise ValueError(f"point_kind: expected {P} integers in {{0, 1, 2}}, got dtype {pk.dtype} "
                             f"and shape {pk.shape}")
        kw["point_kind"] = pk.astype(int)
    for key in ("frame_interval", "pixel_spacing"):
        if optional.get(key) is not None:
            kw[key] = positive(key, as_float_array(key, optional[key], (), numeric_only=True),
                               {"frame_interval": "s", "pixel_spacing": "m"}[key])
    if kw.get("frame_interval") is None and optional.get("frame_times_s") is not None:
        kw["frame_interval"] = _even_spacing(optional["frame_times_s"], F)
    if optional.get("pressure") is not None:
        kw["pressure"] = as_float_array("pressure", optional["pressure"], (F,), numeric_only=True)
    if optional.get("reference_mask") is not None:
        kw["reference_mask"] = as_mask("reference_mask", optional["reference_mask"], 2, nonempty=True)
    if optional.get("frame_masks") is not None:
        kw["frame_masks"] = as_mask("frame_masks", optional["frame_masks"], 3, shape=(F, None, None))
    units = str(np.asarray(optional.get("units", "px")))
    if units not in ("px", "m"):
        raise ValueError(f"units: expected 'px' or 'm', got {units!r}")
    if kw.get("reference_mask") is not None and kw.get("frame_masks") is not None \
            and kw["frame_masks"].shape[1:] != kw["reference_mask"].shape:
        raise ValueError(f"frame_masks: expected images of the reference_mask's shape {kw['reference_mask'].shape}, "
                         f"got {kw['frame_masks'].shape[1:]}")
    if kw.get("reference_mask") is not None and units == "px":
        _check_points_on_mask(pts, kw["reference_mask"])
    if units == "m" and kw.get("pixel_spacing") is not None:
        raise ValueError("pixel_spacing: given, but units is 'm' (points already in metres)")
    kw["units"] = units
    kw["provenance"] = str(np.asarray(optional.get("provenance", "")))
    return Sequence(points=pts, displacement=disp,
                    extra={k: optional[k] for k in unknown}, **kw)


def _check_points_on_mask(points, mask) -> None:
    """Most points (pixels: x = column, y = row) must fall on or next to the reference mask's tissue.

    Border points (the contours ``sfem-filters observe`` tracks) lie on the half-pixel boundary
    between tissue and background, so a point counts when its pixel or one of the 8 around it is
    tissue; half of all points is the bound. A mask from another image, or points shifted or
    transposed against it, falls far below it."""
    near = binary_dilation(mask, structure=np.ones((3, 3), bool))
    c = np.round(points[:, 0]).astype(int)
    r = np.round(points[:, 1]).astype(int)
    inside = (r >= 0) & (r < mask.shape[0]) & (c >= 0) & (c < mask.shape[1])
    on = np.zeros(len(points), bool)
    on[inside] = near[r[inside], c[inside]]
    if on.sum() < 0.5 * len(points):
        raise ValueError(f"reference_mask: expected the points (pixels, x = column, y = row) on or next to its tissue "
                         f"pixels, got {int(on.sum())} of {len(points)} there ({int((~inside).sum())} outside its "
                         f"{mask.shape[0]} x {mask.shape[1]} image); are the points and the mask in the same pixel frame?")


def load_sequence(path) -> Sequence:
    """Read and validate a sequence ``.npz`` file.

    Raises ``ValueError`` naming the file and the offending key for a missing, truncated or
    malformed file; no partial sequence is ever returned.
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise ValueError(f"path: no such file {path!r}")
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic not in (b"PK\x03\x04", b"PK\x05\x06"):  # a zip (or an empty one); np.load would read text as a pickle
        what = "an .npy array (save it with numpy.savez)" if magic[:2] == b"\x93N" else \
            f"{len(magic)} bytes" if len(magic) < 4 else "not a zip archive"
        raise ValueError(f"{path}: not a readable .npz sequence file (an .npz is a zip archive of arrays; this is {what})")
    try:
        with np.load(path, allow_pickle=False) as f:
            data = {k: f[k] for k in f.files}
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as exc:
        raise ValueError(f"{path}: not a readable .npz sequence file ({exc})") from None
    except Exception as exc:
        raise ValueError(f"{path}: not a readable .npz sequence file ({type(exc).__name__}: {exc})") from None
    missing = [k for k in ("points", "displacement") if k not in data]
    if missing:
        raise ValueError(f"{path}: missing required key(s) {missing}; found {sorted(data)}")
    try:
        return make_sequence(**data)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def save_sequence(seq: Sequence, path) -> str:
    """Write a sequence in the documented format (compressed npz), creating its directory; returns the
    path written (``path``, with ``.npz`` appended when it lacks it, as numpy does). The ``extra`` keys
    (such as ``frame_times_s``) are written beside the format's, so a file read and saved again keeps them."""
    taken = sorted(k for k in seq.extra if k in FORMAT_KEYS or k in ("file", "allow_pickle"))
    if taken:
        raise ValueError(f"seq.extra: keys {taken} are the format's own (or numpy's arguments); give a format key as "
                         "the Sequence's field, and name other data otherwise")
    for k, v in seq.extra.items():
        if np.asarray(v).dtype == object:
            raise ValueError(f"seq.extra[{k!r}]: expected numbers, booleans or text (what load_sequence reads "
                             f"without pickling), got {type(v).__name__}")
    path = os.fspath(path)
    written = path if path.endswith(".npz") else path + ".npz"
    os.makedirs(os.path.dirname(os.path.abspath(written)), exist_ok=True)
    np.savez_compressed(written, **{**seq.extra, **seq.to_dict()})
    return written


EXAMPLE_SEQUENCES = ("subject_a",)


def example_path(name: str = "subject_a", *, data_dir=None, download: bool = False) -> str:
    """Path of an example sequence file (``"subject_a"``: a measured DENSE LV slice, 332 points, 35 frames).

    The example is not shipped with the package (its source has no licence): it is found through
    :func:`sfem_filters.datasets.dataset_path`, in the data directory (``data_dir``, else the
    environment variable ``SFEM_FILTERS_DATA``: ``<folder>/dense/subject_a.npz``) or the download
    cache, or downloaded from its original repository when ``download`` is True (or beforehand
    with ``sfem_filters.datasets.fetch("subject_a")``).

    Raises
    ------
    ValueError
        ``name`` is not an example sequence.
    sfem_filters.datasets.DatasetNotFoundError
        (a ``FileNotFoundError``) the file is not found and ``download`` is False; the message
        says how to get it.
    """
    if name not in EXAMPLE_SEQUENCES:
        raise ValueError(f"name: expected one of {list(EXAMPLE_SEQUENCES)}, got {name!r}")
    return dataset_path(name, data_dir=data_dir, download=download)


def moved_on_lattice(seq: Sequence, quarter_turns: int = 0, mirror: bool = False, shift=(0, 0)) -> Sequence:
    """The same heart placed otherwise in the image: mirrored, turned, shifted by whole pixels.

    The moves map the pixel lattice onto itself, so that a result that depends only on the
    heart, not on where it lies in the image, must not change (the docs' frozen mesh-orientation
    result measures how much it does). In this order:

    1. ``mirror``: x -> W - 1 - x (columns reversed, ``mask[:, ::-1]``), vectors (dx, dy) -> (-dx, dy);
    2. ``quarter_turns`` times ``np.rot90`` of the masks: a pixel (x, y) goes to (y, W - 1 - x),
       a vector (dx, dy) to (dy, -dx) (a quarter turn anticlockwise as the image is shown);
    3. ``shift`` (sx, sy) whole pixels: points + (sx, sy), the masks padded on the left and top.

    W is the width of the reference mask (without masks: 1 + the largest x of the points).

    Parameters
    ----------
    seq : Sequence
        In pixels (``units`` "px").
    quarter_turns : int
        Number of quarter turns (any integer; taken modulo 4).
    mirror : bool
        Mirror first.
    shift : (int, int)
        Pixels to the right and down (>= 0).

    Returns
    -------
    Sequence
        Points, displacements and velocities moved, masks moved with them; every other field
        (noise, confidence, point kinds, pressure, spacing, frame interval) as it was; points keep
        their order.
    """
    if not isinstance(seq, Sequence):
        raise TypeError(f"seq: expected a Sequence, got {type(seq).__name__}")
    if seq.units != "px":
        raise ValueError(f"seq: expected a sequence in pixels (units 'px'), got units {seq.units!r}")
    if isinstance(quarter_turns, bool) or not isinstance(quarter_turns, (int, np.integer)):
        raise ValueError(f"quarter_turns: expected an integer, got {quarter_turns!r}")
    if not isinstance(mirror, (bool, np.bool_)):
        raise ValueError(f"mirror: expected True or False, got {mirror!r}")
    try:
        sx, sy = (int(v) for v in shift)
        ok = all(float(v) == int(v) for v in shift) and sx >= 0 and sy >= 0
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"shift: expected two whole numbers of pixels >= 0 (right, down), got {shift!r}")
    d = seq.to_dict()
    masks = {k: np.asarray(d[k]) for k in ("reference_mask", "frame_masks") if k in d}

    def width(points):
        return masks["reference_mask"].shape[1] if "reference_mask" in masks else int(np.floor(points[:, 0].max())) + 1

    pts = np.array(seq.points, float)
    vecs = {k: np.array(d[k], float) for k in ("displacement", "velocity") if k in d}
    if mirror:
        pts[:, 0] = width(pts) - 1 - pts[:, 0]
        for v in vecs.values():
            v[..., 0] = -v[..., 0]
        masks = {k: m[..., ::-1] for k, m in masks.items()}
    for _ in range(int(quarter_turns) % 4):
        pts = np.column_stack([pts[:, 1], width(pts) - 1 - pts[:, 0]])
        vecs = {k: np.stack([v[..., 1], -v[..., 0]], axis=-1) for k, v in vecs.items()}
        masks = {k: np.rot90(m, axes=(m.ndim - 2, m.ndim - 1)) for k, m in masks.items()}
    pts = pts + np.array([sx, sy], float)
    pad = ((sy, 0), (sx, 0))
    masks = {k: np.pad(m, ((0, 0),) * (m.ndim - 2) + pad) for k, m in masks.items()}
    d.update(seq.extra)
    d.update(points=pts, **vecs, **{k: np.ascontiguousarray(m) for k, m in masks.items()})
    return make_sequence(**d)


def _even_spacing(frame_times_s, n_frames: int):
    """The spacing (s) of evenly spaced frame times, or None: a sequence without ``frame_interval``
    takes it from its ``frame_times_s`` (DENSE gives each frame's time after the encoding) when they
    are ``n_frames`` finite, increasing times whose longest and shortest steps differ by under 1% of
    their median; uneven times give None (the frame interval stays unrecorded, and the reports say
    so)."""
    t = np.asarray(frame_times_s, float)
    if t.shape != (n_frames,) or n_frames < 2 or not np.all(np.isfinite(t)):
        return None
    dt = np.diff(t)
    step = float(np.median(dt))
    if step <= 0 or np.ptp(dt) > 0.01 * step:
        return None
    return step
