"""Every figure the command line writes, rendered on small cases with warnings as errors, and checked
for what a reviewer looks at (issue 41, item 5): a unit on every axis that shows data, a label on
every colour bar, a sequential map for one-signed data and a diverging map centred at zero only
for signed data, every colour-mapped panel explained by a colour bar with the same map and limits,
labelled lines in a legend, constrained layout with nothing outside the figure and no title under
another panel or colour bar, the thresholds the tests use drawn (the prior check's |z|, the
estimators' stop rules), and the error maps beside the displacement estimates."""
from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import matplotlib
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

matplotlib.use("Agg")
from matplotlib import pyplot as plt  # noqa: E402
from matplotlib.colors import TwoSlopeNorm  # noqa: E402
from matplotlib.layout_engine import ConstrainedLayoutEngine  # noqa: E402

from sfem_filters.benchmark.comparison import (LABELS, ROWS, Comparison, StrategyRun, benchmark_model,  # noqa: E402
                                                evaluate, pinned_benchmark, run_strategy)
from sfem_filters.benchmark.summary import summarise  # noqa: E402
from sfem_filters.cardiac import annulus, closing  # noqa: E402
from sfem_filters.cardiac.specs import specs_from  # noqa: E402
from sfem_filters.filtering.iterated import IteratedSmoother  # noqa: E402
from sfem_filters.imaging.phase_contrast import VelocityData  # noqa: E402
from sfem_filters.imaging.tracking import track_masks  # noqa: E402
from sfem_filters.plotting import comparison as cplots  # noqa: E402
from sfem_filters.plotting import frontend as fplots  # noqa: E402
from sfem_filters.plotting import measured as mplots  # noqa: E402
from sfem_filters.plotting._common import DIVERGING, SEQUENTIAL, SIGNED_BY_DEFINITION, colour_scale  # noqa: E402

BACKGROUND = ("gray", "gray_r", "Greys")       # the masks under the tracked points (0/1 images)


# ----------------------------------------------------------------------------------- small cases
@pytest.fixture(scope="module")
def comp():
    """The pinned benchmark (seed 0) with every row of the comparison, cut short: the cyclic rows at 3
    loops, the joint smoother at 3 Gauss-Newton iterations (as :func:`run_strategy` runs it otherwise)."""
    bench = pinned_benchmark(0, 1, 0.1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)          # unconverged: on purpose
        runs = {s: run_strategy(bench, s, max_loops=3) for s in ROWS if s != "joint_smoother"}
        model = benchmark_model(bench, "joint_ekf")
        result = IteratedSmoother(max_iterations=3).run(model, bench.observations)
    runs["joint_smoother"] = StrategyRun("joint_smoother", model, result, *evaluate(bench, model, result, 0.0))
    return Comparison(bench, runs)


@pytest.fixture(scope="module")
def loop():
    """A small synthetic slice (4 frames) through the measured-data workflow with the smoother: strain
    sd and the prior-data check present."""
    seq = annulus.annulus_sequence("active_polar", n_frames=4, seed=0, amplitude=(0.3, -0.6))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return closing.closing_the_loop(seq, *specs_from(effects="none", estimator="smoother", max_iterations=2,
                                                             folds=9))


@pytest.fixture(scope="module")
def obs():
    """Tracked borders of masks deformed by a known motion, and velocities at mid-wall points."""
    seq, truth = annulus.annulus_sequence(effect="active_polar", seed=1, return_truth=True, beta=0.03, n_frames=6)
    masks = annulus.deformed_masks(seq, truth["displacement"])
    rng = np.random.default_rng(0)
    pick = rng.choice(len(seq.points), size=40, replace=False)
    vel = VelocityData(points=seq.points[pick], velocity=truth["velocity"][:, pick],
                       lpc=rng.uniform(0, 1, (seq.n_frames, len(pick))), sigma=np.ones((seq.n_frames, len(pick))))
    return {"tracks": track_masks(masks), "masks": masks, "velocity": vel}


def written(fn, obj, directory) -> dict:
    """``fn(obj, directory)`` (a ``*_figures`` function of the CLI) with every warning an error: file name
    -> figure, each file checked to be written."""
    captured = []
    real = plt.close
    plt.close = lambda fig=None: captured.append(fig)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            paths = fn(obj, str(directory))
    finally:
        plt.close = real
    assert len(paths) == len(captured)
    names = [Path(p).name for p in paths]
    for name in names:
        assert (Path(directory) / name).stat().st_size > 10_000, name
    return dict(zip(names, captured))


