"""How sure a held-out difference against the spline is: the delete-one-cluster jackknife of
``RMSE(a) - RMSE(b)`` (exact algebra, pairing, NaN handling, coverage on draws with a known
difference), the angular sectors it clusters by, and its place in the rounds' report."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy.stats import t as student_t

from sfem_filters.cardiac import EstimatorSettings, LoopSettings, ModelSpec, annulus_sequence, closing
from sfem_filters.cardiac.reference import angular_sectors, rmse_difference, spline_reference


def _draw(seed, F=4, G=5, per=3):
    rng = np.random.default_rng(seed)
    labels = np.repeat(np.arange(G), per)
    a = rng.standard_normal((F, G * per, 2))
    b = 0.7 * a + rng.standard_normal((F, G * per, 2)) * rng.uniform(0.1, 2.0)
    return a, b, labels


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10_000), st.floats(0.1, 10.0))
def test_the_difference_is_the_pooled_rmses_and_behaves_like_one(seed, c):
    a, b, labels = _draw(seed)
    d = rmse_difference(a, b, labels)
    assert d["difference"] == pytest.approx(np.sqrt(np.mean(np.sum(a ** 2, 2))) - np.sqrt(np.mean(np.sum(b ** 2, 2))))
    assert d["low"] <= d["difference"] <= d["high"] and d["se"] > 0
    swapped = rmse_difference(b, a, labels)
    assert swapped["difference"] == pytest.approx(-d["difference"])
    assert (swapped["low"], swapped["high"]) == pytest.approx((-d["high"], -d["low"]))
    scaled = rmse_difference(c * a, c * b, labels)          # a change of unit scales everything
    assert (scaled["difference"], scaled["low"], scaled["high"]) == pytest.approx(
        (c * d["difference"], c * d["low"], c * d["high"]))
    same = rmse_difference(a, a, labels)
    assert same["difference"] == 0.0 and same["se"] == 0.0 and same["low"] == same["high"] == 0.0


def test_the_jackknife_se_is_the_delete_one_cluster_formula():
    a, b, labels = _draw(3, G=6)
    d = rmse_difference(a, b, labels, level=0.9)
    loo = []
    for g in range(6):
        keep = labels != g
        loo.append(np.sqrt(np.mean(np.sum(a[:, keep] ** 2, 2))) - np.sqrt(np.mean(np.sum(b[:, keep] ** 2, 2))))
    loo = np.array(loo)
    se = np.sqrt(5 / 6 * np.sum((loo - loo.mean()) ** 2))
    assert d["se"] == pytest.approx(se)
    assert d["high"] - d["difference"] == pytest.approx(student_t.ppf(0.95, 5) * se)
    assert d["n_clusters"] == 6 and d["level"] == 0.9


def test_entries_missing_in_either_prediction_are_left_out_of_both():
    a, b, labels = _draw(4)
    a[0, :3] = np.nan
    b[2, 5:7] = np.nan
    both = ~(np.isnan(a).any(2) | np.isnan(b).any(2))
    d = rmse_difference(a, b, labels)
    assert d["rmse_a"] == pytest.approx(np.sqrt(np.mean(np.sum(a ** 2, 2)[both])))
    assert d["rmse_b"] == pytest.approx(np.sqrt(np.mean(np.sum(b ** 2, 2)[both])))
    a[:, labels == 0] = np.nan                 # a cluster with no pair left drops out of the count
    assert rmse_difference(a, b, labels)["n_clusters"] == 4


def test_the_interval_covers_a_known_difference_at_its_level():
    """Draws whose points share a cluster effect (errors alike within a sector, as between two
    landmarks): the 95% interval covers the population difference in 91-99% of 300 draws (binomial
    sd 1.3%); treating the points as independent would not."""
    rng = np.random.default_rng(11)
    G, F, per, sa, sb, tau = 10, 8, 15, 1.0, 0.8, 0.5
    labels = np.repeat(np.arange(G), per)
    truth = np.sqrt(2.0) * (sa - sb)        # sqrt(E|r|^2) of 2 components with total sd s each
    hits = naive_hits = 0
    for _ in range(300):
        ca, cb = rng.normal(0, tau, (G, 2)), rng.normal(0, tau, (G, 2))
        a = rng.normal(0, np.sqrt(sa ** 2 - tau ** 2), (F, G * per, 2)) + ca[labels][None]
        b = rng.normal(0, np.sqrt(sb ** 2 - tau ** 2), (F, G * per, 2)) + cb[labels][None]
        d = rmse_difference(a, b, labels)
        hits += d["low"] <= truth <= d["high"]
        naive = rmse_difference(a, b, np.arange(G * per))           # every point its own cluster
        naive_hits += naive["low"] <= truth <= naive["high"]
    assert 0.91 <= hits / 300 <= 0.99
    assert naive_hits / 300 < 0.85


def test_bad_input_is_named():
    a, b, labels = _draw(0)
    with pytest.raises(ValueError, match="residual_b"):
        rmse_difference(a, b[:, :-1], labels)
    with pytest.raises(ValueError, match="clusters"):
        rmse_difference(a, b, labels[:-1])
    with pytest.raises(ValueError, match="at least 2 clusters"):
        rmse_difference(a, b, np.zeros_like(labels))
    with pytest.raises(ValueError, match="level"):
        rmse_difference(a, b, labels, level=1.0)
    with pytest.raises(ValueError, match="residual_a"):
        rmse_difference(np.full_like(a, np.inf), b, labels)
    with pytest.raises(ValueError, match="n"):
        angular_sectors([0.0, 1.0], 1)


def test_angular_sectors_cut_the_circle_evenly():
    ang = np.array([0.0, 0.1, np.pi / 2 - 1e-9, np.pi / 2, np.pi, 2 * np.pi - 1e-12, 2 * np.pi, -0.1])
    assert angular_sectors(ang, 4).tolist() == [0, 0, 0, 1, 2, 3, 0, 3]


def test_the_rounds_report_each_difference_from_the_spline_with_its_interval():
    seq = annulus_sequence("active_polar", n_frames=4, seed=2)
    out = closing.closing_the_loop(seq, ModelSpec(parameterisation="none"), EstimatorSettings(max_iterations=2),
                                   LoopSettings(effects=["active_polar"], corrections=False,
                                                folds=9))     # 9 folds of 8 landmarks: no CV, quicker
    js = out.as_json()
    setup = out.setup
    held = setup.node_of_point[setup.heldout]
    spline = spline_reference(seq.points, seq.displacement, setup.observed, setup.heldout,
                              setup.geometry.radial[held], setup.geometry.circumferential[held])
    for r in js["rounds"]:
        vs = r["versus_spline"]
        assert vs["sectors"] == setup.n_landmarks
        m, p = vs["model"], vs["model_plus_spline"]
        # the same held-out RMSEs the report prints, paired on the same points and frames
        assert m["rmse_a"] == pytest.approx(r["heldout_rmse_px"], rel=1e-9)
        assert m["rmse_b"] == pytest.approx(spline["heldout_rmse_px"], rel=1e-9)
        assert p["rmse_a"] == pytest.approx(r["residual_spline"]["heldout_rmse_px"], rel=1e-9)
        assert m["low"] < m["difference"] < m["high"] and p["low"] < p["difference"] < p["high"]
    report = closing.format_report(out)
    last = js["rounds"][-1]["versus_spline"]["model"]
    assert f"model {last['difference']:+.3f} ({last['low']:+.3f} to {last['high']:+.3f})" in report
    assert "jackknife over" in report
