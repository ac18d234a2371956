"""Third-party data sets: found in a data directory, or fetched from their original repositories.

No third-party data file ships with sfem_filters. A data set is looked for, in this order:

1. the data directory: the ``data_dir`` argument if given, else the environment variable
   ``SFEM_FILTERS_DATA`` (the argument replaces the variable, it is not searched beside it);
2. the download cache (:func:`cache_dir`: ``pooch.os_cache("sfem_filters")``, or the
   ``cache_dir`` argument), where :func:`fetch` puts what it downloads.

Both are laid out alike (the layout of the project's ``shared/data``)::

    <folder>/dense/subject_a.npz                      "subject_a"
    <folder>/dense_sim/LICENSE                        the DENSE-Sim MIT licence, kept with its cases
    <folder>/dense_sim/invivo_subject_1/...           "dense_sim/invivo_subject_1"
    <folder>/dense_sim/phantom_subject_1/...          "dense_sim/phantom_subject_1"

Registered data sets (:data:`DATASETS`):

``"subject_a"``
    One mid-ventricular short-axis slice of a human left ventricle imaged with cine DENSE MRI, as
    a sequence file (see :mod:`sfem_filters.cardiac.sequence`): 332 myocardial pixels, 35 frames,
    displacements in pixels. Source: the example training case of StrainNet (Wang et al.),
    ``data/train/0001/{input,label}.mat`` of GitHub ``EpsteinLabUVA/StrainNet`` at commit
    36cf435; :func:`fetch` downloads the two files and converts them with
    :func:`strainnet_sequence` without changing any value. That repository has no licence: the
    data may be read from there, not redistributed, which is why they are not in the package.
``"dense_sim/invivo_subject_1"``, ``"dense_sim/phantom_subject_1"``
    Two simulated cine DENSE cases with ground-truth Lagrangian strain (DENSE-Sim, Barbaroux et
    al., JCMR 2025): folders with ``phase_x.npy``, ``phase_y.npy``, ``magnitude.npy``,
    ``LV_mask_time_lowres.npy``, ``GT_Ecc.npy``, ``GT_Err.npy`` and ``config.yaml``, from GitHub
    ``Hbarbaroux/DENSE_Sim`` at commit 84fa296, ``data_samples/DENSE_images/{invivo,phantom}/
    subject_1/``. MIT licence: its notice (the repository's ``LICENSE``) must stay with any copy,
    so :func:`fetch` puts it in ``dense_sim/LICENSE`` and :func:`dataset_path` finds a case only
    where that notice is beside it.

Every downloaded file is checked against its SHA-256 (by pooch) before it is used.

Examples
--------
>>> from sfem_filters import datasets
>>> sorted(datasets.DATASETS)
['dense_sim/invivo_subject_1', 'dense_sim/phantom_subject_1', 'subject_a']
>>> datasets.DATASETS["subject_a"].source.url("data/train/0001/label.mat")   # doctest: +ELLIPSIS
'https://raw.githubusercontent.com/EpsteinLabUVA/StrainNet/36cf435...1a7/data/train/0001/label.mat'
>>> path = datasets.dataset_path("subject_a")               # needs the data   # doctest: +SKIP
>>> path = datasets.fetch("dense_sim/phantom_subject_1")    # needs the network   # doctest: +SKIP
"""
from __future__ import annotations

import os
import posixpath
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pooch
import scipy.io

__all__ = ["ENV_VAR", "Source", "RemoteFile", "Dataset", "DATASETS", "DatasetNotFoundError", "data_dir", "cache_dir",
           "dataset_path", "fetch", "how_to_get", "strainnet_sequence", "write_strainnet_sequence"]

ENV_VAR = "SFEM_FILTERS_DATA"


class DatasetNotFoundError(FileNotFoundError):
    """A registered data set is in neither the data directory nor the download cache; the message
    says where it was looked for and how to get it."""


