"""Closing the loop in rounds where the answer is known: the issue-14 synthetic checks, with the spline beside.

    OPENBLAS_NUM_THREADS=1 python benchmarks/rounds_synthetic.py [--cases scale two akinetic clean harmonic]
        [--selection best|first] [--max-tries 3] [--no-prune] [--criterion evidence|cv]

Synthetic annulus sequences drawn from the library's own generative model
(:func:`sfem_filters.cardiac.annulus_sequence`), run through
:func:`sfem_filters.cardiac.closing_the_loop` with its defaults (rounds, smoother, region map):

* ``scale``: pressure-driven passive tissue at 5, 30 and 100 kPa (pressure scaled with E), no
  effect: the estimated stiffness level with its 95% interval;
* ``two``: undeclared ``active_polar`` and ``active_helical`` at once, at two balances of strength;
* ``akinetic``: ``active_segments`` with one segment not contracting;
* ``clean``: no undeclared effect, seeds 0-3;
* ``harmonic``: ``active_harmonic`` (uniform plus a first harmonic in angle of both the
  circumferential and the radial stress), with ``active_harmonic`` named among the candidates
  (the rounds try it only when named), once with each ``selection`` (``"first"`` with 2 tries, the
  default ``"best"`` fitting the 3 best-scored); not in the default list of cases.

``--selection`` and ``--max-tries`` are passed to every case but ``harmonic``, which runs both
selections itself; ``--no-prune`` turns the backward steps off in every case; ``--criterion``
(``evidence``, the default, or ``cv``) is the rounds' criterion in every case. Per case: the
effects the rounds added, why they stopped, NIS/dof and held-out RMSE of the final model, the
thin-plate spline's held-out RMSE, and the case's own check. The same cases are asserted in
``tests/cardiac/test_rounds.py`` (slow marks), with the default criterion.
"""
from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

from sfem_filters.cardiac import annulus_sequence, closing_the_loop, measured, prepare
from sfem_filters.cardiac.closing import CRITERIA, DEFAULT_CANDIDATES, SELECTIONS
from sfem_filters.fem import Material

CASES = ("scale", "two", "akinetic", "clean", "harmonic")


def harmonic_amplitudes() -> tuple:
    """The ``harmonic`` case's 20 amplitudes (component, angular function, depth; units of E0):
    circumferential 0.15 + 0.10 cos(theta), radial -0.3 - 0.2 cos(theta), the same at both depths."""
    amp = np.zeros(20)
    amp[[0, 1]], amp[[2, 3]] = 0.15, 0.10
    amp[[10, 11]], amp[[12, 13]] = -0.3, -0.2
    return tuple(amp)


