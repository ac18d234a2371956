"""Table 1 over many noise draws: how often each strategy is rejected, and the spread of its errors.

The paper's Table 1 rests on one noise realisation, so its p-values say little about how often
a strategy is rejected. :func:`summarise` takes the comparisons of many seeds (their
``as_json()`` dicts, as a batch run stores them) and gives, per strategy, the rejection rate
of the KS test at 5% with its Wilson interval and the median and quartiles of D, p, the
material errors, loops and run time; :func:`format_summary` prints it.
"""
from __future__ import annotations

import numpy as np

from .comparison import LABELS, PAPER_TABLE1, REPORT_FRAME
from .statistics import wilson_interval

__all__ = ["summarise", "format_summary", "SUMMARY_QUANTITIES"]

#: Quantities summarised by median and quartiles: (metrics key, label). Keys missing from a
#: strategy's metrics (material errors of the fixed-material KFs) are left out for it.
SUMMARY_QUANTITIES = (
    ("ks_D", "D"), ("ks_p_asymptotic", "p"), ("rmse_displacement_mm", "RMSE u [mm]"),
    ("E_rel_error_middle", "E err mid"), ("E_rel_error_outside", "E err out"),
    ("nu_rel_error_middle", "nu err mid"), ("nu_rel_error_outside", "nu err out"),
    ("loops", "loops"), ("seconds", "time [s]"),
)


def summarise(results, level: float = 0.95) -> dict:
    """Per-strategy summary of many comparisons.

    Parameters
    ----------
    results : sequence of dict
        ``Comparison.as_json()`` of each draw (keys ``seed`` and ``strategies``; the metrics may
        carry ``seconds``). At least one.
    level : float
        Confidence level of the rejection rate's Wilson interval.

    Returns
    -------
    dict
        ``{"n_draws", "seeds", "level", "strategies": {name: {"n", "rejections", "rate", "interval",
        "values": {key: list}, "quartiles": {key: (q1, median, q3)}, "unconverged"}}}``; ``unconverged``
        (draws whose loops or iterations hit their limit) only where the metrics say ``converged``.
    """
    results = list(results)
    if not results:
        raise ValueError("results: expected the comparisons of at least one seed, got none")
    for i, r in enumerate(results):
        if not isinstance(r, dict) or "strategies" not in r:
            raise ValueError(f"results[{i}]: expected a comparison's as_json() dict with 'strategies'")
    names = [s for s in LABELS if any(s in r["strategies"] for r in results)]
    out = {"n_draws": len(results), "seeds": [r.get("seed") for r in results], "level": level, "strategies": {}}
    for s in names:
        rows = [r["strategies"][s] for r in results if s in r["strategies"]]
        k = int(sum(int(m["ks_H"]) for m in rows))
        # a null in a stored result (an undefined figure) counts as missing, not as zero
        values = {key: [np.nan if m[key] is None else float(m[key]) for m in rows]
                  for key, _ in SUMMARY_QUANTITIES if all(key in m for m in rows)}
        out["strategies"][s] = {
            "n": len(rows), "rejections": k, "rate": k / len(rows), "interval": wilson_interval(k, len(rows), level),
            "values": values,
            "quartiles": {key: tuple(float(q) for q in np.nanpercentile(v, [25, 50, 75])) if np.any(np.isfinite(v))
                          else (np.nan,) * 3 for key, v in values.items()},
        }
        if all("converged" in m for m in rows):
            out["strategies"][s]["unconverged"] = int(sum(not m["converged"] for m in rows))
    return out


def format_summary(summary: dict) -> str:
    """Text table of :func:`summarise`: rejection rate with its interval, then median [q1, q3]."""
    level = summary["level"]
    lines = [f"KS test of e_yy at frame {REPORT_FRAME} over {summary['n_draws']} noise draws: "
             f"rejection rate at 5% with its {100 * level:.0f}% Wilson interval; median [quartiles]"]
    for s, v in summary["strategies"].items():
        lo, hi = v["interval"]
        paper = PAPER_TABLE1.get(s)
        ref = f"   (paper, one draw: D={paper['D']:.4f} p={paper['p']:.4f} H={paper['H']})" if paper else ""
        lines.append(f"{LABELS[s]:<22} rejected {v['rejections']:>3}/{v['n']:<3} = {v['rate']:6.1%} "
                     f"[{lo:6.1%}, {hi:6.1%}]{ref}")
        if "unconverged" in v:
            lines.append(f"    {'limit hit':<12} {v['unconverged']:>10d} of {v['n']} draws (loops or iterations)")
        for key, label in SUMMARY_QUANTITIES:
            if key in v["quartiles"]:
                q1, med, q3 = v["quartiles"][key]
                lines.append(f"    {label:<12} {med:>10.4g} [{q1:.4g}, {q3:.4g}]")
    return "\n".join(lines)