@pytest.fixture(scope="module")
def comp_figs(comp, tmp_path_factory):
    figs = written(cplots.comparison_figures, comp, tmp_path_factory.mktemp("compare"))
    yield figs
    for fig in figs.values():
        plt.close(fig)


@pytest.fixture(scope="module")
def dense_figs(loop, tmp_path_factory):
    figs = written(mplots.dense_figures, loop, tmp_path_factory.mktemp("dense"))
    yield figs
    for fig in figs.values():
        plt.close(fig)


# ----------------------------------------------------------------------------------- checks
def render(monkeypatch, fn, obj, path, **kw):
    """Draw one figure with every warning an error; the figure (its ``plt.close`` intercepted)."""
    captured = []
    with monkeypatch.context() as m:
        m.setattr(plt, "close", lambda fig=None: captured.append(fig))
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            fn(obj, str(path), **kw)
    assert path.exists() and path.stat().st_size > 10_000, path
    assert len(captured) == 1
    return captured[0]


def colourbars(fig) -> list:
    return [ax._colorbar for ax in fig.axes if getattr(ax, "_colorbar", None) is not None]


def data_axes(fig) -> list:
    return [ax for ax in fig.axes if getattr(ax, "_colorbar", None) is None and ax.axison
            and (ax.lines or ax.collections or ax.images or ax.patches)]


def mapped(ax) -> list:
    return [a for a in list(ax.collections) + list(ax.images) if a.get_array() is not None]


def finite(a) -> np.ndarray:
    v = np.ma.filled(np.ma.asarray(a, float), np.nan).ravel()
    return v[np.isfinite(v)]


def centred(norm) -> bool:
    if isinstance(norm, TwoSlopeNorm):
        return norm.vcenter == 0
    return np.isclose(norm.vmin, -norm.vmax)


def check_figure(fig):
    """The reviewer's checks common to every figure; returns the colour bars."""
    assert isinstance(fig.get_layout_engine(), ConstrainedLayoutEngine)
    axes = data_axes(fig)
    assert axes
    for ax in axes:
        assert ax.get_xlabel().strip() and ax.get_ylabel().strip(), (ax.get_title(), ax.get_xlabel(), ax.get_ylabel())
    cbs = colourbars(fig)
    for cb in cbs:
        assert cb.long_axis.get_label_text().strip(), "unlabelled colour bar"
    for ax in axes:
        for art in mapped(ax):
            name, norm, v = art.get_cmap().name, art.norm, finite(art.get_array())
            assert name in SEQUENTIAL + DIVERGING + BACKGROUND, name
            one_signed = v.size == 0 or v.min() >= 0 or v.max() <= 0
            if name in DIVERGING:
                assert centred(norm), (ax.get_title(), name, norm.vmin, norm.vmax)
                assert not one_signed or art.get_gid() == SIGNED_BY_DEFINITION, (ax.get_title(), name)
            else:
                assert one_signed, (ax.get_title(), name, v.min(), v.max())
            if name in BACKGROUND:
                continue
            # explained by a colour bar with the same map and limits
            assert any(cb.cmap.name == name and np.isclose(cb.norm.vmin, norm.vmin)
                       and np.isclose(cb.norm.vmax, norm.vmax)
                       for cb in cbs), (ax.get_title(), name)
        labelled = [ln.get_label() for ln in ax.lines if not ln.get_label().startswith("_")]
        labelled += [c.get_label() for c in ax.collections if not c.get_label().startswith("_")]
        if labelled:
            legend = ax.get_legend()
            assert legend is not None, (ax.get_title(), labelled)
            texts = {t.get_text() for t in legend.get_texts()}
            assert set(labelled) <= texts, (set(labelled) - texts)
    # nothing clipped, no title under another panel or a colour bar (the layout, without rasterising)
    fig.draw_without_rendering()
    r = fig.canvas.get_renderer()
    box = fig.bbox
    for ax in fig.axes:
        bb = ax.get_tightbbox(r)
        assert bb.x0 >= box.x0 - 2 and bb.y0 >= box.y0 - 2 and bb.x1 <= box.x1 + 2 and bb.y1 <= box.y1 + 2, \
            (ax.get_title(), bb, box)
    for ax in fig.axes:
        if not ax.get_title():
            continue
        tb = ax.title.get_window_extent(r)
        for other in fig.axes:
            if other is not ax and other.axison:
                ob = other.get_window_extent(r)
                assert not tb.overlaps(ob), (ax.get_title(), other.get_title() or "colour bar")
            if other is not ax and other.get_title():
                assert not tb.overlaps(other.title.get_window_extent(r)), (ax.get_title(), other.get_title())
    if fig._suptitle is not None:
        sb = fig._suptitle.get_window_extent(r)
        assert sb.x0 >= box.x0 - 2 and sb.x1 <= box.x1 + 2, fig._suptitle.get_text()
    return cbs