def _row(name, out, extra=""):
    e = out.extended.metrics
    if "steps:" not in extra and len(out.rounds) > 1:            # corrections are steps too, not effects
        extra += ("; " if extra else "") + "steps: " + ", ".join(r.change for r in out.rounds[1:])
    print(f"{name:<30}{','.join(out.effects) or 'none':<32} {out.stop_reason:<25}{e['nis_mean_over_dof']:>8.3f}"
          f"{e['heldout_rmse_px']:>9.3f}{out.reference['heldout_rmse_px']:>8.3f}  {extra}", flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", nargs="*", choices=CASES, default=[c for c in CASES if c != "harmonic"])
    ap.add_argument("--selection", choices=SELECTIONS, default="best",
                    help="how a round picks among significant candidates (closing_the_loop's selection)")
    ap.add_argument("--max-tries", type=int, default=3, help="most significant candidates fitted per round")
    ap.add_argument("--measurement-noise", choices=("fixed", "estimate"), default="fixed",
                    help="the measurement noise at the noise floor, or its level by type-II ML in every fit "
                         "(closing_the_loop's measurement_noise)")
    ap.add_argument("--no-prune", action="store_true",
                    help="no backward steps (closing_the_loop's prune=False, the rule before this option)")
    ap.add_argument("--criterion", choices=CRITERIA, default="evidence",
                    help="what a step must improve (closing_the_loop's criterion)")
    args = ap.parse_args(argv)
    if args.measurement_noise == "estimate" and args.criterion != "evidence":
        ap.error("--measurement-noise estimate needs --criterion evidence (the cross-validation's folds would "
                 "use the noise floor)")
    warnings.simplefilter("ignore", RuntimeWarning)
    pick = {"selection": args.selection, "max_tries": args.max_tries, "prune": not args.no_prune,
            "measurement_noise": args.measurement_noise, "criterion": args.criterion}
    print(f"{'case':<30}{'effects added':<32} {'stopped':<25}{'NIS/dof':>8}{'held-out':>9}{'spline':>8}  check",
          flush=True)
    t0 = time.perf_counter()
    if "scale" in args.cases:
        mesh = prepare(annulus_sequence(None, n_frames=4), 8).mesh
        for E in (5.0, 30.0, 100.0):
            mat = Material.uniform(mesh.n_elements, E * 1e3, measured.NOMINAL["nu"])
            seq = annulus_sequence(None, seed=0, drive="pressure", material=mat, peak_pressure=2e3 * E / 10)
            out = closing_the_loop(seq, effects="auto", drive="pressure", max_iterations=80, **pick)
            m, f = out.baseline.metrics, out.extended.metrics
            lo, hi = m["E_level_kPa_95"]
            final = ""
            if len(out.rounds) > 1:
                flo, fhi = f["E_level_kPa_95"]
                final = f"; final model's level {f['E_level_kPa']:.2f} kPa (95% {flo:.2f}-{fhi:.2f})"
            _row(f"pressure, E = {E:g} kPa", out,
                 f"level {m['E_level_kPa']:.2f} kPa (95% {lo:.2f}-{hi:.2f}), {m['loops']} iterations"
                 f"{'' if m['converged'] else ' (not converged)'}, baseline NIS/dof {m['nis_mean_over_dof']:.3f}{final}")
    if "two" in args.cases:
        for label, amps in (("polar (0.15, -0.3), helical 0.3", ((0.15, -0.3), (0.0, 0.3))),
                            ("polar (0.1, -0.2), helical 0.6", ((0.1, -0.2), (0.0, 0.6)))):
            out = closing_the_loop(annulus_sequence(["active_polar", "active_helical"], amplitude=amps, seed=0),
                                   effects="auto", max_iterations=6, **pick)
            _row(label, out, "steps: " + ", ".join(r.change for r in out.rounds[1:]))
    if "akinetic" in args.cases:
        amp = np.tile([0.15, -0.3], 6)
        amp[[4, 5]] = 0.0
        out = closing_the_loop(annulus_sequence("active_segments", amplitude=tuple(amp), seed=0), effects="auto",
                               max_iterations=6, **pick)
        m = out.extended.metrics
        extra = ""
        if "active_segments[4]" in m.get("effect_state_names", []):
            names = m["effect_state_names"]
            st, sd = np.array(m["effect_states"]), np.array(m["effect_states_sd"])
            peak = int(np.argmax(np.abs(st[:, names.index("active_segments[1]")])))
            k = names.index("active_segments[4]")
            extra = (f"segment 2 at peak: a_c {st[peak, k]:+.3f} +- {sd[peak, k]:.3f}, a_r {st[peak, k + 1]:+.3f} +- "
                     f"{sd[peak, k + 1]:.3f} (truth 0); segment 0: a_r {st[peak, 1]:+.3f} (truth -0.3)")
        for r in out.rounds[1:]:
            entry = next((e for e in (r.ranking or []) if e["effect"] == "active_segments"), None)
            if r.added == "active_segments" and entry is not None:
                extra += (f"; active_segments in round {r.number}: per frame {entry['score_per_frame']:.2f}, "
                          f"tied {entry.get('score_time_courses', float('nan')):.2f} (-log10 p)")
        _row("akinetic segment 2", out, extra)
    if "clean" in args.cases:
        for seed in range(4):
            _row(f"no effect, seed {seed}", closing_the_loop(annulus_sequence(None, seed=seed), effects="auto",
                                                            max_iterations=6, **pick))
    if "harmonic" in args.cases:
        seq = annulus_sequence("active_harmonic", amplitude=harmonic_amplitudes(), seed=0)
        for selection, tries in (("first", 2), ("best", 3)):
            out = closing_the_loop(seq, effects="auto", max_iterations=6, selection=selection, max_tries=tries,
                                   prune=pick["prune"], measurement_noise=pick["measurement_noise"],
                                   criterion=args.criterion,
                                   candidates=list(DEFAULT_CANDIDATES) + ["active_harmonic"])
            gap = out.extended.metrics["versus_spline"]["model"]
            fitted = "; ".join(f"round {r.number}: " + ", ".join(f"{t['effect']} {t['evidence_gain']:+.1f}"
                                                                 for t in r.tried if t.get("score") is not None)
                               for r in out.rounds[1:] if r.removed is None)
            _row(f"active_harmonic, {selection}", out,
                 "round-0 scores: " + ", ".join(f"{r['effect']} {r['score']:.1f}" for r in out.ranking[:3])
                 + f"; fitted (gain in log p(y), nats): {fitted}"
                 + "; steps: " + ", ".join(r.change for r in out.rounds[1:])
                 + f"; model - spline {gap['difference']:+.3f} px (95% {gap['low']:+.3f} to {gap['high']:+.3f})")
    print(f"wall time {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
