"""Masks with a defect of a pixel or two are mended into a ring; larger defects stay errors that name the mask.

The cases we are not given may carry masks resampled to a coarse grid; a stray pixel, a pinhole or a
one-pixel cut must not stop the routes (the meshing and the border tracking need one ring around one
cavity), and must not change the anatomy either: the repair gives back the ring the defect was made in.
"""
import os
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy.ndimage import binary_dilation, binary_erosion

from sfem_filters.cardiac.strain_route import image_settings, masks_can_be_fused, unusable_mask_frames
from sfem_filters.imaging import (check_myocardium_mask, mask_borders, read_dense_sim, reference_mask_mismatch,
                                  repair_myocardium_mask)
from sfem_filters.imaging.contours import MAX_REPAIR_FRACTION, mended_masks_summarised

DATA = Path(os.environ.get("SFEM_FILTERS_DATA", Path(__file__).resolve().parents[3] / "shared" / "data"))
CASE = DATA / "dense_sim" / "phantom_subject_1"


def annulus(n=48, cx=23.5, cy=23.5, inner=8.0, outer=13.0):
    yy, xx = np.mgrid[0:n, 0:n]
    d = np.hypot(xx - cx, yy - cy)
    return (d >= inner) & (d <= outer)


rings = st.builds(annulus, cx=st.floats(21.0, 26.0), cy=st.floats(21.0, 26.0), inner=st.floats(6.0, 9.0),
                  outer=st.floats(12.0, 15.0))


def test_a_ring_is_left_as_it_is():
    ring = annulus()
    out, changes = repair_myocardium_mask(ring)
    assert changes == "" and np.array_equal(out, ring)


@settings(max_examples=40, deadline=None)
@given(ring=rings, pick=st.integers(0, 10 ** 6))
def test_a_pinhole_in_the_wall_is_filled(ring, pick):
    inner = np.argwhere(binary_erosion(ring))                 # a pixel of the wall, not on its border
    r, c = inner[pick % len(inner)]
    holed = ring.copy()
    holed[r, c] = False
    out, changes = repair_myocardium_mask(holed)
    assert np.array_equal(out, ring) and "hole" in changes


@settings(max_examples=40, deadline=None)
@given(ring=rings, corner=st.sampled_from([(0, 0), (0, 47), (47, 0), (47, 47), (2, 23), (23, 45)]))
def test_a_stray_pixel_is_removed(ring, corner):
    stray = ring.copy()
    stray[corner] = True
    assert not ring[corner]
    out, changes = repair_myocardium_mask(stray)
    assert np.array_equal(out, ring) and "stray" in changes


@settings(max_examples=40, deadline=None)
@given(ring=rings, angle=st.floats(0.0, 2 * np.pi), width=st.sampled_from([1.0, 1.6]))
def test_a_narrow_cut_through_the_wall_is_closed(ring, angle, width):
    yy, xx = np.mgrid[0:48, 0:48]
    centre = np.argwhere(ring).mean(axis=0)[::-1]
    # the pixels closer than width / 2 to a ray from the centre: a cut one or two pixels wide
    d = np.abs(-(xx - centre[0]) * np.sin(angle) + (yy - centre[1]) * np.cos(angle))
    ahead = (xx - centre[0]) * np.cos(angle) + (yy - centre[1]) * np.sin(angle) > 0
    cut = ring & ahead & (d < width / 2)
    broken = ring & ~cut
    try:
        check_myocardium_mask(broken)
        return                                                # the ray only grazed the ring: no cut made
    except ValueError:
        pass
    out, changes = repair_myocardium_mask(broken)
    check_myocardium_mask(out)
    assert np.all(out[ring & ~cut])                           # the ring's tissue is kept
    assert np.sum(out != ring) <= MAX_REPAIR_FRACTION * ring.sum()
    # a diagonal band may leave the tissue 8-connected across it: then it is pockets of background, filled
    assert ("cut" in changes) or ("hole" in changes)


def _two_cavities():
    m = np.zeros((30, 40), bool)
    m[5:25, 5:35] = True
    m[10:20, 9:18] = m[10:20, 22:31] = False              # two equal cavities: neither is the one
    return m


