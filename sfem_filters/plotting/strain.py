"""Figures of a strain report (``sfem-filters strain``), drawn from its JSON alone.

:func:`strain_figures` takes the report dict the verb writes (or reads back from its JSON), so the
figures can be made again from a saved report without rerunning the route. It draws:

* ``strain_segments.png``: the six segment curves of Ecc and Err (2 x 6 panels) over time, the
  route's mean with its 95% band (the only band drawn), against the conventional analysis, the thin-plate spline (when
  the report has a ``spline`` block) and the ground truth (when it has a ``truth`` block,
  labelled as such);
* ``strain_global.png``: the global Ecc and Err curves, the same lines;
* ``strain_peaks_bullseye.png``: a six-segment ring per method of peak Ecc (minimum over time) and
  peak Err (maximum), with the time to peak, in the image's orientation (x right, y down);
* ``stiffness_bullseye.png``: relative stiffness per segment and its sd, only when the report
  has a ``material`` block with ``segments`` ``relative_stiffness`` and ``relative_stiffness_sd``
  (six values each, dimensionless, relative to the route's nominal modulus). The DENSE and
  contours routes hold the material fixed (their ``settings``, ``material`` or ``estimator``, say
  so), so their reports have no such block and this figure is not drawn: a fixed modulus has no
  sd and nothing to map.

Strain is shown in percent (100 x the Green-Lagrange fraction), time in ms after the encoding.
Colours follow :mod:`sfem_filters.plotting._common`: sequential maps for one-signed peaks,
diverging maps centred at zero only for peaks of both signs.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..imaging.strain import N_SEGMENTS
from ..imaging.strain_report import PEAK_KIND, method_blocks, with_peaks
from ._common import _plt, colour_scale

__all__ = ["strain_figures", "segment_curves_figure", "global_curves_figure", "peaks_bullseye",
           "stiffness_bullseye", "method_label"]

PCT = 100.0
#: Line style of each method (the route's own is drawn with :data:`ROUTE_STYLE`).
STYLES = {"conventional": {"color": "tab:orange", "ls": "--", "lw": 1.4},
          "spline": {"color": "tab:green", "ls": "-.", "lw": 1.4},
          "truth": {"color": "black", "ls": "-", "lw": 1.1}}
ROUTE_STYLE = {"color": "tab:blue", "ls": "-", "lw": 1.8}
NAMES = {"Ecc": "circumferential strain E_cc", "Err": "radial strain E_rr"}


def method_label(name: str, block: dict) -> str:
    """What a method's line is, for legends and titles."""
    if name == "conventional":
        s = block.get("smoothing_sigma_px")
        return "conventional analysis (finite differences" + (
            f", Gaussian sigma {s:g} px)" if s else ", no smoothing)" if s is not None else ")")
    if name == "spline":
        return "thin-plate spline through the same observed points"
    if name == "truth":
        return "ground truth" + (f" ({block['source']})" if block.get("source") else "")
    return f"this library, {name} route (finite-element smoother): mean"


def _arr(v) -> np.ndarray:
    return np.asarray(v, float)


def _time_ms(report: dict) -> np.ndarray:
    return _arr(report["frame_times_s"]) * 1e3


def _draw_curves(ax, report: dict, region: str, q: str, k: int | None):
    """The lines of every method for one curve (global when ``k`` is None) into ``ax``; legend handles
    (the route's own first, its band with its mean width). Only the route's band is drawn: the
    spline's delta-method band, when it has one, stays in the JSON and the CSV (two bands in a
    small panel hide the lines)."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch
    t = _time_ms(report)
    handles = []
    blocks = method_blocks(report)
    route = blocks[0][0]
    for name, block in blocks:
        d = block.get(region)
        if not d or q not in d:
            continue
        pick = (lambda a: _arr(a)) if k is None else (lambda a: _arr(a)[k])
        style = ROUTE_STYLE if name == route else STYLES.get(name, {"color": "tab:purple", "ls": ":", "lw": 1.4})
        z = 3 if name == route else 2
        ax.plot(t, PCT * pick(d[q]), label="_line", zorder=z, **style)
        handles.append(Line2D([], [], label=method_label(name, block), **style))
        if name == route and _has_band(d, q):                            # the others' bands: in the JSON and CSV
            lo, hi = PCT * pick(d[q + "_lo"]), PCT * pick(d[q + "_hi"])
            ax.fill_between(t, lo, hi, color=style["color"], alpha=0.3, lw=0, label="_band", zorder=z)
            handles.append(Patch(color=style["color"], alpha=0.3, label=f"95% band ({name}; {_widths(d)})"))
    ax.axhline(0.0, color="0.6", lw=0.6, zorder=0, label="_zero")
    return handles


def _has_band(d: dict, q: str) -> bool:
    """Whether a region's curve ``q`` has a band with at least one finite frame."""
    return q + "_lo" in d and q + "_hi" in d and bool(np.isfinite(_arr(d[q + "_hi"]) - _arr(d[q + "_lo"])).any())


