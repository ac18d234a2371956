"""Third-party data sets stay out of the package (issue 42 item 6): lookup, registry, download.

No test here touches the network: downloads go through a pooch downloader that copies from a
local folder (pooch has no file:// protocol; a custom downloader is its documented hook), so the
registry's URLs, pooch's SHA-256 checks and the cache layout are exercised as on a user's machine.
"""
import dataclasses
import hashlib
import os
import pathlib
import re
import shutil

import numpy as np
import pytest
import requests
import scipy.io

from sfem_filters import datasets
from sfem_filters.cardiac.sequence import example_path, load_sequence
from sfem_filters.cli import main

PACKAGE = pathlib.Path(datasets.__file__).resolve().parent
CASES = ("dense_sim/invivo_subject_1", "dense_sim/phantom_subject_1")


def sha256(path) -> str:
    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


@pytest.fixture(scope="module")
def published():
    """Root folder (data directory or cache) of each data set found, looked up before any test hides
    them (a module fixture is set up before the function fixtures)."""
    out = {}
    for name, ds in datasets.DATASETS.items():
        try:
            out[name] = datasets.dataset_path(name)[: -len(ds.path) - 1]
        except datasets.DatasetNotFoundError:
            pass
    return out


@pytest.fixture
def no_data(monkeypatch, tmp_path):
    """Neither a data directory nor anything in the download cache (an empty temporary one)."""
    monkeypatch.delenv(datasets.ENV_VAR, raising=False)
    cache = tmp_path / "cache"
    monkeypatch.setattr(datasets.pooch, "os_cache", lambda project: cache / project)
    return cache / "sfem_filters"


def touch(root, *relpaths):
    for r in relpaths:
        p = pathlib.Path(root, r)
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(b"x")
    return str(root)


class LocalCopies:
    """A pooch downloader serving each registered URL from a local folder with the data-directory
    layout (the registered file's ``local`` path), or with the bytes ``corrupt`` when given."""

    def __init__(self, name, folder, corrupt=None):
        self.by_url = {datasets.DATASETS[name].source.url(f.remote): os.path.join(folder, f.local)
                       for f in datasets.DATASETS[name].downloads}
        self.corrupt, self.urls = corrupt, []

    def __call__(self, url, output_file, pooch):
        self.urls.append(url)
        if self.corrupt is not None:
            pathlib.Path(output_file).write_bytes(self.corrupt)
        else:
            shutil.copyfile(self.by_url[url], output_file)


# ------------------------------------------------------------------ nothing third-party in the package
def test_the_package_holds_no_data_file():
    found = [p for p in PACKAGE.rglob("*") if p.suffix in (".npz", ".npy", ".mat", ".dns", ".dcm", ".nii")]
    assert found == []


# ------------------------------------------------------------------ the registry
def test_registry_pins_each_file_by_commit_and_sha256():
    assert set(datasets.DATASETS) == {"subject_a", *CASES}
    for name, ds in datasets.DATASETS.items():
        assert ds.name == name and re.fullmatch(r"[0-9a-f]{40}", ds.source.commit)
        assert ds.downloads and ds.required and ds.path
        for f in ds.downloads:
            assert re.fullmatch(r"[0-9a-f]{64}", f.sha256), (name, f)
            url = ds.source.url(f.remote)
            assert url == f"https://raw.githubusercontent.com/{ds.source.repository}/{ds.source.commit}/{f.remote}"
            assert not os.path.isabs(f.local) and ".." not in f.local.split("/")
    assert datasets.DATASETS["subject_a"].source.repository == "EpsteinLabUVA/StrainNet"
    assert datasets.DATASETS["subject_a"].source.commit == "36cf43506880ce24c46d7b9bd37dfbd4ff1da1a7"
    assert [f.remote for f in datasets.DATASETS["subject_a"].downloads] == ["data/train/0001/input.mat",
                                                                           "data/train/0001/label.mat"]
    for kind, name in zip(("invivo", "phantom"), CASES):
        ds = datasets.DATASETS[name]
        assert ds.source.repository == "Hbarbaroux/DENSE_Sim"
        assert ds.source.commit == "84fa296da434f1e245790c159b2be507d5950184"
        remote = {f.remote for f in ds.downloads}
        assert remote == {f"data_samples/DENSE_images/{kind}/subject_1/{f}" for f in datasets.DENSE_SIM_FILES} \
            | {"LICENSE"}
        assert "dense_sim/LICENSE" in ds.required                  # the licence notice stays with the case
        assert {f.local for f in ds.downloads} == set(ds.required)
        assert len({f.sha256 for f in ds.downloads}) == len(ds.downloads)