def _tiny_cavity(pinhole=0):
    m = np.zeros((20, 20), bool)
    m[5:15, 5:15] = True
    m[9, 9] = False                                         # a one-pixel cavity: a ring as check_myocardium_mask has it
    m[12, 12:12 + pinhole] = False                          # and a pinhole as large: which is the cavity?
    return m


@pytest.mark.parametrize("mask, message", [
    (np.zeros((20, 20), bool), "masks\\[4\\]: expected some tissue"),
    (annulus() | annulus(cx=40.0, cy=40.0, inner=0.0, outer=5.0), "masks\\[4\\]: expected one connected piece"),
    (annulus() & (np.mgrid[0:48, 0:48][1] < 24), "masks\\[4\\]: expected a ring around exactly one cavity"),
    (annulus() | annulus(inner=3.0, outer=5.0), "masks\\[4\\]: expected one connected piece"),
    (_two_cavities(), "masks\\[4\\]: expected a ring around exactly one cavity, got 2 enclosed background regions"),
    (_tiny_cavity(pinhole=2), "masks\\[4\\]: .*none clearly the cavity"),
])
def test_larger_defects_stay_errors_naming_the_mask(mask, message):
    with pytest.raises(ValueError, match=message):
        repair_myocardium_mask(mask, "masks[4]")


def test_a_ring_around_a_small_cavity_is_left_as_given():
    m = _tiny_cavity()
    out, changes = repair_myocardium_mask(m)
    assert changes == "" and np.array_equal(out, m)


def test_a_cut_ring_with_a_pinhole_is_closed_not_taken_for_a_ring_around_the_pinhole():
    ring = annulus()
    broken = ring.copy()
    broken[23, 31:40] = False                               # a one-pixel cut on the right
    wall = np.argwhere(binary_erosion(ring) & (np.mgrid[0:48, 0:48][1] < 20))
    broken[tuple(wall[0])] = False                          # and a pinhole on the left
    check_myocardium_mask(broken)                           # passes: one piece around one "cavity", the pinhole
    out, changes = repair_myocardium_mask(broken)
    assert np.array_equal(out, ring) and "cut" in changes


def test_a_cut_at_the_image_edge_is_closed_without_losing_the_edge():
    ring = annulus(n=40, cx=19.5, cy=19.5, inner=12.0, outer=22.0)   # clipped by the image's edges
    check_myocardium_mask(ring)
    broken = ring.copy()
    broken[19, 30:] = False                                 # cut through to the right edge
    out, changes = repair_myocardium_mask(broken)
    assert "cut" in changes and not np.any(ring & ~out)     # no tissue lost at the edge
    assert np.sum(out != ring) <= MAX_REPAIR_FRACTION * ring.sum()


def test_the_borders_of_a_mended_mask_warn_and_name_it():
    stray = annulus()
    stray[0, 0] = True
    with pytest.warns(RuntimeWarning, match=r"masks\[3\]: not one ring.*removed 1 stray piece"):
        b = mask_borders(stray, name="masks[3]")
    clean = mask_borders(annulus())
    assert np.allclose(b.endo, clean.endo) and np.allclose(b.epi, clean.epi)


def test_a_frame_mask_that_cannot_be_mended_is_left_out_and_none_readable_leaves_the_phase_alone():
    ring = annulus()
    moved = annulus(outer=14.0)
    good = np.stack([ring, moved, moved])
    assert masks_can_be_fused(good) and unusable_mask_frames(good) == ([], None)
    half = moved & (np.mgrid[0:48, 0:48][1] < 24)              # half a ring: no cavity, a wide cut
    bad = good.copy()
    bad[2] = half
    found, reason = unusable_mask_frames(bad)
    assert found == [2] and reason.startswith("masks[2]: expected a ring")
    with warnings.catch_warnings():                            # guided border data read each frame on its own
        warnings.simplefilter("error")
        assert masks_can_be_fused(bad)
    with pytest.warns(RuntimeWarning, match=r"index \[2\].*landmarks tracked from frame to frame need every.*"
                                            r"does without the masks"):
        assert not masks_can_be_fused(bad, every_frame=True)  # landmarks tracked from frame to frame need each
    bad[1] = half
    with pytest.warns(RuntimeWarning, match=r"frame\(s\) \[0, 1\] \(index \[1, 2\].*no frame's is left"):
        assert not masks_can_be_fused(bad)
    with pytest.warns(RuntimeWarning, match=r"the reference mask cannot be made one ring.*reference_mask: expected"):
        assert not masks_can_be_fused(np.stack([half, moved, moved]))      # no border can be read against it
    assert unusable_mask_frames(np.stack([half, moved, moved]))[0] == [0]