def _widths(d: dict) -> str:
    """Mean width of the bands of a region's curves over frames (and segments), per component."""
    w = [f"{q} {PCT * np.nanmean(_arr(d[q + '_hi']) - _arr(d[q + '_lo'])):.2g}" for q in ("Ecc", "Err")
         if _has_band(d, q)]
    return "mean width " + ", ".join(w) + " % points"


def _segment_title(report: dict, k: int) -> str:
    s0 = float(report["segments"].get("start_deg", 0.0))
    a, b = (s0 + 60 * k) % 360, (s0 + 60 * (k + 1)) % 360
    return f"segment {k} ({a:g} to {b if b else 360:g} deg)"


def segment_curves_figure(report: dict, path) -> None:
    """Six segment curves of Ecc (top row) and Err (bottom row) over time, every method's line."""
    plt = _plt()
    fig, axes = plt.subplots(2, N_SEGMENTS, figsize=(20, 7.2), layout="constrained", sharex=True, sharey="row")
    handles = []
    for i, q in enumerate(("Ecc", "Err")):
        for k in range(N_SEGMENTS):
            ax = axes[i, k]
            h = _draw_curves(ax, report, "segments", q, k)
            handles = handles if len(handles) >= len(h) else h
            ax.set_title(_segment_title(report, k), fontsize=10)
            ax.set_xlabel("time after encoding [ms]")
            ax.set_ylabel(f"{q} [%]")
            ax.tick_params(labelleft=True, labelbottom=True)
    fig.legend(handles=handles, loc="outside lower center", ncols=min(len(handles), 3), fontsize=9, frameon=False)
    start = float(report["segments"].get("start_deg", 0.0))
    fig.suptitle(f"Segment curves: {NAMES['Ecc']} (top) and {NAMES['Err']} (bottom), Green-Lagrange, in % "
                 f"(segments of 60 deg from {start:g} deg, from the image's +x axis towards +y)")
    fig.savefig(path, dpi=100)
    plt.close(fig)


def global_curves_figure(report: dict, path) -> None:
    """The global (mean over reference pixels) Ecc and Err curves over time, every method's line."""
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(12.5, 5.6), layout="constrained")
    handles = []
    for ax, q in zip(axes, ("Ecc", "Err")):
        h = _draw_curves(ax, report, "global", q, None)
        handles = handles if len(handles) >= len(h) else h
        ax.set_title(f"global {NAMES[q]}")
        ax.set_xlabel("time after encoding [ms]")
        ax.set_ylabel(f"{q} [%]")
    fig.legend(handles=handles, loc="outside lower center", ncols=2, fontsize=9, frameon=False)
    fig.suptitle("Global curves (mean over the reference myocardium), Green-Lagrange, in %")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _text_colour(cmap, norm, v) -> str:
    r, g, b, _ = cmap(norm(v))
    return "black" if 0.299 * r + 0.587 * g + 0.114 * b > 0.55 else "white"


def _ring(ax, values, scale: dict, start_deg: float, texts, centre_text: str = ""):
    """Six wedges coloured by ``values`` (missing: grey, hatched) in the image's orientation; the mappable."""
    import matplotlib as mpl
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Wedge
    v = _arr(values)
    wedges = [Wedge((0.0, 0.0), 1.0, start_deg + 60 * k, start_deg + 60 * (k + 1), width=0.55) for k in range(len(v))]
    cmap = mpl.colormaps[scale["cmap"]].with_extremes(bad="0.85")
    pc = PatchCollection(wedges, cmap=cmap, edgecolor="white", linewidth=1.5)
    pc.set_array(np.ma.masked_invalid(v))
    pc.set_clim(scale["vmin"], scale["vmax"])
    ax.add_collection(pc)
    norm = pc.norm
    for k, (val, txt) in enumerate(zip(v, texts)):
        a = np.radians(start_deg + 60 * k + 30)
        colour = _text_colour(cmap, norm, val) if np.isfinite(val) else "black"
        ax.text(0.725 * np.cos(a), 0.725 * np.sin(a), txt, ha="center", va="center", fontsize=7.5, color=colour)
    if centre_text:
        ax.text(0, 0, centre_text, ha="center", va="center", fontsize=8)
    ax.set_xlim(-1.08, 1.08)
    ax.set_ylim(1.08, -1.08)                                    # y down, as the image is shown
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    for side in ax.spines.values():
        side.set_visible(False)
    # a schematic: the axes say only which way the image's x and y run (no scale)
    ax.set_xlabel("image +x (columns) to the right", fontsize=8)
    ax.set_ylabel("image +y (rows) downwards", fontsize=8)
    return pc


def _fmt(v, unit: str = "%", scale: float = PCT, digits: int = 1) -> str:
    return "n/a" if v is None or not np.isfinite(v) else f"{scale * v:.{digits}f}{unit}"


def _one_signed(*arrays) -> bool:
    v = np.concatenate([np.ravel(a) for a in arrays])
    v = v[np.isfinite(v)]
    return v.size == 0 or v.min() >= 0 or v.max() <= 0