@dataclass(frozen=True)
class Source:
    """A public GitHub repository pinned at one commit, and the terms its data come under."""

    repository: str     # "owner/name" on GitHub
    commit: str         # 40 hex digits
    licence: str        # one sentence: the licence, or that there is none and what that allows

    def url(self, path: str) -> str:
        """Raw download URL of ``path`` (a file of the repository) at the pinned commit."""
        return f"https://raw.githubusercontent.com/{self.repository}/{self.commit}/{path}"


@dataclass(frozen=True)
class RemoteFile:
    """One file to download: its path in the source repository, where it goes below the cache
    folder (the data-directory layout), and its SHA-256 (64 hex digits)."""

    remote: str
    local: str
    sha256: str


@dataclass(frozen=True)
class Dataset:
    """A registered data set.

    ``path`` is where it lies below a data directory or the cache (a file, or a case folder);
    ``required`` lists the paths (relative to the same root) that must all be present for it to
    count as found, licence notices included; ``build``, if set, makes ``path`` from the
    downloaded files (``build(root)``, ``root`` the cache folder).
    """

    name: str
    path: str
    source: Source
    downloads: tuple
    required: tuple
    description: str
    build: Callable | None = None


# ------------------------------------------------------------------ StrainNet: the DENSE slice "subject_a"
STRAINNET = Source("EpsteinLabUVA/StrainNet", "36cf43506880ce24c46d7b9bd37dfbd4ff1da1a7",
                   "none: the repository has no licence file, so the data may be read from there, not "
                   "redistributed (this is why sfem_filters does not ship them)")
_STRAINNET_RAW = "strainnet/36cf43506880ce24c46d7b9bd37dfbd4ff1da1a7/data/train/0001"
MASK_SOURCE = "dense-magnitude"


def _loadmat(name: str, path, key: str) -> np.ndarray:
    try:
        data = scipy.io.loadmat(os.fspath(path))
    except (OSError, ValueError, TypeError, scipy.io.matlab.MatReadError) as exc:
        raise ValueError(f"{name}: not a readable MATLAB .mat file {os.fspath(path)!r} ({exc})") from None
    if key not in data:
        found = sorted(k for k in data if not k.startswith("__"))
        raise ValueError(f"{name}: expected a variable {key!r} in {os.fspath(path)!r}; found {found}")
    return np.asarray(data[key])


def strainnet_sequence(input_mat, label_mat) -> dict:
    """The DENSE slice of a StrainNet case folder as the arrays of a sequence file, no value changed.

    Parameters
    ----------
    input_mat : path
        StrainNet's ``input.mat``: variable ``input``, (1, H, W, F), the myocardium mask of each
        frame (0/1), segmented from the DENSE magnitude images.
    label_mat : path
        StrainNet's ``label.mat``: variable ``label``, (2, H, W, F), the measured Lagrangian
        displacement (dx, dy) of each pixel at each frame, in pixels; zero outside the myocardium.

    Returns
    -------
    dict
        ``points`` (P, 2) float: (x = column, y = row) of the pixels where the label is non-zero in
        any component and frame, in row-major order, in pixels; ``displacement`` (F, P, 2) float:
        ``label[:, y, x, t]`` of each point, in pixels; ``reference_mask`` (H, W) bool: those
        pixels; ``frame_masks`` (F, H, W) bool; ``mask_source``: ``"dense-magnitude"``.
    """
    masks = _loadmat("input_mat", input_mat, "input")
    label = _loadmat("label_mat", label_mat, "label")
    if label.ndim != 4 or label.shape[0] != 2:
        raise ValueError(f"label_mat: expected 'label' of shape (2, H, W, F), got {label.shape}")
    if masks.shape != (1,) + label.shape[1:]:
        raise ValueError(f"input_mat: expected 'input' of shape (1, H, W, F) = {(1,) + label.shape[1:]} "
                         f"(that of the label), got {masks.shape}")
    if not np.all(np.isfinite(label)):
        raise ValueError("label_mat: expected finite displacements, found NaN or infinity")
    if not np.all((masks == 0) | (masks == 1)):
        raise ValueError("input_mat: expected masks of 0 and 1 only")
    support = np.any(label != 0, axis=(0, 3))
    if not support.any():
        raise ValueError("label_mat: every displacement is zero: no myocardium to list")
    rows, cols = np.nonzero(support)                              # row-major order
    displacement = np.transpose(label[:, rows, cols, :], (2, 1, 0)).astype(float)   # (F, P, 2)
    return {"points": np.column_stack([cols, rows]).astype(float),
            "displacement": displacement,
            "reference_mask": support,
            "frame_masks": np.moveaxis(masks[0] != 0, -1, 0),
            "mask_source": np.array(MASK_SOURCE)}