def by_title(fig, part) -> list:
    return [ax for ax in fig.axes if part in ax.get_title()]


# ----------------------------------------------------------------------------------- colour rule
@settings(max_examples=60, deadline=None)
@given(hnp.arrays(float, st.integers(1, 30), elements=st.floats(-1e3, 1e3)))
def test_colour_scale_follows_the_sign_of_the_data(v):
    s = colour_scale(v)
    if v.min() >= 0 or v.max() <= 0:
        assert s["cmap"] in SEQUENTIAL and s["vmin"] <= v.min() and s["vmax"] >= v.max()
    else:
        assert s["cmap"] in DIVERGING and s["vmin"] == -s["vmax"] and s["vmax"] == np.abs(v).max()


def test_colour_scale_ignores_nan_and_starts_at_vmin():
    s = colour_scale([np.nan, 0.2, 0.5], vmin=0.0, sequential="plasma")
    assert s == {"cmap": "plasma", "vmin": 0.0, "vmax": 0.5}


# ----------------------------------------------------------------------------------- compare
def test_comparison_figures_are_written(comp_figs):
    assert sorted(comp_figs) == sorted(
        ["displacement_maps.png", "eyy_frame9.png", "eyy_cdfs_frame9.png", "material_maps.png", "convergence.png"])
    for fig in comp_figs.values():
        check_figure(fig)


def test_displacement_maps_show_each_estimates_error_beside_it(comp, comp_figs):
    fig = comp_figs["displacement_maps.png"]
    frames = (1, 5, 9, 13)                                          # the CLI's
    errors = by_title(fig, ": error, frame")
    assert len(errors) == len(comp.runs) * len(frames)
    art = mapped(by_title(fig, f"{LABELS['joint_ekf']}: error, frame 9")[0])[0]
    want = np.linalg.norm((comp.runs["joint_ekf"].U[8] - comp.bench.U[8]).reshape(-1, 2), axis=1) * 1e3
    # one log scale for all errors, from 1/100 of the largest: smaller ones at its low end
    np.testing.assert_allclose(art.get_array(), np.maximum(want, art.norm.vmin))
    assert np.isclose(art.norm.vmax, 100 * art.norm.vmin) and want.max() <= art.norm.vmax
    assert any("error" in cb.long_axis.get_label_text() and "mm" in cb.long_axis.get_label_text()
               for cb in colourbars(fig))


def test_displacement_maps_take_other_frames(comp, tmp_path, monkeypatch):
    fig = render(monkeypatch, cplots.displacement_maps, comp, tmp_path / "d.png", frames=(9,))
    check_figure(fig)
    assert len(by_title(fig, ": error, frame 9")) == len(comp.runs)
    plt.close(fig)


def test_eyy_map_of_one_sign_is_sequential(comp_figs):
    fig = comp_figs["eyy_frame9.png"]
    v = np.concatenate([finite(a.get_array()) for ax in data_axes(fig) for a in mapped(ax)])
    name = mapped(data_axes(fig)[0])[0].get_cmap().name
    assert (name in SEQUENTIAL) == (v.max() <= 0 or v.min() >= 0)


def test_cdfs_say_what_each_line_is(comp, comp_figs):
    fig = comp_figs["eyy_cdfs_frame9.png"]
    texts = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert len(texts) == 1 + len(comp.runs) and all("D = " in t for t in texts[1:])


def test_material_maps_use_sequential_maps_and_call_the_error_relative(comp_figs):
    fig = comp_figs["material_maps.png"]
    cbs = colourbars(fig)
    labels = [cb.long_axis.get_label_text() for cb in cbs]
    assert any("kPa" in t for t in labels) and sum("sd" in t for t in labels) == 2
    assert "relative E error" in fig._suptitle.get_text()
    E_panel = mapped(by_title(fig, "true E")[0])[0]
    assert E_panel.norm.vmin <= 75.0 <= E_panel.norm.vmax and E_panel.get_cmap().name in SEQUENTIAL


def test_convergence_draws_each_estimators_own_stop_rule(comp, tmp_path, monkeypatch):
    fig = render(monkeypatch, cplots.convergence, comp, tmp_path / "v.png", ekf_tol=2e-3)
    check_figure(fig)
    (a,), (b,), (c,) = by_title(fig, "(a) joint EKF"), by_title(fig, "(b) joint smoother"), by_title(fig, "(c)")
    s = IteratedSmoother()
    flat = lambda ax: {ln.get_ydata()[0] for ln in ax.lines if len(set(ln.get_ydata())) == 1}  # noqa: E731
    assert flat(a) == {2e-3}
    assert flat(b) == {s.tol, s.sd_tol} and flat(c) == {s.cost_tol}
    assert comp.runs["joint_smoother"].result.stop_reason in b.get_title()
    plt.close(fig)


