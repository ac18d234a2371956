"""Figures of a strain report (``sfem-filters strain --figures``), drawn from its JSON alone: rendered with
warnings as errors and held to the reviewer's checks of issue 41 item 5 (:func:`test_figures.check_figure`)."""
from __future__ import annotations

import csv
import json
import warnings

import matplotlib
import numpy as np
import pytest
from strain_report_helpers import synthetic_report
from test_cli_strain import CASE, short_case  # noqa: F401  (the 6-frame DENSE-Sim case folder fixture)
from test_figures import check_figure, colourbars, data_axes, written

matplotlib.use("Agg")
from matplotlib import pyplot as plt  # noqa: E402

from sfem_filters.cli import main  # noqa: E402
from sfem_filters.imaging.strain_report import csv_row_count, with_peaks  # noqa: E402
from sfem_filters.plotting import strain_figures  # noqa: E402
from sfem_filters.plotting._common import SEQUENTIAL  # noqa: E402

FIGURES = ["strain_segments.png", "strain_global.png", "strain_peaks_bullseye.png"]


def drawn(report, directory) -> dict:
    """``strain_figures(report, directory)`` with every warning an error: file name -> figure (kept open)."""
    return written(strain_figures, report, directory)


@pytest.fixture(scope="module")
def figs(tmp_path_factory):
    out = drawn(synthetic_report(empty_segment=4), tmp_path_factory.mktemp("strain"))
    yield out
    for fig in out.values():
        plt.close(fig)


def legend_texts(fig) -> list:
    return [t.get_text() for leg in fig.legends for t in leg.get_texts()]


def test_the_figures_pass_the_reviewers_checks(figs):
    assert sorted(figs) == sorted(FIGURES)                  # no material in the report: no stiffness ring
    for fig in figs.values():
        check_figure(fig)


def test_segment_curves_draw_every_method_with_the_band_and_say_what_each_line_is(figs):
    fig = figs["strain_segments.png"]
    axes = data_axes(fig)
    assert len(axes) == 12
    for ax in axes:
        assert "[ms]" in ax.get_xlabel() and "[%]" in ax.get_ylabel()
        assert len([ln for ln in ax.lines if ln.get_label() == "_line"]) == 4     # route, conventional, spline, truth
        assert len(ax.collections) == 1                                # the route's 95% band (not the spline's)
    texts = " | ".join(legend_texts(fig))
    for what in ("this library, dense route", "95% band (dense", "conventional analysis", "Gaussian sigma 1 px",
                 "thin-plate spline through the same observed points", "ground truth (synthetic truth)"):
        assert what in texts, what


def test_the_band_drawn_is_the_reports_band_in_percent(tmp_path):
    r = synthetic_report()
    fig = drawn(r, tmp_path)["strain_global.png"]
    ax_cc = data_axes(fig)[0]
    band = ax_cc.collections[0].get_paths()[0].vertices[:, 1]
    lo, hi = 100 * np.array(r["global"]["Ecc_lo"]), 100 * np.array(r["global"]["Ecc_hi"])
    assert np.isclose(band.min(), lo.min()) and np.isclose(band.max(), hi.max())
    plt.close(fig)


def test_peak_rings_colour_each_segment_by_its_peak(figs):
    fig = figs["strain_peaks_bullseye.png"]
    peaks = with_peaks(synthetic_report(empty_segment=4))
    rings = data_axes(fig)
    assert len(rings) == 2 * 4                                                  # Ecc and Err x 4 methods
    titles = [ax.get_title() for ax in rings]
    assert sum("peak Ecc" in t for t in titles) == 4 and any("ground truth" in t for t in titles)
    ours = next(ax for ax in rings if "dense route" in ax.get_title() and "peak Err" in ax.get_title())
    values = np.ma.filled(ours.collections[0].get_array(), np.nan)
    want = 100 * np.array(peaks["peaks"]["segments"]["Err"]["value"], float)
    np.testing.assert_allclose(values, want)
    assert np.isnan(values[4])                                                  # the empty segment: grey
    labels = [cb.long_axis.get_label_text() for cb in colourbars(fig)]
    assert any("peak Ecc (minimum over time) [%]" in t for t in labels)
    assert any("peak Err (maximum over time) [%]" in t for t in labels)
    assert all(cb.cmap.name in SEQUENTIAL for cb in colourbars(fig))          # one-signed peaks