def write_strainnet_sequence(input_mat, label_mat, out) -> str:
    """Write :func:`strainnet_sequence` of the two files as a compressed ``.npz`` at ``out``
    (through a temporary file, so that a partial file never stands at ``out``); returns ``out``."""
    arrays = strainnet_sequence(input_mat, label_mat)
    out = os.fspath(out)
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    tmp = out + ".part.npz"
    np.savez_compressed(tmp, **arrays)
    os.replace(tmp, out)
    return out


def _build_subject_a(root: str) -> None:
    raw = os.path.join(root, _STRAINNET_RAW)
    write_strainnet_sequence(os.path.join(raw, "input.mat"), os.path.join(raw, "label.mat"),
                             os.path.join(root, "dense", "subject_a.npz"))


# ------------------------------------------------------------------ DENSE-Sim cases
DENSE_SIM = Source("Hbarbaroux/DENSE_Sim", "84fa296da434f1e245790c159b2be507d5950184",
                   "MIT (Copyright (c) 2024 Hugo Barbaroux); its notice, the repository's LICENSE, must be "
                   "kept with any copy")
DENSE_SIM_FILES = ("phase_x.npy", "phase_y.npy", "magnitude.npy", "LV_mask_time_lowres.npy", "GT_Ecc.npy",
                   "GT_Err.npy", "config.yaml")
_DENSE_SIM_LICENCE = RemoteFile("LICENSE", "dense_sim/LICENSE",
                                "a445a7d4ba1dc8994e061a42f3acd9afc8d950213d4c7a1d0fef50b9b8a7792f")
_DENSE_SIM_SHA256 = {
    "invivo": ("75c21b95644550e2a7d8ff884048b7c17f5fe4ea3da06e5f337f7227ba185230",
               "054a069430e02c4c270510d76eae5f5f60aa8d243cd3e5c7bcc178f3d54f230a",
               "080658dd656240579cd7bdd32453c9a20676dba2b9144e7c5f653c56d10a01f0",
               "835ea3c18ca7685b6a6a3dfe61054e06a4357680e5e1734ae7859936e8d90f7a",
               "daedaf37f51d83967c1dcd29ac0176fc6bf81b734bbab53cf216ea5f5f14525b",
               "bf2078b3b9a628c624ba5b5603988fce06f6892b1b5fd27df7f286126fab7566",
               "d9b3806800327d9fe4b590c062818c9db925802f9018d2efe77f1bc16d8cb618"),
    "phantom": ("e07c33a8a2e347524d5a39f4f4bf328e922321ab06b038bb8955bd390ef32531",
                "348da1002d7b2eb8f0fbb15b3edc0d0f92b9a54db5eb94becbc364da824b0b17",
                "8a4bae54ac0d4cbe74d4f92ca5326c7faa3a360eb82cb1de0531dfa6d926ab71",
                "d0fd102f2a2a098ab488677a32703ca22069874c6ada2b31d1de18e78c272447",
                "d36f5a49fa345d0b2ffe12935e0c58303fd5c24654ee0f9c23138d6c14f53d72",
                "34046f60e13600d5602f8f44266cd39ef010c8556f2f029b4f6cdf9de4b831cd",
                "2df3b0ef2cb87e95d8e754d1a6846b00fbba509c37a30b1ac97bcf673930312c"),
}


