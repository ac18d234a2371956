"""The strain-variants claim's transforms (validation/strain_variants.py): the same heart, the same truth."""
import os
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from sfem_filters.imaging import read_dense_sim, truth_at_points  # noqa: E402
from sfem_filters.cardiac.strain_route import unusable_mask_frames  # noqa: E402
from validation.strain_variants import CUT_EVERY, CUT_FIRST, every_other_frame, masks_cut, mirrored, transposed  # noqa: E402,E501

DATA = Path(os.environ.get("SFEM_FILTERS_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
CASE = DATA / "dense_sim" / "phantom_subject_1"
pytestmark = pytest.mark.skipif(not (CASE / "config.yaml").is_file(), reason="the DENSE-Sim case is not here")


@pytest.fixture(scope="module")
def case():
    return read_dense_sim(CASE)


def _sorted_truth(c):
    """The truth at the reference pixels, as a multiset per frame (the transforms permute the pixels)."""
    return [np.sort(t, axis=1) for t in truth_at_points(c)]


@pytest.mark.parametrize("turn", [mirrored, transposed])
def test_a_turn_keeps_the_truth_and_undoes_itself(case, turn):
    t = turn(case)
    assert t.phases.shape == case.phases.shape and np.all(np.abs(t.phases) <= np.pi)
    for a, b in zip(_sorted_truth(case), _sorted_truth(t)):
        assert np.array_equal(a, b, equal_nan=True)
    back = turn(t)
    for name in ("magnitude", "masks", "truth_ecc", "truth_err"):
        assert np.array_equal(getattr(back, name), getattr(case, name), equal_nan=True)
    # the phase back to itself up to the wrap at +-pi (a phase of exactly -pi may come back as +pi)
    assert np.allclose(np.exp(1j * back.phases), np.exp(1j * case.phases), atol=1e-6)


def test_the_mirror_flips_x_and_the_x_encoding(case):
    m = mirrored(case)
    W = case.magnitude.shape[-1]
    assert np.array_equal(m.masks[0][:, ::-1], case.masks[0])
    f, r, c = 3, *np.argwhere(case.masks[0])[0]
    assert np.isclose(np.exp(1j * m.phases[0, f, r, W - 1 - c]), np.exp(-1j * case.phases[0, f, r, c]))
    assert m.phases[1, f, r, W - 1 - c] == case.phases[1, f, r, c]


def test_half_the_frame_rate_keeps_every_second_frame(case):
    h = every_other_frame(case)
    keep = np.arange(0, len(case.frame_times_s), 2)
    assert np.array_equal(h.frame_times_s, case.frame_times_s[keep])
    assert np.array_equal(h.phases, case.phases[:, keep])
    assert np.array_equal(h.masks[0], case.masks[0]) and np.array_equal(h.masks[1:], case.masks[1:][keep])
    assert np.array_equal(h.truth_err, case.truth_err[keep], equal_nan=True)


def test_the_cut_masks_are_no_rings_where_cut_and_nothing_else_changes(case):
    c = masks_cut(case)
    frames = np.arange(CUT_FIRST, case.n_frames, CUT_EVERY)
    assert unusable_mask_frames(c.masks)[0] == list(frames + 1)        # no mending bridges the cut
    assert unusable_mask_frames(case.masks)[0] == []
    others = np.setdiff1d(np.arange(case.n_frames + 1), frames + 1)
    assert np.array_equal(c.masks[others], case.masks[others])
    assert np.all(c.masks[frames + 1] <= case.masks[frames + 1])        # only tissue taken away
    assert (case.masks[frames + 1] & ~c.masks[frames + 1]).sum(axis=(1, 2)).min() >= 3 * 3
    for name in ("phases", "magnitude", "truth_ecc", "truth_err"):
        assert np.array_equal(getattr(c, name), getattr(case, name), equal_nan=True)