def test_summary_figure_marks_the_level(comp, tmp_path):
    draws = []
    rng = np.random.default_rng(0)
    for seed in range(4):
        j = comp.as_json()
        j["seed"] = seed
        for m in j["strategies"].values():
            m["ks_D"] = float(rng.integers(1, 12)) / 35
            m["ks_p_asymptotic"] = float(rng.uniform(0.001, 1))
        draws.append(j)
    captured = []
    real = plt.close
    plt.close = lambda fig=None: captured.append(fig)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            path = cplots.summary_figure(summarise(draws), str(tmp_path / "s.png"))
    finally:
        plt.close = real
    fig = captured[0]
    check_figure(fig)
    assert (tmp_path / "s.png").stat().st_size > 10_000 and path.endswith("s.png")
    assert any(0.05 in set(ln.get_ydata()) for ln in fig.axes[1].lines)
    plt.close(fig)


# ----------------------------------------------------------------------------------- dense
def test_dense_figures_are_written(dense_figs):
    assert sorted(dense_figs) == sorted(
        ["residual_maps.png", "strain_maps.png", "nis_trace.png", "rounds.png", "material_maps.png"])
    for name, fig in dense_figs.items():
        check_figure(fig)
        for ax in data_axes(fig):
            assert "[px]" in ax.get_xlabel() + ax.get_ylabel() or "frame" in ax.get_xlabel() \
                or "round" in ax.get_xlabel(), (name, ax.get_xlabel())


def test_dense_strain_maps_have_the_sd_row_and_units(dense_figs):
    fig = dense_figs["strain_maps.png"]
    assert len(by_title(fig, "posterior sd")) == 3 and len(data_axes(fig)) == 9
    assert all("dimensionless" in cb.long_axis.get_label_text() for cb in colourbars(fig))


def test_nis_trace_draws_the_95_band(dense_figs):
    fig = dense_figs["nis_trace.png"]
    assert any("95%" in t.get_text() for t in fig.axes[0].get_legend().get_texts())


def test_prior_check_marks_its_threshold_with_readable_ticks(loop, dense_figs):
    fig = dense_figs["material_maps.png"]
    cbs = colourbars(fig)
    thr = loop.extended.metrics["prior_conflict"]["threshold"]
    z_bars = [cb for cb in cbs if "z of" in cb.long_axis.get_label_text()]
    assert len(z_bars) == 2
    for cb in z_bars:
        assert {ln.get_ydata()[0] for ln in cb.ax.lines} == {-thr, thr}
        ticks = list(cb.ax.get_yticks())
        assert 0.0 in ticks and thr in ticks and -thr in ticks
        assert {t.get_text() for t in cb.ax.get_yticklabels()} >= {"0", f"{thr:.2f}", f"-{thr:.2f}"}


def test_rounds_figure_with_several_rounds_keeps_its_labels_inside(loop, tmp_path, monkeypatch):
    """A longer search (the same round repeated under long effect names) still fits the figure."""
    r = loop.rounds[0]
    more = dataclasses.replace(loop, rounds=[r] * 4)
    real = type(loop).as_json

    def as_json(self):
        out = real(self)
        for x, name in zip(out["rounds"][1:], ("active_circumferential", "stiffer landmark springs", "active_polar")):
            x["added"] = name
        return out
    monkeypatch.setattr(type(loop), "as_json", as_json)
    fig = render(monkeypatch, mplots.rounds_figure, more, tmp_path / "r.png")
    check_figure(fig)
    plt.close(fig)


# ----------------------------------------------------------------------------------- observe
@pytest.mark.parametrize("fn", [fplots.tracked_contours, fplots.velocity_vectors])
def test_observe_figures_pass_the_checks(fn, obs, tmp_path, monkeypatch):
    fig = render(monkeypatch, fn, obs, tmp_path / "o.png")
    check_figure(fig)
    assert all("[px]" in ax.get_xlabel() and "[px]" in ax.get_ylabel() for ax in data_axes(fig))
    plt.close(fig)


def test_observe_figures_are_written(obs, tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        paths = fplots.observe_figures(obs, str(tmp_path))
    assert sorted(p.split("/")[-1] for p in paths) == ["tracked_contours.png", "velocity_lpc.png"]