def _dense_sim_case(kind: str) -> Dataset:
    case = f"{kind}_subject_1"
    files = tuple(RemoteFile(f"data_samples/DENSE_images/{kind}/subject_1/{f}", f"dense_sim/{case}/{f}", h)
                  for f, h in zip(DENSE_SIM_FILES, _DENSE_SIM_SHA256[kind]))
    return Dataset(f"dense_sim/{case}", f"dense_sim/{case}", DENSE_SIM, files + (_DENSE_SIM_LICENCE,),
                   tuple(f.local for f in files) + (_DENSE_SIM_LICENCE.local,),
                   f"DENSE-Sim case {case} (simulated cine DENSE images with ground-truth strain), a folder")


DATASETS = {d.name: d for d in (
    Dataset("subject_a", "dense/subject_a.npz", STRAINNET,
            (RemoteFile("data/train/0001/input.mat", f"{_STRAINNET_RAW}/input.mat",
                        "d2db3824b0433713baf93b46a3d9c868b60cf3cfd8373bad76ded708ff8049fb"),
             RemoteFile("data/train/0001/label.mat", f"{_STRAINNET_RAW}/label.mat",
                        "193c14f19d4a62d01082b2eddc55638b02dd95104ca32b0d34d75fd224405a2f")),
            ("dense/subject_a.npz",),
            "the measured DENSE slice subject_a (StrainNet's example training case), a sequence .npz",
            _build_subject_a),
    _dense_sim_case("invivo"),
    _dense_sim_case("phantom"),
)}


# ------------------------------------------------------------------ where data sets are looked for
def _data_dir(path) -> str | None:
    value = os.fspath(path) if path is not None else os.environ.get(ENV_VAR, "")
    return os.path.abspath(os.path.expanduser(value)) if value else None


def _cache_dir(path) -> str:
    return os.path.abspath(os.fspath(path)) if path is not None else str(pooch.os_cache("sfem_filters"))


def data_dir(path=None) -> str | None:
    """The data directory: ``path`` if given, else the environment variable ``SFEM_FILTERS_DATA``,
    else None. Returned as an absolute path (it need not exist)."""
    return _data_dir(path)


def cache_dir(path=None) -> str:
    """The download cache: ``path`` if given, else pooch's cache folder for ``sfem_filters``
    (``pooch.os_cache("sfem_filters")``, e.g. ``~/.cache/sfem_filters`` on Linux)."""
    return _cache_dir(path)


def _dataset(name) -> Dataset:
    if name not in DATASETS:
        raise ValueError(f"name: expected one of {sorted(DATASETS)}, got {name!r}")
    return DATASETS[name]


def _missing(ds: Dataset, root: str) -> list:
    return [r for r in ds.required if not os.path.isfile(os.path.join(root, r))]


def how_to_get(name: str) -> str:
    """The instructions the not-found error gives for data set ``name``."""
    ds = _dataset(name)
    groups = {}
    for f in ds.downloads:
        folder, base = posixpath.split(f.remote)
        groups.setdefault(folder, []).append(base)
    files = "; ".join(f"{d}/ ({', '.join(b)})" if d else ", ".join(b) for d, b in groups.items())
    lines = [
        "To get it, either",
        f"  - set {ENV_VAR} to a folder laid out as <folder>/{ds.path}"
        + (" (with <folder>/dense_sim/LICENSE beside the case)" if ds.source is DENSE_SIM else "")
        + ", or pass data_dir=<folder>; or",
        f"  - download it from its original repository (needs network access): call "
        f'sfem_filters.datasets.fetch("{name}") in Python, or pass --download on the sfem-filters command line.',
        f"Source: https://github.com/{ds.source.repository} at commit {ds.source.commit}, files {files}.",
        f"Licence: {ds.source.licence}.",
    ]
    return "\n".join(lines)