@pytest.mark.needs_data(*CASES)
def test_registry_hashes_are_those_of_the_published_files(published):
    """The shared copies are byte-identical to the repository's files at the pinned commit."""
    for name in CASES:
        for f in datasets.DATASETS[name].downloads:
            assert sha256(os.path.join(published[name], f.local)) == f.sha256, f.local


# ------------------------------------------------------------------ where data sets are found
def test_data_dir_argument_then_environment(monkeypatch, tmp_path):
    monkeypatch.delenv(datasets.ENV_VAR, raising=False)
    assert datasets.data_dir() is None
    monkeypatch.setenv(datasets.ENV_VAR, str(tmp_path / "env"))
    assert datasets.data_dir() == str(tmp_path / "env")
    assert datasets.data_dir(tmp_path / "arg") == str(tmp_path / "arg")
    monkeypatch.setenv(datasets.ENV_VAR, "")
    assert datasets.data_dir() is None


def test_lookup_order_argument_environment_cache(monkeypatch, tmp_path, no_data):
    rel = "dense/subject_a.npz"
    arg, env, cache = touch(tmp_path / "arg", rel), touch(tmp_path / "env", rel), touch(no_data, rel)
    monkeypatch.setenv(datasets.ENV_VAR, env)
    assert datasets.dataset_path("subject_a", data_dir=arg) == os.path.join(arg, rel)
    assert datasets.dataset_path("subject_a") == os.path.join(env, rel)
    assert example_path() == os.path.join(env, rel)
    os.remove(os.path.join(env, rel))
    assert datasets.dataset_path("subject_a") == os.path.join(cache, rel)
    # the argument replaces the variable: a data_dir without the file falls through to the cache only
    monkeypatch.setenv(datasets.ENV_VAR, touch(tmp_path / "env2", rel))
    assert datasets.dataset_path("subject_a", data_dir=tmp_path / "empty") == os.path.join(cache, rel)
    monkeypatch.delenv(datasets.ENV_VAR)
    assert datasets.dataset_path("subject_a", cache_dir=tmp_path / "env2") == str(tmp_path / "env2" / rel)


def test_missing_data_set_error_says_how_to_get_it(no_data, tmp_path):
    with pytest.raises(datasets.DatasetNotFoundError) as err:
        datasets.dataset_path("subject_a")
    assert isinstance(err.value, FileNotFoundError)
    text = str(err.value)
    for needle in ("'subject_a' not found (SFEM_FILTERS_DATA is not set)", f"download cache {no_data}: no such folder",
                   "set SFEM_FILTERS_DATA to a folder laid out as <folder>/dense/subject_a.npz",
                   'sfem_filters.datasets.fetch("subject_a")', "--download",
                   "https://github.com/EpsteinLabUVA/StrainNet at commit 36cf43506880ce24c46d7b9bd37dfbd4ff1da1a7",
                   "data/train/0001/ (input.mat, label.mat)", "no licence", "not shipped with sfem_filters"):
        assert needle in text, needle
    touch(tmp_path / "d", "dense/other.npz")
    with pytest.raises(FileNotFoundError, match=r"data_dir=.*/d: missing dense/subject_a.npz"):
        example_path(data_dir=tmp_path / "d")
    with pytest.raises(ValueError, match=r"name: expected one of \['dense_sim/invivo_subject_1'"):
        datasets.dataset_path("subject_b")
    with pytest.raises(ValueError, match=r"name: expected one of \['subject_a'\], got 'dense_sim/"):
        example_path("dense_sim/invivo_subject_1")                # a case folder is not a sequence file


def test_a_dense_sim_case_counts_only_with_its_licence_beside_it(no_data, tmp_path):
    name = "dense_sim/phantom_subject_1"
    files = [f"{name}/{f}" for f in datasets.DENSE_SIM_FILES]
    root = touch(tmp_path / "d", *files)
    with pytest.raises(datasets.DatasetNotFoundError) as err:
        datasets.dataset_path(name, data_dir=root)
    text = str(err.value)
    assert f"data_dir={root}: missing dense_sim/LICENSE" in text and "MIT" in text
    assert "with <folder>/dense_sim/LICENSE beside the case" in text
    touch(root, "dense_sim/LICENSE")
    assert datasets.dataset_path(name, data_dir=root) == os.path.join(root, name)
    os.remove(os.path.join(root, files[2]))                         # an incomplete case is not found either
    with pytest.raises(datasets.DatasetNotFoundError, match=f"missing {files[2]}"):
        datasets.dataset_path(name, data_dir=root)


