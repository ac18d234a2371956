"""The search's moves: the candidates' loads and their spans, the corrections the residual points
to, and the backward steps."""
from __future__ import annotations

import numpy as np

from ..effects import build_effects
from ..measured import NOMINAL, Setup
from ..specs import DEFAULT_CANDIDATES, STIFF_SPRINGS, ModelSpec
from .records import Round

__all__ = ["candidate_loads", "spans", "removals", "DRIVE_CORRECTIONS", "STIFF_SPRINGS"]

_SPAN_TOL = 1e-6


def candidate_loads(setup: Setup, names=None) -> list:
    """(name, load matrix) of the named catalogue effects (default :data:`DEFAULT_CANDIDATES`), for scoring."""
    names = DEFAULT_CANDIDATES if names is None else names
    effs = build_effects(names, setup.mesh, setup.geometry, angle_origin_deg=setup.angle_origin_deg,
                         scale=NOMINAL["E"])
    return [(e.name, e.loads) for e in effs]


def spans(A, B, tol: float = _SPAN_TOL) -> bool:
    """True when every column of ``B`` lies in the column span of ``A`` (relative residual of
    the least-squares fit below ``tol``): the loads ``B`` add nothing the loads ``A`` lack."""
    A, B = np.asarray(A, float), np.asarray(B, float)
    if A.size == 0:
        return not np.any(B)
    coef = np.linalg.lstsq(A, B, rcond=None)[0]
    return bool(np.linalg.norm(B - A @ coef) <= tol * max(np.linalg.norm(B), np.finfo(float).tiny))


#: Corrections of the drive the rounds may make: from the drive in use to the one tried instead.
DRIVE_CORRECTIONS = {"penalty": "contour"}

#: Corrections of the material's prior the rounds may make: from the map in use to a smoother one
#: (independent regions or elements to the smooth basis of a few modes, which ties neighbours).
MATERIAL_CORRECTIONS = {"region": "basis", "element": "basis"}

#: The corrections' factors: springs made this much stiffer (``springs:x10``), process noise this
#: much larger (``noise:x2``); a backward step (:func:`removals`) divides by the same factor.
SPRING_FACTOR, NOISE_FACTOR = 10.0, 2.0

#: The drives the correction ``springs:x10`` is offered to, by :data:`STIFF_SPRINGS`
#: (``LoopSettings.stiff_springs``, ``--stiff-springs``): ``"contour"``, springs spread along the whole
#: contour only (the default); ``"any"``, the isolated landmarks' springs (``drive="penalty"``) too.
SPRING_DRIVES = {"contour": ("contour",), "any": ("penalty", "contour")}

#: |z| of the innovations' checks (NIS, lag-1 whiteness; each ~N(0, 1) for a consistent model)
#: beyond which the residual points to a correction of the model's noise or dynamics.
CHECK_Z = 3.0


def _corrections(cur: Round, stiff_springs: str = "contour") -> list:
    """(name, ModelSpec) of the corrections the current round's residual points to.

    ``drive:<new>``: the drive's correction (:data:`DRIVE_CORRECTIONS`), always a candidate.
    When the innovations are correlated in time (whiteness z above :data:`CHECK_Z`), the model
    is a frame behind the motion: ``drive:trend``, spring targets extrapolated from the two
    previous frames instead of held at the last one (also with the drive's correction,
    ``drive:<new>+trend``: the drive is one factor, its alternatives are tried side by side);
    ``effects:trend``, effect amplitudes that
    follow a trend (integrated random walks) instead of holding their last value.
    ``springs:x10``: the springs ten times stiffer (soft springs let the tissue lag its border and
    leave the interior to the elastic response of a few updates), always a candidate for the drives
    ``stiff_springs`` names (:data:`STIFF_SPRINGS`): by default only springs spread along the whole
    contour (``drive="contour"``); on isolated landmarks (``"any"`` also offers those of
    ``drive="penalty"``) stiff springs pull tents, which the evidence need not reject (docs, the
    measured slice, "A second split": +82 nats while the held-out error nearly doubled).
    ``noise:x2``: when the innovations are too large for their covariance (NIS z above +3) and no
    effect explains them, every process noise (kinematics, drive, effects) doubled. Not the other
    way: a NIS below 1 in the smoother's final pass comes from the parameters' prior as well as
    from the process noise (a model that is right everywhere gives NIS/dof 0.5-0.8 on the
    synthetic checks), so it is no evidence that the noise is too large.
    ``material:<map>``: the material's prior made smoother (:data:`MATERIAL_CORRECTIONS`, from the
    map in use, :attr:`~sfem_filters.cardiac.specs.ModelSpec.material_map`), always a candidate: independent
    regions or elements let the stiffness absorb a misfit of the border that a smooth field
    cannot.
    """
    v, m = cur.variant, cur.run.metrics
    out = []
    lagged = m["lag1_z"] > CHECK_Z
    alt = DRIVE_CORRECTIONS.get(v.drive)
    if alt is not None:
        out.append((f"drive:{alt}", v.with_(drive=alt)))
    if lagged and v.drive in ("penalty", "contour") and not v.drive_trend:
        out.append(("drive:trend", v.with_(drive_trend=True)))
        if alt is not None:             # the drive's two corrections together: one alternative drive
            out.append((f"drive:{alt}+trend", v.with_(drive=alt, drive_trend=True)))
    if lagged and v.effects and not v.effect_rates:
        out.append(("effects:trend", v.with_(effect_rates=True)))
    if v.drive in SPRING_DRIVES[stiff_springs]:
        out.append(("springs:x10", v.with_(spring_scale=v.spring_scale * SPRING_FACTOR)))
    if m["nis_z"] > CHECK_Z:
        out.append(("noise:x2", v.with_(process_scale=v.process_scale * NOISE_FACTOR)))
    smoother = MATERIAL_CORRECTIONS.get(v.material_map)
    if smoother is not None:
        out.append((f"material:{smoother}", v.with_(material=smoother)))
    return out