def dataset_path(name: str, *, data_dir=None, download: bool = False, cache_dir=None) -> str:
    """Path of a registered data set: the ``.npz`` file of ``"subject_a"``, the case folder of a
    DENSE-Sim case.

    Parameters
    ----------
    name : str
        A key of :data:`DATASETS`.
    data_dir : path, optional
        Folder with the data-directory layout; replaces ``SFEM_FILTERS_DATA``.
    download : bool
        If the data set is in neither the data directory nor the cache, :func:`fetch` it into the
        cache (network access needed) instead of raising.
    cache_dir : path, optional
        The download cache (default :func:`cache_dir`).

    Raises
    ------
    ValueError
        ``name`` is not registered.
    DatasetNotFoundError
        (a ``FileNotFoundError``) not found and ``download`` is False: the message lists where it
        was looked for, what was missing there, and how to get it. A DENSE-Sim case whose licence
        notice (``dense_sim/LICENSE``) is not beside it does not count as found.
    """
    ds = _dataset(name)
    given = _data_dir(data_dir)
    places = []
    if given is not None:
        places.append((f"data_dir={given}" if data_dir is not None else f"{ENV_VAR}={given}", given))
    cache = _cache_dir(cache_dir)
    places.append((f"download cache {cache}", cache))
    looked = []
    for label, root in places:
        if not os.path.isdir(root):
            looked.append(f"{label}: no such folder")
            continue
        missing = _missing(ds, root)
        if not missing:
            return os.path.join(root, ds.path)
        looked.append(f"{label}: missing {', '.join(missing)}")
    if download:
        return fetch(name, cache_dir=cache_dir)
    where = "" if given is not None else f" ({ENV_VAR} is not set)"
    raise DatasetNotFoundError(
        f"data set {name!r} not found{where}; looked in:\n" + "".join(f"  - {line}\n" for line in looked)
        + f"{name!r} is {ds.description}; it is not shipped with sfem_filters.\n" + how_to_get(name))


def fetch(name: str, *, cache_dir=None, downloader=None, progressbar: bool = False) -> str:
    """Download a registered data set from its original repository into the cache; returns its path.

    Each file comes from ``https://raw.githubusercontent.com/<repository>/<commit>/<path>`` at the
    pinned commit through :func:`pooch.retrieve`, which checks its SHA-256 and keeps it in the
    cache (a file already there with the right hash is not downloaded again). ``"subject_a"`` is
    then converted to a sequence file by :func:`strainnet_sequence`; a DENSE-Sim case gets the
    repository's MIT ``LICENSE`` in its parent folder (``dense_sim/LICENSE``). Nothing is
    downloaded if the data set is already complete in the cache.

    Parameters
    ----------
    name : str
        A key of :data:`DATASETS`.
    cache_dir : path, optional
        Where to put the files (default :func:`cache_dir`), in the data-directory layout; a folder
        given here can be used as ``SFEM_FILTERS_DATA``.
    downloader : callable, optional
        A pooch downloader ``downloader(url, output_file, pooch)`` (default: pooch's choice for
        HTTPS).
    progressbar : bool
        Show pooch's progress bar (needs tqdm).

    Raises
    ------
    DatasetNotFoundError
        When a file cannot be downloaded (no network, the host refuses): the message says which
        and how else to get the data set (:func:`how_to_get`).

    See Also
    --------
    dataset_path : the data directory (``SFEM_FILTERS_DATA``) and the cache first, then, with
        ``download=True``, this download; what a script should call.
    """
    ds = _dataset(name)
    root = _cache_dir(cache_dir)
    if not _missing(ds, root):
        return os.path.join(root, ds.path)
    for f in ds.downloads:
        folder, fname = os.path.split(os.path.join(root, f.local))
        url = ds.source.url(f.remote)
        try:
            pooch.retrieve(url, known_hash=f"sha256:{f.sha256}", fname=fname, path=folder,
                           downloader=downloader, progressbar=progressbar)
        except OSError as exc:          # requests' errors are OSErrors: no network, a refused host, HTTP 404
            reason = str(exc).splitlines()[0][:200] if str(exc) else type(exc).__name__
            raise DatasetNotFoundError(
                f"data set {name!r}: could not download {url} into {folder} ({type(exc).__name__}: {reason}).\n"
                + how_to_get(name)) from exc
    if ds.build is not None:
        ds.build(root)
    missing = _missing(ds, root)
    if missing:                                                   # a registry defect, not a user error
        raise RuntimeError(f"fetch({name!r}): after the download, still missing {missing} in {root}")
    return os.path.join(root, ds.path)