@pytest.mark.skipif(not (CASE / "config.yaml").is_file(), reason="the DENSE-Sim case is not here")
def test_image_settings_fuse_mended_masks_and_fall_back_from_broken_ones():
    case = read_dense_sim(CASE)
    assert image_settings(case).border_masks
    masks = case.masks.copy()
    wall = np.argwhere(binary_erosion(masks[3]))
    masks[3, wall[0][0], wall[0][1]] = False                   # a pinhole: mended, still fused
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert image_settings(replace(case, masks=masks)).border_masks
    masks = case.masks.copy()
    r, c = np.nonzero(masks[0])
    gap = (np.abs(np.arange(masks.shape[1])[:, None] - r.mean()) <= 1.5) & (np.arange(masks.shape[2]) > c.mean())
    masks[5] &= ~gap                                           # a cut of 3 px in one frame: that frame left out
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert image_settings(replace(case, masks=masks)).border_masks
    with pytest.warns(RuntimeWarning, match=r"index \[5\].*tracked"):       # but landmarks need every frame
        assert not image_settings(replace(case, masks=masks), border_correspondence="landmarks").border_masks
    masks[1:] &= ~gap                                          # no frame's: the phase alone
    with pytest.warns(RuntimeWarning, match=r"index \[1, 2, .*no frame's is left"):
        assert not image_settings(replace(case, masks=masks)).border_masks
    # asked for explicitly, no check and no warning: the route then says what is wrong
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert image_settings(replace(case, masks=masks), border_masks=True).border_masks


def test_the_mending_of_many_masks_is_one_warning_naming_each_and_what_changed():
    stray = annulus()
    stray[0, 0] = True
    hole = annulus()
    hole[23, 23 + 10] = False                                  # a pinhole in the wall (radius 10 of 8-13)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        with mended_masks_summarised():
            for t, m in enumerate([stray, stray, annulus(), hole]):
                mask_borders(m, name=f"masks[{t}]")
            warnings.warn("something else", UserWarning)       # passes as it was
    said = [str(w.message) for w in rec if issubclass(w.category, RuntimeWarning)]
    assert [w.filename for w in rec if issubclass(w.category, RuntimeWarning)] == [__file__]   # the caller's line
    assert len(said) == 1 and said[0].startswith("3 masks (masks[0-1, 3]): not one ring")
    assert "removed 1 stray piece(s) of 1 px (masks[0-1])" in said[0]
    assert "filled 1 hole(s) of 1 px in the wall (masks[3])" in said[0]
    assert [str(w.message) for w in rec if issubclass(w.category, UserWarning)] == ["something else"]
    with pytest.warns(RuntimeWarning, match=r"^masks\[1\]: not one ring around one cavity; mended"):   # one: as is
        with mended_masks_summarised():
            mask_borders(stray, name="masks[1]")
    with pytest.warns(RuntimeWarning, match=r"^masks\[0\]: not one ring") as rec:     # given before an error too
        with pytest.raises(ValueError, match=r"masks\[1\]: expected"):
            with mended_masks_summarised():
                mask_borders(stray, name="masks[0]")
                mask_borders(annulus() & (np.mgrid[0:48, 0:48][1] < 24), name="masks[1]")