def peaks_bullseye(report: dict, path) -> None:
    """Peak Ecc and peak Err of each segment as six-segment rings, one column per method, with the
    time to peak. One colour bar per component shared by the methods when their peaks share a
    sign (the usual case: Ecc shortens, Err thickens); otherwise each ring gets its own scale
    (sequential when its own peaks share a sign, diverging about zero when they do not)."""
    plt = _plt()
    rep = with_peaks(report)
    blocks = method_blocks(rep)
    start = float(rep["segments"].get("start_deg", 0.0))
    fig, axes = plt.subplots(2, len(blocks), figsize=(max(3.5 * len(blocks) + 1.8, 7.5), 7.8), layout="constrained",
                             squeeze=False)
    for i, q in enumerate(("Ecc", "Err")):
        vals = [PCT * _arr(b["peaks"]["segments"][q]["value"]) if q in b["peaks"].get("segments", {}) else
                np.full(N_SEGMENTS, np.nan) for _, b in blocks]
        seq = "viridis" if q == "Err" else "viridis_r"
        shared = _one_signed(*vals)
        kind = "minimum" if PEAK_KIND[q] == "min" else "maximum"
        bar = f"peak {q} ({kind} over time) [%]\n(Green-Lagrange x 100)"
        for j, ((name, b), v) in enumerate(zip(blocks, vals)):
            seg = b["peaks"].get("segments", {}).get(q, {"time_s": [None] * N_SEGMENTS})
            texts = [f"{k}: {_fmt(x, scale=1.0)}\n{_fmt(tt, ' ms', 1e3, 0)}"
                     for k, (x, tt) in enumerate(zip(v, seg["time_s"]))]
            g = b["peaks"]["global"].get(q, {})
            scale = colour_scale(*vals, sequential=seq) if shared else colour_scale(v, sequential=seq)
            pc = _ring(axes[i, j], v, scale, start, texts,
                       centre_text=f"global\n{_fmt(g.get('value'))}\n{_fmt(g.get('time_s'), ' ms', 1e3, 0)}")
            label = method_label(name, b).removesuffix(": mean")
            axes[i, j].set_title(f"{label.replace(' (', chr(10) + '(', 1)}\npeak {q}", fontsize=9)
            if not shared:
                fig.colorbar(pc, ax=axes[i, j], shrink=0.7, location="bottom", label=bar)
        if shared:
            fig.colorbar(pc, ax=axes[i, :], shrink=0.85, label=bar)
    first = "the image's +x axis" if start % 360 == 0 else f"{start % 360:g} deg from the image's +x axis"
    fig.suptitle(f"Peak strain and time to peak (ms after encoding) per segment k;\nsix 60-degree segments, k = 0 "
                 f"starting at {first}, k rising towards +y,\ndrawn as the image is shown (x right, y down: "
                 f"clockwise); centre: the global curve's peak", fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _stiffness(report: dict):
    seg = (report.get("material") or {}).get("segments") or {}
    if "relative_stiffness" in seg and "relative_stiffness_sd" in seg:
        return _arr(seg["relative_stiffness"]), _arr(seg["relative_stiffness_sd"])
    return None


def stiffness_bullseye(report: dict, path) -> None:
    """Relative stiffness per segment and its posterior sd as two six-segment rings (sequential maps,
    the sd's from zero); needs ``report["material"]["segments"]`` (see the module docstring)."""
    plt = _plt()
    got = _stiffness(report)
    if got is None:
        raise ValueError("report: expected material.segments with relative_stiffness and relative_stiffness_sd "
                         "(a route that estimates the material); this report has none")
    value, sd = got
    start = float(report["segments"].get("start_deg", 0.0))
    fig, axes = plt.subplots(1, 2, figsize=(9.5, 4.6), layout="constrained")
    for ax, v, what, lo in ((axes[0], value, "relative stiffness E / E_nominal", None),
                            (axes[1], sd, "posterior sd of the relative stiffness", 0.0)):
        scale = colour_scale(v, sequential="cividis", vmin=lo)
        pc = _ring(ax, v, scale, start, [f"{k}: {x:.2f}" for k, x in enumerate(v)])
        ax.set_title(what, fontsize=10)
        fig.colorbar(pc, ax=ax, shrink=0.85, label=f"{what}\n(dimensionless)")
    fig.suptitle(f"Material per segment (six 60-degree segments, k = 0 from {start % 360:g} deg, image orientation)")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def strain_figures(report: dict, out_dir) -> list:
    """Every figure of a strain report into ``out_dir`` (created); the paths written (``Path``).

    ``report`` is the dict of the verb's JSON (``json.load`` of it will do). The stiffness ring is
    drawn only when the report has a material per segment (module docstring); otherwise it is
    left out (the routes today hold the material fixed, as ``report["settings"]`` says).
    """
    method_blocks(report)                                        # a clear error for anything else
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    figures = [("strain_segments.png", segment_curves_figure), ("strain_global.png", global_curves_figure),
               ("strain_peaks_bullseye.png", peaks_bullseye)]
    if _stiffness(report) is not None:
        figures.append(("stiffness_bullseye.png", stiffness_bullseye))
    paths = []
    for name, fn in figures:
        fn(report, out / name)
        paths.append(out / name)
    return paths