def _key(variant: ModelSpec) -> ModelSpec:
    """A model's identity for the rounds: its spec with the effects in a fixed order."""
    return variant.with_(effects=tuple(sorted(variant.effects)))


def removals(variant: ModelSpec, start: ModelSpec, loads: dict) -> list:
    """(name, ModelSpec) of the backward steps from ``variant``: every term it holds beyond ``start``,
    taken out one at a time.

    An effect is removed (``name``: the effect; the last one out takes ``effects:trend`` with it),
    or replaced by a catalogue effect strictly nested in it (``<effect>-><nested>``: its loads span
    the nested effect's and not the other way, as six segments contain the uniform
    ``active_polar``), unless the other effects' loads already span the nested one (that would be
    a second copy of one cause). A correction is undone by one step (``drive:<drive>``: back to
    ``start``'s drive; ``drive:trend``, ``effects:trend``: off; ``springs:x10``, ``noise:x2``: the
    scale divided by that factor; ``material:<map>``: back to ``start``'s material map); ``drive:contour+trend``, one forward step, is undone in two. A
    greedy forward search can let a term enter that a later one makes unnecessary (stiffer springs
    standing in for a missing effect); these steps let the rounds take it out again (stepwise
    selection in both directions, Efroymson 1960).

    Parameters
    ----------
    variant : ModelSpec
        The current model.
    start : ModelSpec
        The rounds' starting model (its drive and scales are not terms).
    loads : dict
        Catalogue effect name -> load matrix (``candidate_loads``: (n_dofs, k) nodal loads per
        unit amplitude; only their column spans are used): the effects a nested replacement may
        use. Effects of ``variant`` missing from it get no nested replacement.

    Returns
    -------
    list of (str, ModelSpec)
        Each backward step's name and the model it leads to, effects first (in ``variant``'s
        order), then the corrections.
    """
    out = []
    for e in variant.effects:
        rest = tuple(x for x in variant.effects if x != e)
        out.append((e, variant.with_(effects=rest, effect_rates=variant.effect_rates and bool(rest))))
        if e not in loads:
            continue
        others = [loads[x] for x in rest if x in loads]
        G_rest = np.column_stack(others) if others else np.zeros((loads[e].shape[0], 0))
        for c, G in loads.items():
            if (c not in variant.effects and spans(loads[e], G) and not spans(G, loads[e])
                    and not spans(G_rest, G)):
                out.append((f"{e}->{c}", variant.with_(effects=tuple(c if x == e else x for x in variant.effects))))
    if variant.drive != start.drive:
        out.append((f"drive:{variant.drive}", variant.with_(drive=start.drive)))
    if variant.drive_trend and not start.drive_trend:
        out.append(("drive:trend", variant.with_(drive_trend=False)))
    if variant.effect_rates and not start.effect_rates:
        out.append(("effects:trend", variant.with_(effect_rates=False)))
    if variant.spring_scale > start.spring_scale:
        out.append(("springs:x10", variant.with_(spring_scale=variant.spring_scale / SPRING_FACTOR)))
    if variant.process_scale > start.process_scale:
        out.append(("noise:x2", variant.with_(process_scale=variant.process_scale / NOISE_FACTOR)))
    if variant.material != start.material:
        out.append((f"material:{variant.material}", variant.with_(material=start.material)))
    return out
