"""Pluggable model terms ("effects") that a passive elastic model lacks.

Each effect is a load ``G eta`` (N over the global dofs) linear in a few amplitude states
``eta`` that the filter estimates as random walks; the model appends them to its state, and
the Jacobian of the transition with respect to them is ``B G`` (exact, analytic). Effects are
built from the mesh and the geometry; none depends on the material, so the material Jacobian
M_t is unchanged except that it is evaluated at the total load.

Stress-type effects use the equivalent nodal load of a prescribed (active) stress
``sigma_a`` in each element, ``f_e = -t A_e B_e^T sigma_a`` (Voigt order xx, yy, xy): the
elastic stress then balances ``sigma_a``, so a positive active tension along a direction
shortens the tissue along it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._validate import as_float_array, integer, positive
from ..fem.loads import pressure_load, stress_loads
from ..fem.mesh import TriMesh
from .myocardium import LVGeometry, transmural_depth


@dataclass(frozen=True, eq=False)
class Effect:
    """A load term ``loads @ eta`` with random-walk amplitude states.

    Parameters
    ----------
    name : str
        Identifier used in configuration (``--effects NAME``).
    loads : (n_dofs, k) array
        Global load (N) per unit of each state.
    unit : str
        Unit of the states (for reports).
    process_std, initial_std : float or (k,) array
        Per-frame random-walk and initial standard deviations of the amplitudes (their unit).
    initial : float or (k,) array
        Initial value of the amplitudes.
    description : str
    rate_std : float, optional
        When given, each amplitude also gets a rate state (unit per frame) and moves as
        ``a_{t+1} = a_t + r_t``, ``r_{t+1} = r_t`` (an integrated random walk whose rate has
        this per-frame standard deviation): the model then extrapolates the trend of the
        effect one frame ahead instead of holding it.
    """

    name: str
    loads: np.ndarray
    unit: str
    process_std: object
    initial_std: object
    initial: object = 0.0
    description: str = ""
    rate_std: float | None = None

    def __post_init__(self):
        loads = as_float_array("loads", self.loads)
        if loads.ndim != 2 or loads.shape[1] < 1:
            raise ValueError(f"loads: expected an (n_dofs, k) array with k >= 1, got shape {loads.shape}")
        object.__setattr__(self, "loads", loads)
        k = loads.shape[1]
        for name, value, strict in (("process_std", self.process_std, False),
                                    ("initial_std", self.initial_std, True)):
            v = as_float_array(name, value)
            if v.ndim not in (0, 1) or (v.ndim == 1 and v.shape != (k,)):
                raise ValueError(f"{name}: expected a number or {k} numbers, got shape {v.shape}")
            if np.any(v < 0) or (strict and np.any(v == 0)):
                raise ValueError(f"{name}: expected standard deviations {'>' if strict else '>='} 0 "
                                 f"({self.unit}), got minimum {float(np.min(v))!r}")
        as_float_array("initial", self.initial)
        if self.rate_std is not None:
            positive("rate_std", self.rate_std, f"{self.unit} per frame")

    @property
    def n_amplitudes(self) -> int:
        """Number k of amplitudes (columns of ``loads``)."""
        return self.loads.shape[1]

    @property
    def n_states(self) -> int:
        """Number of states: the k amplitudes, and k rates with ``rate_std``."""
        return self.n_amplitudes * (1 if self.rate_std is None else 2)

    def transition(self) -> np.ndarray:
        """State transition over one frame, (n_states, n_states)."""
        k = self.n_amplitudes
        if self.rate_std is None:
            return np.eye(k)
        return np.block([[np.eye(k), np.eye(k)], [np.zeros((k, k)), np.eye(k)]])

    def state_loads(self) -> np.ndarray:
        """Load per unit of every state (rates load nothing), (n_dofs, n_states)."""
        if self.rate_std is None:
            return self.loads
        return np.hstack([self.loads, np.zeros_like(self.loads)])

    def _expand(self, v, rate_value) -> np.ndarray:
        v = np.broadcast_to(np.asarray(v, float), (self.n_amplitudes,))
        if self.rate_std is None:
            return np.array(v)
        return np.concatenate([v, np.full(self.n_amplitudes, rate_value)])

    def process_variances(self) -> np.ndarray:
        """Per-frame random-walk variances of the states, (n_states,): ``process_std^2`` for the amplitudes
        (``unit`` squared), ``rate_std^2`` for the rates ((unit per frame) squared)."""
        return self._expand(self.process_std, self.rate_std or 0.0) ** 2

    def initial_variances(self) -> np.ndarray:
        """Initial variances of the states, (n_states,): ``initial_std^2`` for the amplitudes (``unit``
        squared), ``rate_std^2`` for the rates ((unit per frame) squared)."""
        return self._expand(self.initial_std, self.rate_std or 0.0) ** 2

    def initial_states(self) -> np.ndarray:
        """Initial values of the states, (n_states,): ``initial`` for the amplitudes (``unit``), 0 for the rates."""
        return self._expand(self.initial, 0.0)


def _element_direction(mesh: TriMesh, node_vectors) -> np.ndarray:
    v = np.asarray(node_vectors)[mesh.elements].mean(axis=1)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _uniaxial(d) -> np.ndarray:
    """Voigt stress of unit tension along unit vectors d: (dx^2, dy^2, dx dy)."""
    return np.column_stack([d[:, 0] ** 2, d[:, 1] ** 2, d[:, 0] * d[:, 1]])


def active_stress(mesh: TriMesh, geometry: LVGeometry, direction: str = "circumferential",
                  name: str | None = None, scale: float = 1e3, thickness: float = 1.0, **noise) -> Effect:
    """Active fibre tension along the circumferential (or radial) direction, one amplitude.

    ``scale`` (Pa) is the stress of one unit of the state, so that states are O(1).
    """
    if direction not in ("circumferential", "radial"):
        raise ValueError(f"direction: expected 'circumferential' or 'radial', got {direction!r}")
    positive("scale", scale, "Pa")
    vec = {"circumferential": geometry.circumferential, "radial": geometry.radial}[direction]
    sigma = _uniaxial(_element_direction(mesh, vec)) * scale
    G = stress_loads(mesh, sigma, thickness)[:, None]
    return Effect(name or f"active_{direction}", G, f"{scale:g} Pa",
                  description=f"uniform active {direction} tension (one amplitude per frame)",
                  **_noise(noise))


def polar_active_stress(mesh: TriMesh, geometry: LVGeometry, scale: float = 1e3, thickness: float = 1.0,
                        **noise) -> Effect:
    """Active stress along the circumferential and the radial direction (2 states).

    Myocyte shortening (circumferential) and wall thickening (radial) that a 2D slice shows
    when the ventricle also shortens through the plane; for a homogeneous material this spans
    the same loads as a circumferential plus a radial eigenstrain.
    """
    G = np.column_stack([
        stress_loads(mesh, _uniaxial(_element_direction(mesh, geometry.circumferential)) * scale, thickness),
        stress_loads(mesh, _uniaxial(_element_direction(mesh, geometry.radial)) * scale, thickness)])
    return Effect("active_polar", G, f"{scale:g} Pa",
                  description="active circumferential and radial stress (shortening and thickening)",
                  **_noise(noise))


def transmural_active_stress(mesh: TriMesh, geometry: LVGeometry, scale: float = 1e3,
                             thickness: float = 1.0, **noise) -> Effect:
    """Circumferential active tension varying linearly from endocardium to epicardium (2 states)."""
    depth = transmural_depth(mesh, geometry)
    u = _uniaxial(_element_direction(mesh, geometry.circumferential)) * scale
    G = np.column_stack([stress_loads(mesh, u * (1 - depth)[:, None], thickness),
                         stress_loads(mesh, u * depth[:, None], thickness)])
    return Effect("active_transmural", G, f"{scale:g} Pa",
                  description="circumferential active tension, endocardial and epicardial amplitudes",
                  **_noise(noise))


def _symmetric(a, b) -> np.ndarray:
    """Voigt stress of ``(a b^T + b a^T) / 2`` for unit vectors a, b per element."""
    return np.column_stack([a[:, 0] * b[:, 0], a[:, 1] * b[:, 1], 0.5 * (a[:, 0] * b[:, 1] + a[:, 1] * b[:, 0])])


def segment_labels(mesh: TriMesh, geometry: LVGeometry, n_segments: int = 6, offset_deg: float = 0.0) -> np.ndarray:
    """Wall segment of each element: equal sectors of the angle about the cavity centre, counted
    from ``offset_deg`` (degrees, from +x) in the direction of increasing angle."""
    integer("n_segments", n_segments, 2)
    ang = np.degrees(geometry.angle(mesh.centroids)) - float(offset_deg)
    # np.mod of a tiny negative angle can round to 360.0 itself: that is segment 0 as well
    return np.floor(np.mod(ang, 360.0) / (360.0 / n_segments)).astype(int) % int(n_segments)


def segmental_active_stress(mesh: TriMesh, geometry: LVGeometry, n_segments: int = 6, offset_deg: float = 0.0,
                            scale: float = 1e3, thickness: float = 1.0, **noise) -> Effect:
    """Active circumferential and radial stress with its own amplitudes in each wall segment.

    ``n_segments`` equal angular sectors (six, as the clinical mid-ventricular segment model),
    each with a circumferential and a radial amplitude (``2 n_segments`` states, ordered segment
    by segment): regional timing or strength of contraction, an akinetic segment (its amplitudes
    stay near zero) or a hypokinetic one.
    """
    seg = segment_labels(mesh, geometry, n_segments, offset_deg)
    ucc = _uniaxial(_element_direction(mesh, geometry.circumferential)) * scale
    urr = _uniaxial(_element_direction(mesh, geometry.radial)) * scale
    cols = []
    for k in range(int(n_segments)):
        w = (seg == k).astype(float)[:, None]
        cols += [stress_loads(mesh, ucc * w, thickness), stress_loads(mesh, urr * w, thickness)]
    return Effect("active_segments", np.column_stack(cols), f"{scale:g} Pa",
                  description=f"active circumferential and radial stress in each of {n_segments} wall segments",
                  **_noise(noise))


def helical_active_stress(mesh: TriMesh, geometry: LVGeometry, scale: float = 1e3, thickness: float = 1.0,
                          **noise) -> Effect:
    """Active tension along fibres whose in-plane angle turns through the wall (2 states).

    A fibre direction ``d = cos(phi) e_c + sin(phi) e_r`` whose angle goes from ``+phi_0`` at the
    endocardium to ``-phi_0`` at the epicardium, ``phi = phi_0 (1 - 2 depth)``, carries the active
    stress ``a d d^T = a [e_c e_c + phi (e_c e_r + e_r e_c) + O(phi^2)]``. Its two terms, linear in
    their amplitudes: a circumferential tension, and a shear stress ``(1 - 2 depth) (e_c e_r +
    e_r e_c)`` that changes sign through the wall and produces the transmural shear E_rc of a
    twisting ventricle. The angle's size and sign are the ratio of the two amplitudes.
    """
    depth = transmural_depth(mesh, geometry)
    ec = _element_direction(mesh, geometry.circumferential)
    er = _element_direction(mesh, geometry.radial)
    shear = 2.0 * _symmetric(ec, er) * (1.0 - 2.0 * depth)[:, None]
    G = np.column_stack([stress_loads(mesh, _uniaxial(ec) * scale, thickness),
                         stress_loads(mesh, shear * scale, thickness)])
    return Effect("active_helical", G, f"{scale:g} Pa",
                  description="active tension along fibres turning through the wall: circumferential and "
                              "transmural shear amplitudes", **_noise(noise))


def angular_basis(angle, order: int) -> np.ndarray:
    """Real Fourier basis in the angle about the cavity centre, ``(n, 2 order + 1)``.

    Columns ``1, cos(theta), sin(theta), ..., cos(order theta), sin(order theta)`` at the
    angles ``angle`` (rad): the smooth periodic functions around the wall up to ``order``
    waves per turn.
    """
    integer("order", order, 0)
    a = np.asarray(angle, float)
    cols = [np.ones_like(a)]
    for k in range(1, int(order) + 1):
        cols += [np.cos(k * a), np.sin(k * a)]
    return np.column_stack(cols)


#: Stress components of :func:`harmonic_active_stress`: circumferential tension, radial
#: tension, and the radial-circumferential shear ``e_c e_r + e_r e_c``.
HARMONIC_COMPONENTS = ("cc", "rr", "rc")


def harmonic_active_stress(mesh: TriMesh, geometry: LVGeometry, order: int = 2, components=("cc", "rr"),
                           transmural: bool = True, scale: float = 1e3, thickness: float = 1.0,
                           **noise) -> Effect:
    """Active stress whose amplitude is a smooth field over the wall: angular harmonics times a
    linear transmural profile.

    The active stress in an element at angle ``theta`` and transmural depth ``d`` (0 endo, 1 epi) is
    ``sum_c sum_j sum_m a_{c j m} phi_j(theta) psi_m(d) S_c``, with ``phi_j`` the real Fourier
    basis up to ``order`` (:func:`angular_basis`), ``psi = (1 - d, d)`` (or ``psi = 1`` when
    ``transmural`` is false) and ``S_c`` the unit stress of component ``c`` in the local polar
    frame (``cc``: circumferential tension, ``rr``: radial tension, ``rc``: the symmetric shear
    ``e_c e_r + e_r e_c``). States are ordered component, then angular function, then depth
    function: ``len(components) (2 order + 1) (2 if transmural else 1)`` amplitudes, one unit of
    each being ``scale`` Pa.

    Between the uniform stresses (``active_polar`` is ``order=0, transmural=False``) and six
    independent segments, this is regional contraction that varies smoothly around and through
    the wall, as strain in a real ventricle does, without the segments' jumps at their borders.

    Parameters
    ----------
    mesh, geometry : TriMesh, LVGeometry
        The wall (m) and its cavity centre, contours and local directions.
    order : int
        Highest angular harmonic (waves per turn, >= 0).
    components : sequence of {"cc", "rr", "rc"}
        Stress components (:data:`HARMONIC_COMPONENTS`), distinct.
    transmural : bool
        Each angular function times ``(1 - depth, depth)`` (True) or uniform through the wall.
    scale : float
        Stress of one unit of each amplitude (Pa).
    thickness : float
        Out-of-plane thickness of the slice (m).
    **noise
        ``process_std``, ``initial_std``, ``initial``, ``rate_std`` of :class:`Effect` (units of
        the amplitudes).
    """
    integer("order", order, 0)
    comps = tuple(components)
    if not comps or len(set(comps)) != len(comps) or any(c not in HARMONIC_COMPONENTS for c in comps):
        raise ValueError(f"components: expected distinct names from {HARMONIC_COMPONENTS}, got {components!r}")
    positive("scale", scale, "Pa")
    ec = _element_direction(mesh, geometry.circumferential)
    er = _element_direction(mesh, geometry.radial)
    unit = {"cc": _uniaxial(ec), "rr": _uniaxial(er), "rc": 2.0 * _symmetric(ec, er)}
    phi = angular_basis(geometry.angle(mesh.centroids), order)
    depth = transmural_depth(mesh, geometry)
    psi = np.column_stack([1.0 - depth, depth]) if transmural else np.ones((mesh.n_elements, 1))
    cols = [stress_loads(mesh, unit[c] * scale * (phi[:, j] * psi[:, m])[:, None], thickness)
            for c in comps for j in range(phi.shape[1]) for m in range(psi.shape[1])]
    return Effect("active_harmonic", np.column_stack(cols), f"{scale:g} Pa",
                  description=f"active {'/'.join(comps)} stress, angular harmonics up to order {order}"
                              f"{' times a linear transmural profile' if transmural else ''}",
                  **_noise(noise))


def in_plane_dilatation(mesh: TriMesh, scale: float = 1e3, thickness: float = 1.0, **noise) -> Effect:
    """Isotropic in-plane active stress: area change of the slice that plane strain forbids
    (through-plane motion, longitudinal shortening). Positive states shrink the area."""
    sigma = np.tile([scale, scale, 0.0], (mesh.n_elements, 1))
    G = stress_loads(mesh, sigma, thickness)[:, None]
    return Effect("dilatation", G, f"{scale:g} Pa",
                  description="isotropic in-plane active stress (through-plane motion)", **_noise(noise))


def cavity_pressure(mesh: TriMesh, geometry: LVGeometry, scale: float = 1e3, thickness: float = 1.0,
                    **noise) -> Effect:
    """Unknown blood pressure on the endocardium (pushing the wall outwards), one amplitude."""
    G = pressure_load(mesh, geometry.endo_edges, scale, thickness)[:, None]
    return Effect("cavity_pressure", G, f"{scale:g} Pa",
                  description="cavity pressure on the endocardium (one amplitude per frame)", **_noise(noise))


def _noise(noise: dict) -> dict:
    out = {"process_std": 1.0, "initial_std": 1.0, "initial": 0.0}
    out.update(noise)
    return out


#: Effect builders by configuration name: ``builder(mesh, geometry, **options) -> Effect``.
CATALOGUE = {
    "active_circumferential": lambda mesh, geo, **kw: active_stress(mesh, geo, "circumferential", **kw),
    "active_radial": lambda mesh, geo, **kw: active_stress(mesh, geo, "radial", **kw),
    "active_polar": lambda mesh, geo, **kw: polar_active_stress(mesh, geo, **kw),
    "active_transmural": lambda mesh, geo, **kw: transmural_active_stress(mesh, geo, **kw),
    "dilatation": lambda mesh, geo, **kw: in_plane_dilatation(mesh, **kw),
    "cavity_pressure": lambda mesh, geo, **kw: cavity_pressure(mesh, geo, **kw),
    "active_segments": lambda mesh, geo, **kw: segmental_active_stress(mesh, geo, **kw),
    "active_helical": lambda mesh, geo, **kw: helical_active_stress(mesh, geo, **kw),
    "active_harmonic": lambda mesh, geo, **kw: harmonic_active_stress(mesh, geo, **kw),
}

#: Catalogue effects that the rounds (:func:`sfem_filters.cardiac.closing.closing_the_loop`) try
#: only when asked for by name (``candidates=``, ``--effects``): ``active_harmonic`` spends 20
#: amplitudes per frame, and the rounds' behaviour with it among the candidates has no test with
#: a known answer yet (see the docs' explanation page on the measured slice).
EXPLICIT_ONLY = ("active_harmonic",)


#: Catalogue effects whose loads depend on where the angles about the cavity centre start.
ANGULAR = ("active_segments",)


def build_effects(names, mesh: TriMesh, geometry: LVGeometry, angle_origin_deg: float = 0.0, **options) -> list:
    """Effects from configuration names (see :data:`CATALOGUE`): a sequence of names, or one name.

    ``angle_origin_deg`` (degrees from +x): where segment 0 of the effects in :data:`ANGULAR`
    starts (their ``offset_deg``); the others do not depend on it (``active_harmonic``'s cosines
    and sines span the same loads from any origin, but the phases of its amplitudes are counted
    from +x)."""
    if "offset_deg" in options:
        raise ValueError("options: the segments' offset_deg is set by angle_origin_deg; pass that instead")
    out = []
    for name in ([names] if isinstance(names, str) else names):
        if name not in CATALOGUE:
            raise ValueError(f"effects: unknown effect {name!r}; expected one of {sorted(CATALOGUE)}")
        extra = {"offset_deg": float(angle_origin_deg)} if name in ANGULAR else {}
        out.append(CATALOGUE[name](mesh, geometry, **options, **extra))
    return out