def test_dense_example_without_data_says_how_to_get_it_and_exits_2(no_data, capsys):
    assert main(["dense", "example", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("sfem-filters dense: error: data set 'subject_a' not found")
    assert "SFEM_FILTERS_DATA" in err and 'fetch("subject_a")' in err and "EpsteinLabUVA/StrainNet" in err


# ------------------------------------------------------------------ downloads (pooch, no network)
@pytest.mark.needs_data("dense_sim/phantom_subject_1")
def test_fetch_downloads_checks_and_caches_a_case_with_its_licence(published, no_data):
    name = "dense_sim/phantom_subject_1"
    served = LocalCopies(name, published[name])
    path = datasets.fetch(name, downloader=served)
    assert path == os.path.join(no_data, name)
    assert sorted(served.urls) == sorted(served.by_url)            # every registered URL, once
    assert sorted(os.listdir(path)) == sorted(datasets.DENSE_SIM_FILES)
    licence = os.path.join(no_data, "dense_sim", "LICENSE")
    assert open(licence).read().startswith("MIT License")
    assert datasets.dataset_path(name) == path                     # found in the cache now
    assert datasets.fetch(name, downloader=served) == path and len(served.urls) == len(served.by_url)  # cached
    truth = np.load(os.path.join(published[name], name, "GT_Err.npy"))
    np.testing.assert_array_equal(np.load(os.path.join(path, "GT_Err.npy")), truth)


@pytest.mark.needs_data("dense_sim/invivo_subject_1")
def test_dataset_path_downloads_when_asked_and_a_bad_download_is_refused(published, no_data, monkeypatch):
    """dataset_path(download=True) has no downloader argument (it uses pooch's HTTPS one): pooch's
    retrieve is wrapped here to pass the local one."""
    name = "dense_sim/invivo_subject_1"
    retrieve = datasets.pooch.retrieve

    def through(downloader):
        return lambda *args, **kwargs: retrieve(*args, **{**kwargs, "downloader": downloader})
    bad = LocalCopies(name, published[name], corrupt=b"not the published file")
    monkeypatch.setattr(datasets.pooch, "retrieve", through(bad))
    with pytest.raises(ValueError, match=r"SHA256 hash of downloaded file \(phase_x.npy\) does not match"):
        datasets.dataset_path(name, download=True)
    assert len(bad.urls) == 1
    assert not any(n.endswith(".npy") for _, _, ns in os.walk(no_data) for n in ns)   # nothing kept
    good = LocalCopies(name, published[name])
    monkeypatch.setattr(datasets.pooch, "retrieve", through(good))
    assert datasets.dataset_path(name, download=True) == os.path.join(no_data, name)
    assert len(good.urls) == len(datasets.DATASETS[name].downloads)


def test_a_failed_download_is_one_clear_error_saying_how_else_to_get_it(no_data):
    """No network (a downloader that raises what requests raises offline): the error names the data
    set and the URL, and says how to get the data otherwise; no traceback of requests is needed."""
    import requests

    def offline(url, output_file, pooch_):
        raise requests.exceptions.ConnectionError(f"HTTPSConnectionPool: Max retries exceeded with url: {url}")
    name = "dense_sim/invivo_subject_1"
    with pytest.raises(datasets.DatasetNotFoundError) as exc:
        datasets.fetch(name, downloader=offline)
    text = str(exc.value)
    assert f"data set {name!r}: could not download https://raw.githubusercontent.com/" in text
    assert "ConnectionError" in text and "SFEM_FILTERS_DATA" in text and "Hbarbaroux/DENSE_Sim" in text
    assert not any(n.endswith(".npy") for _, _, ns in os.walk(no_data) for n in ns)


def write_strainnet_case(folder, label, masks):
    folder.mkdir(parents=True, exist_ok=True)
    scipy.io.savemat(folder / "input.mat", {"input": masks})
    scipy.io.savemat(folder / "label.mat", {"label": label})
    return folder / "input.mat", folder / "label.mat"


def small_case(rng):
    """A 5 x 6 image, 3 frames: label non-zero on 4 pixels (one only at the last frame)."""
    label = np.zeros((2, 5, 6, 3))
    support = [(1, 2), (1, 4), (3, 0), (4, 5)]
    for r, c in support[:3]:
        label[:, r, c, :] = rng.normal(size=(2, 3))
    label[1, 4, 5, 2] = -0.5
    masks = (rng.uniform(size=(1, 5, 6, 3)) < 0.5).astype(np.uint8)
    return label, masks, support


def test_strainnet_conversion_keeps_every_value_in_row_major_order(tmp_path):
    label, masks, support = small_case(np.random.default_rng(3))
    out = datasets.strainnet_sequence(*write_strainnet_case(tmp_path, label, masks))
    assert sorted(out) == ["displacement", "frame_masks", "mask_source", "points", "reference_mask"]
    np.testing.assert_array_equal(out["points"], [(c, r) for r, c in support])        # x = column, y = row
    for i, (r, c) in enumerate(support):
        np.testing.assert_array_equal(out["displacement"][:, i, 0], label[0, r, c, :])
        np.testing.assert_array_equal(out["displacement"][:, i, 1], label[1, r, c, :])
    assert out["reference_mask"].sum() == 4 and all(out["reference_mask"][r, c] for r, c in support)
    np.testing.assert_array_equal(out["frame_masks"], np.moveaxis(masks[0] == 1, -1, 0))
    assert str(out["mask_source"]) == "dense-magnitude"


@pytest.mark.parametrize("label_shape, mask_shape, match", [
    ((3, 5, 6, 3), (1, 5, 6, 3), r"label_mat: expected 'label' of shape \(2, H, W, F\), got \(3, 5, 6, 3\)"),
    ((2, 5, 6, 3), (1, 5, 6, 4), r"input_mat: expected 'input' of shape \(1, H, W, F\) = \(1, 5, 6, 3\)"),
])
def test_strainnet_files_of_the_wrong_shape_are_named(tmp_path, label_shape, mask_shape, match):
    with pytest.raises(ValueError, match=match):
        datasets.strainnet_sequence(*write_strainnet_case(tmp_path, np.ones(label_shape), np.ones(mask_shape)))


def test_strainnet_bad_files_are_named(tmp_path):
    (tmp_path / "x.mat").write_text("not a mat file")
    label, masks, _ = small_case(np.random.default_rng(0))
    inp, lab = write_strainnet_case(tmp_path / "ok", label, masks)
    with pytest.raises(ValueError, match="input_mat: not a readable MATLAB .mat file"):
        datasets.strainnet_sequence(tmp_path / "x.mat", lab)
    with pytest.raises(ValueError, match=r"label_mat: expected a variable 'label' in .*; found \['input'\]"):
        datasets.strainnet_sequence(inp, inp)
    with pytest.raises(ValueError, match="label_mat: every displacement is zero"):
        datasets.strainnet_sequence(*write_strainnet_case(tmp_path / "z", 0 * label, masks))


def test_fetch_subject_a_downloads_the_two_mat_files_and_writes_a_sequence(no_data, monkeypatch, tmp_path):
    """The route of "subject_a" on a small stand-in case (the real files need the network): the
    registry entry is the real one with the stand-in's hashes."""
    label, masks, _ = small_case(np.random.default_rng(5))
    remote = tmp_path / "remote"
    raw = remote / datasets._STRAINNET_RAW
    write_strainnet_case(raw, label, masks)
    real = datasets.DATASETS["subject_a"]
    files = tuple(dataclasses.replace(f, sha256=sha256(remote / f.local)) for f in real.downloads)
    monkeypatch.setitem(datasets.DATASETS, "subject_a", dataclasses.replace(real, downloads=files))
    served = LocalCopies("subject_a", remote)
    path = datasets.fetch("subject_a", downloader=served)
    assert path == os.path.join(no_data, "dense", "subject_a.npz") and example_path() == path
    assert served.urls == [real.source.url(f.remote) for f in real.downloads]
    seq = load_sequence(path)
    np.testing.assert_array_equal(seq.displacement, datasets.strainnet_sequence(raw / "input.mat",
                                                                                raw / "label.mat")["displacement"])
    assert not [n for n in os.listdir(os.path.dirname(path)) if n != "subject_a.npz"]   # no partial file left


@pytest.mark.needs_data("subject_a")
def test_strainnet_conversion_reproduces_the_shared_file():
    """Where StrainNet's two .mat files are in the download cache (after ``fetch("subject_a")``
    with network access), their conversion equals the shared ``subject_a.npz`` value for value."""
    real = datasets.DATASETS["subject_a"]
    raw = [os.path.join(datasets.cache_dir(), f.local) for f in real.downloads]
    if not all(os.path.isfile(p) and sha256(p) == f.sha256 for p, f in zip(raw, real.downloads)):
        pytest.skip("StrainNet's input.mat and label.mat are not in the download cache (needs the network once)")
    out = datasets.strainnet_sequence(*raw)
    with np.load(datasets.dataset_path("subject_a")) as shared:
        assert sorted(shared.files) == sorted(out)
        for k in shared.files:
            assert shared[k].dtype == out[k].dtype and np.array_equal(shared[k], out[k]), k