def test_the_summary_of_mended_masks_never_takes_the_place_of_an_error_and_touches_no_filter():
    stray = annulus()
    stray[0, 0] = True
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)       # a user who makes warnings errors
        with pytest.raises(ValueError, match=r"masks\[1\]: expected"):
            with mended_masks_summarised():
                mask_borders(stray, name="masks[0]")
                mask_borders(annulus() & (np.mgrid[0:48, 0:48][1] < 24), name="masks[1]")
        with pytest.raises(RuntimeWarning, match=r"masks\[0\]: not one ring"):   # no error leaving: the warning's
            with mended_masks_summarised():
                mask_borders(stray, name="masks[0]")
    before = list(warnings.filters)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        with mended_masks_summarised():
            assert warnings.filters[0][0] == "always"        # the filters are the caller's inside, as outside
            mask_borders(stray, name="masks[0]")
    assert warnings.filters == before and len(rec) == 1


# ---------------------------------------------------------------------- a reference mask not the frames'
@settings(max_examples=30, deadline=None)
@given(ring=rings, grow=st.sampled_from([-1.0, 1.0]), shift=st.floats(-1.5, 1.5))
def test_a_reference_mask_a_pixel_thicker_or_thinner_than_the_frames_is_named(ring, grow, shift):
    """Frames of the same ring moved about (areas unchanged): no message; a reference one pixel out: one."""
    frames = np.stack([np.roll(ring, k, axis=1) for k in (0, 1, 2, 1)])
    assert reference_mask_mismatch(np.concatenate([ring[None], frames])) is None
    moved = annulus(cx=23.5 + shift, inner=8.0, outer=13.0)                    # the same ring, elsewhere
    assert reference_mask_mismatch(np.stack([moved, annulus(), annulus()])) is None
    other = binary_dilation(ring) if grow > 0 else binary_erosion(ring)        # a pixel out at both borders
    message = reference_mask_mismatch(np.concatenate([other[None], frames]))
    assert message is not None and message.startswith("masks[0] (the reference) holds")
    assert f"holds {other.sum()} pixels and masks[1] (the first frame) {ring.sum()}" in message


def test_a_reference_mask_is_not_named_when_the_frames_vary_as_much():
    """The frames' own area changes over the cycle bound what the reference may differ by."""
    wide = annulus(inner=7.0, outer=14.0)
    frames = np.stack([annulus(), annulus(inner=7.5, outer=13.5), wide])
    assert reference_mask_mismatch(np.concatenate([wide[None], frames])) is None
    assert reference_mask_mismatch(np.concatenate([annulus()[None], frames])) is None
    assert reference_mask_mismatch(annulus()[None]) is None                     # nothing to compare with
    empty = np.zeros_like(wide)
    assert reference_mask_mismatch(np.stack([annulus(), empty, annulus(), annulus()])) is None   # passed over
    thick = binary_dilation(annulus())
    assert "masks[2] (the first frame with tissue)" in reference_mask_mismatch(np.stack([thick, empty, annulus()]))
    with pytest.raises(ValueError, match="masks"):
        reference_mask_mismatch(annulus())


def test_a_frame_left_out_does_not_hide_a_reference_a_pixel_thicker():
    """A frame whose mask a route cannot read (passed in ``exclude``) sets neither the frames' spread nor the frame
    compared: a filled disc among the frames would otherwise widen the spread past any reference's jump."""
    thick = binary_dilation(annulus())
    filled = annulus(inner=0.0, outer=14.0)
    masks = np.stack([thick, annulus(), filled, annulus()])
    assert reference_mask_mismatch(masks) is None                          # the disc's area swamps the jump
    assert "masks[1] (the first frame)" in reference_mask_mismatch(masks, exclude=[2])
    assert reference_mask_mismatch(np.stack([annulus(), annulus(), filled, annulus()]), exclude=[2]) is None
    assert reference_mask_mismatch(masks, exclude=None) == reference_mask_mismatch(masks)
    for bad in ([0], [4], [1.7], ["2"]):
        with pytest.raises(ValueError, match="exclude"):
            reference_mask_mismatch(masks, exclude=bad)
    with pytest.raises(ValueError, match="masks"):
        reference_mask_mismatch(np.zeros((0, 8, 8), bool))
    with pytest.raises(ValueError, match="masks: expected a rectangular 3D mask.*different sizes"):
        reference_mask_mismatch([annulus(), annulus(n=50)])