def test_peaks_of_both_signs_get_a_scale_per_ring(tmp_path):
    r = synthetic_report()
    seg = r["spline"]["segments"]
    seg["Err"] = [[None if x is None else -x for x in row] for row in seg["Err"]]      # a thinning wall
    fig = drawn(r, tmp_path)["strain_peaks_bullseye.png"]
    check_figure(fig)
    bars = [cb.long_axis.get_label_text() for cb in colourbars(fig)]
    assert sum("peak Ecc" in t for t in bars) == 1 and sum("peak Err" in t for t in bars) == 4
    plt.close(fig)


def test_the_stiffness_ring_is_drawn_only_when_the_route_estimates_a_material(tmp_path):
    figs = drawn(synthetic_report(material=True), tmp_path)
    assert sorted(figs) == sorted(FIGURES + ["stiffness_bullseye.png"])
    fig = figs["stiffness_bullseye.png"]
    check_figure(fig)
    labels = [cb.long_axis.get_label_text() for cb in colourbars(fig)]
    assert any("relative stiffness" in t for t in labels) and any("sd" in t for t in labels)
    sd_bar = next(cb for cb in colourbars(fig) if "sd" in cb.long_axis.get_label_text())
    assert sd_bar.norm.vmin == 0.0
    for f in figs.values():
        plt.close(f)


def test_figures_without_the_optional_blocks(tmp_path):
    r = synthetic_report()
    for name in ("spline", "truth", "conventional"):
        del r[name]
    figs = drawn(r, tmp_path)
    fig = figs["strain_segments.png"]
    assert not any("ground truth" in t or "spline" in t for t in legend_texts(fig))
    assert len(data_axes(figs["strain_peaks_bullseye.png"])) == 2
    for f in figs.values():
        check_figure(f)
        plt.close(f)


def test_a_route_without_bands_and_a_segment_without_pixels_draw_without_warnings(tmp_path):
    r = synthetic_report(empty_segment=0)
    missing = [None] * len(r["frame_times_s"])
    for d, none in ((r["global"], missing), (r["segments"], [missing] * 6)):
        for q in ("Ecc", "Err"):
            d[q + "_lo"] = d[q + "_hi"] = none
    figs = drawn(r, tmp_path)
    for name, fig in figs.items():
        check_figure(fig)
        if name != "strain_peaks_bullseye.png":
            assert all(not ax.collections for ax in data_axes(fig))               # no band to draw
        plt.close(fig)


def test_strain_figures_refuse_what_is_not_a_report(tmp_path):
    with pytest.raises(ValueError, match="report: expected the strain report dict"):
        strain_figures({"route": "dense"}, tmp_path)


# ----------------------------------------------------------------------------------- from the command line
@pytest.mark.needs_data(CASE)
def test_the_strain_verb_writes_csv_and_figures_that_a_saved_json_redraws(short_case, tmp_path, capsys):  # noqa: F811
    out, table, figdir = tmp_path / "s.json", tmp_path / "s.csv", tmp_path / "figs"
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        assert main(["strain", str(short_case), "--json", str(out), "--snr", "30", "--csv", str(table),
                     "--figures", str(figdir), "--quiet"]) == 0
    # the only warnings are the route's own (frames where the data move beyond its motion), none from the CSV or
    # figures
    assert all("faster than the model's motion allows" in str(w.message) for w in seen), [str(w.message) for w in seen]
    err = capsys.readouterr().err
    assert "progress" not in err and f"wrote {table}" in err
    assert sorted(p.name for p in figdir.iterdir()) == sorted(FIGURES)
    d = json.loads(out.read_text())
    # the case's ground truth beside the estimate, and every block's peaks
    assert d["truth"]["source"].startswith("DENSE-Sim") and np.shape(d["truth"]["segments"]["Err"]) == (6, 6)
    for block in (d, d["conventional"], d["spline"], d["truth"]):
        seg = np.array(block["segments"]["Err"], float)
        assert block["peaks"]["segments"]["Err"]["value"] == list(np.nanmax(seg, axis=1))
        assert block["peaks"]["global"]["Ecc"]["time_s"] in d["frame_times_s"]
    with open(table, newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == csv_row_count(d)
    assert {r["method"] for r in rows} == {"dense", "conventional", "spline", "truth"}
    assert "tracked reference pixels" in d["spline"]["through"]
    assert np.shape(d["spline"]["strain"]["Ecc"]) == np.shape(d["strain"]["Ecc"])
    # figures again from the saved JSON, with warnings as errors
    again = drawn(d, tmp_path / "again")
    assert sorted(again) == sorted(FIGURES)
    for fig in again.values():
        check_figure(fig)
        plt.close(fig)
