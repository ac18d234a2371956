"""The stochastic finite-element model of the myocardium as a filterpy plug-in.

:class:`SFEMModel` supplies everything filterpy's ``ExtendedKalmanFilter`` needs: the
transition ``fx`` (Eq. 19) and its Jacobian ``F_jacobian`` (Eq. 31 with M_t of Eq. 33),
the measurement ``hx`` and its Jacobian ``H_jacobian`` (Eqs. 21-22), and ``Q``, ``R``,
``x0``, ``P0`` (Eq. 34). The paper's three strategies are configurations of this one class:

* material fixed (``parameterisation=None``): a linear Kalman filter on ``x = [U; U']`` with the
  given material, uniform (``"uniform_kf"``) or the true one (``"perfect_kf"``);
* material estimated (``parameterisation=Parameterisation``): the joint EKF on ``z = [x; theta]``
  (``"joint_ekf"``), theta being log E and logit(2 nu) through the parameterisation.

Frame indices ``t`` are 0-based. ``fx(z, t)`` moves the state from frame t to frame t + 1
under the load ``loads[t + 1]``, held over that interval (zero-order hold).
"""
from __future__ import annotations

import copy
import hashlib
from collections import OrderedDict

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from ._validate import as_float_array, non_negative, positive
from .fem import modal_stiffness
from .fem.dofs import DofMap
from .fem.elasticity import mass_matrix, stiffness_matrix
from .fem.material import Material, Parameterisation
from .fem.mesh import TriMesh, check_mesh
from .fem.modal_stiffness import modal_stiffness_budget, modal_stiffness_pays, stiffness_directions, stiffness_plan
from .fem.reference_zoh import reference_sensitivity, scatter_direction
from .fem.restart_state import load_patterns, modal_coordinates, restart_outputs
from .fem.statespace import ModalSystem
from .filtering.linear import LinearObservation
from .filtering.linearised import LinearisedModel, linearise_dense
from .filtering.protocol import measurement_cov, process_profile
from .resources import frame_map

__all__ = ["SFEMModel"]


def _std_vector(name: str, value, n: int, unit: str) -> np.ndarray:
    v = np.broadcast_to(as_float_array(name, value), (n,)) if np.ndim(value) == 0 else \
        as_float_array(name, value, shape=(n,))
    if np.any(v <= 0):
        raise ValueError(f"{name}: expected standard deviations > 0 {unit}, got minimum {float(v.min())!r}")
    return np.array(v, float)


class SFEMModel(LinearObservation):
    """Linear-elastic FEM dynamics with optional material estimation (Shi & Liu 2003).

    Parameters
    ----------
    mesh : TriMesh
        Mesh in metres.
    material : Material
        The material used when it is not estimated, and the initial estimate when it is.
    loads : (n_frames, n_dofs) array
        Global nodal loads in N; ``loads[t]`` is held over the interval from frame t-1 to
        frame t (``loads[0]`` is unused).
    observation_operator : (n_obs, n_dofs) array or sparse matrix
        D of Eq. (12): the observed combinations of global displacements (m); the measured
        numbers themselves are the observations.
    frame_interval : float
        Time between frames in s.
    fixed_dofs : array of int
        Global dofs held at zero; they are removed from the state.
    density : float
        Mass density in kg/m^3.
    alpha, beta : float
        Rayleigh damping ``C = alpha M + beta K`` (alpha in 1/s, beta in s).
    measurement_std : float, (n_obs,) or (n_frames, n_obs) array
        Standard deviation of the observation noise in m (m/s for velocity rows); ``R`` is
        diagonal. A 2D array gives each frame its own R (data weighted by a per-frame
        confidence, section 2.6): :meth:`R_at` returns it and ``R`` holds the frame average.
    process_std : (float, float)
        Per-frame process noise standard deviations of displacement (m) and velocity (m/s).
    initial_std : (float, float)
        Standard deviations of P1(0) for displacement (m) and velocity (m/s).
    parameterisation : Parameterisation, optional
        Append these material parameters to the state (joint EKF). ``None``: material fixed.
    prior_std : (float, float)
        P3(0) standard deviations of theta_E (log E) and theta_nu (logit 2 nu) (diagonal P3).
    prior_cov : (n_params, n_params) array, optional
        A full P3(0) instead, e.g. :func:`sfem_filters.fem.material.correlated_prior`.
    material_process_std : (float, float)
        Process noise of theta per frame (default 0: the material is constant).
    penalty : (n_dofs, n_dofs) sparse matrix, optional
        Penalty springs (N/m) added to K, section 2.7 (their load goes into ``loads``).
    thickness : float
        Out-of-plane thickness in m.
    lumped_mass : bool
        Lumped instead of consistent mass.
    jacobian : {"modal", "expm_frechet"}
        How M_t is computed: the exact modal Daleckii-Krein form (fast) or one
        ``scipy.linalg.expm_frechet`` per parameter (reference).
    effects : sequence of :class:`sfem_filters.cardiac.effects.Effect`
        Extra model terms, each a load ``G_e eta_e`` (N) linear in its states ``eta_e``
        (random walks), appended to the state after the kinematics: ``z = [x; eta; theta]``.
    velocity_operator : (n_obs, n_dofs) array or sparse matrix, optional
        D_v of Eq. (13): rows observing velocities (m/s), e.g. phase-contrast MR:
        ``H = [D, D_v, 0]``; with it, displacement and velocity rows are stacked, displacement rows
        first, and ``measurement_std`` covers both (m and m/s).
    initial_displacement : (n_dofs,) array, optional
        Displacement (m) of the initial state (default zero: at rest in the mesh geometry).
    process_load_std : float, (n_free,) or (n_free, k) array, optional
        Process noise as random nodal loads (N per frame, zero allowed) on the free dofs: adds
        ``B Sigma_w B^T`` to the kinematic block of Q, a spatially smooth (elastically
        correlated) displacement and velocity noise, evaluated at the initial material.
        Standard deviations per dof (independent loads), or a matrix W whose columns are
        independent unit-variance load patterns (``Sigma_w = W W^T``, loads correlated in space).

    outputs : dict, optional
        Extra output operators ``{name: (k, n_dofs) matrix}`` on the global displacements (m), for
        example polar strains, whose smoothed uncertainty a smoother reports
        (:meth:`output_operators`).

    Notes
    -----
    The state is ``z = [U; U'; eta; theta]``. Each cyclic loop restarts the first
    :attr:`n_restart` entries (kinematics and effect states) and carries theta.
    """

    def __init__(self, mesh: TriMesh, material: Material, loads, observation_operator, frame_interval: float,
                 fixed_dofs=(), *, density: float = 1050.0, alpha: float = 0.0, beta: float = 0.0,
                 measurement_std=1e-4, process_std=(5e-5, 5e-3), initial_std=(1e-4, 1e-3),
                 parameterisation: Parameterisation | None = None, prior_std=(0.3, 1.0),
                 material_process_std=(0.0, 0.0), penalty=None, thickness: float = 1.0,
                 lumped_mass: bool = False, jacobian: str = "modal", effects=(), initial_displacement=None,
                 process_load_std=None, prior_cov=None, velocity_operator=None, outputs=None):
        check_mesh("mesh", mesh)
        if not isinstance(material, Material):
            raise TypeError(f"material: expected a Material, got {type(material).__name__}")
        if material.n_elements != mesh.n_elements:
            raise ValueError(f"material: expected {mesh.n_elements} elements, got {material.n_elements}")
        if jacobian not in ("modal", "expm_frechet"):
            raise ValueError(f"jacobian: expected 'modal' or 'expm_frechet', got {jacobian!r}")
        self.mesh = mesh
        self.material = material
        self.frame_interval = positive("frame_interval", frame_interval, "s")
        self.density = positive("density", density, "kg/m^3")
        self.thickness = positive("thickness", thickness, "m")
        self.alpha = non_negative("alpha", alpha, "1/s")
        self.beta = non_negative("beta", beta, "s")
        self.jacobian = jacobian
        # the exact discretisation over the free dofs (a test may put another class with the same
        # interface here: step, transition_matrix, input_response, sensitivity)
        self._system_class = ModalSystem
        self._outputs = {}
        for name, op in (outputs or {}).items():
            op = sp.csr_matrix(op)
            if op.shape[1] != mesh.n_dofs:
                raise ValueError(f"outputs: expected output {name!r} to have {mesh.n_dofs} columns (n_dofs), "
                                 f"got {op.shape[1]}")
            self._outputs[str(name)] = op
        self.dofmap = DofMap(mesh.n_dofs, fixed_dofs)
        n = self.dofmap.n_free
        loads = as_float_array("loads", loads, shape=(None, mesh.n_dofs))
        if len(loads) < 2:
            raise ValueError(f"loads: expected at least 2 frames, got {len(loads)}")
        self.loads = loads
        self._w = self.dofmap.restrict(loads)
        D = sp.csr_matrix(as_float_array("observation_operator", observation_operator, shape=(None, None))) \
            if not sp.issparse(observation_operator) else observation_operator.tocsr()
        if not np.all(np.isfinite(D.data)):
            raise ValueError("observation_operator: expected finite values, got NaN or inf entries")
        if D.shape[0] == 0:
            raise ValueError("observation_operator: expected at least one observed row, got none")
        if D.shape[1] != mesh.n_dofs:
            raise ValueError(f"observation_operator: expected {mesh.n_dofs} columns (n_dofs), got {D.shape[1]}")
        self.observation_operator = D
        self.M = self.dofmap.restrict_matrix(mass_matrix(mesh, density, thickness, lumped_mass)).toarray()
        self.penalty = None if penalty is None else self.dofmap.restrict_matrix(sp.csr_matrix(penalty)).toarray()
        self._cache: OrderedDict = OrderedDict()
        self._modal_cache: OrderedDict = OrderedDict()
        self._directions_dofs = self.dofmap.free_index()[mesh.element_dofs]
        self.parameterisation = parameterisation
        if parameterisation is not None and not isinstance(parameterisation, Parameterisation):
            raise TypeError(f"parameterisation: expected a Parameterisation or None, got "
                            f"{type(parameterisation).__name__}")
        if parameterisation is not None and parameterisation.n_elements != mesh.n_elements:
            raise ValueError(f"parameterisation: expected a parameterisation of {mesh.n_elements} elements, "
                             f"got {parameterisation.n_elements}")
        self.effects = tuple(effects)
        for e in self.effects:
            if e.loads.shape[0] != mesh.n_dofs:
                raise ValueError(f"effects: effect {e.name!r} has loads for {e.loads.shape[0]} dofs, "
                                 f"expected {mesh.n_dofs}")
        G = [self.dofmap.restrict(np.asarray(e.state_loads(), float).T).T for e in self.effects]
        self._G = np.hstack(G) if G else np.zeros((n, 0))
        self._eta_transition = sla.block_diag(*[e.transition() for e in self.effects]) if G else np.zeros((0, 0))
        self.dim_x = 2 * n
        self.dim_eta = self._G.shape[1]
        self.n_restart = self.dim_x + self.dim_eta
        self.dim_theta = 0 if parameterisation is None else parameterisation.n_params
        self.dim_state = self.n_restart + self.dim_theta
        Dv = None
        if velocity_operator is not None:
            Dv = sp.csr_matrix(velocity_operator)
            if Dv.shape[1] != mesh.n_dofs:
                raise ValueError(f"velocity_operator: expected {mesh.n_dofs} columns (n_dofs), got {Dv.shape[1]}")
        self.velocity_operator = Dv
        n_u = D.shape[0]
        self.dim_obs = n_u + (0 if Dv is None else Dv.shape[0])
        # H = [D 0] over the free dofs (Eq. 22), with velocity rows [0 D_v 0] below (Eq. 13)
        H = np.zeros((self.dim_obs, self.dim_state))
        H[:n_u, :n] = D[:, self.dofmap.free].toarray()
        if Dv is not None:
            H[n_u:, n:2 * n] = Dv[:, self.dofmap.free].toarray()
        self._H = H
        self._R_frames = None
        if np.ndim(measurement_std) == 2:
            sd2 = as_float_array("measurement_std", measurement_std, shape=(len(loads), self.dim_obs))
            if np.any(sd2 <= 0):
                raise ValueError(f"measurement_std: expected standard deviations > 0 m, got minimum "
                                 f"{float(sd2.min())!r}")
            self._R_frames = sd2 ** 2
            self.R = np.diag(self._R_frames.mean(axis=0))
        else:
            sd_m = _std_vector("measurement_std", measurement_std, self.dim_obs, "m")
            self.R = np.diag(sd_m ** 2)
        pu, pv = process_std
        q = [np.full(n, positive("process_std[0]", pu, "m")) ** 2,
             np.full(n, positive("process_std[1]", pv, "m/s")) ** 2]
        iu, iv = initial_std
        p1 = [np.full(n, positive("initial_std[0]", iu, "m")) ** 2,
              np.full(n, positive("initial_std[1]", iv, "m/s")) ** 2]
        if parameterisation is not None:
            self.theta0 = parameterisation.theta_of(material)
            sE, snu = prior_std
            n_nu = parameterisation.n_params - parameterisation.n_E
            p3 = np.concatenate([np.full(parameterisation.n_E, positive("prior_std[0]", sE)) ** 2,
                                 np.full(n_nu, positive("prior_std[1]", snu)) ** 2])
            mE, mnu = (non_negative(f"material_process_std[{i}]", v) for i, v in enumerate(material_process_std))
            q3 = np.concatenate([np.full(parameterisation.n_E, float(mE)) ** 2,
                                 np.full(parameterisation.n_params - parameterisation.n_E, float(mnu)) ** 2])
        else:
            self.theta0 = np.zeros(0)
            p3 = q3 = np.zeros(0)
        q_eta = [e.process_variances() for e in self.effects]
        p_eta = [e.initial_variances() for e in self.effects]
        self.Q = np.diag(np.concatenate(q + q_eta + [q3]))
        if process_load_std is not None:
            # random loads (N per dof per frame) through the dynamics: smooth, elastically
            # correlated displacement noise B Sigma_w B^T (evaluated at the initial material)
            W = load_patterns(process_load_std, n)
            BS = self.system(self.theta0 if parameterisation is not None else None).input_response(W)
            self.Q[: 2 * n, : 2 * n] += BS @ BS.T
        # Eq. (34): P0 = diag(P1, P3) with zero cross-covariance P2 (and effect states apart).
        self.P0 = np.diag(np.concatenate(p1 + p_eta + [p3]))
        if prior_cov is not None:
            if parameterisation is None:
                raise ValueError("prior_cov: given, but the material is not estimated (parameterisation=None)")
            C = as_float_array("prior_cov", prior_cov, shape=(parameterisation.n_params, parameterisation.n_params))
            if np.abs(C - C.T).max() > 1e-12 * np.abs(C).max() or np.linalg.eigvalsh(C).min() <= 0:
                raise ValueError("prior_cov: expected a symmetric positive definite matrix")
            nr = 2 * n + sum(len(v) for v in p_eta)
            self.P0[nr:, nr:] = C
        u0 = np.zeros(n) if initial_displacement is None else self.dofmap.restrict(
            as_float_array("initial_displacement", initial_displacement, shape=(mesh.n_dofs,)))
        eta0 = [e.initial_states() for e in self.effects]
        self.x0 = np.concatenate([u0, np.zeros(n)] + eta0 + [self.theta0])

    # ------------------------------------------------------------------ configuration
    @property
    def n_frames(self) -> int:
        """Number of frames (rows of ``loads``)."""
        return len(self.loads)

    @property
    def estimates_material(self) -> bool:
        """True when the state carries material parameters theta to estimate (a ``parameterisation`` was given)."""
        return self.parameterisation is not None

    def theta_of(self, z) -> np.ndarray:
        """Material parameters of an augmented state (empty when the material is fixed)."""
        return np.asarray(z, float).ravel()[self.n_restart:]

    def eta_of(self, z) -> np.ndarray:
        """Effect states of an augmented state, in the order of :attr:`effects`."""
        return np.asarray(z, float).ravel()[self.dim_x:self.n_restart]

    def material_of_theta(self, theta) -> Material:
        """Material of parameters theta (the fixed material when it is not estimated)."""
        if self.parameterisation is None:
            return self.material
        return self.parameterisation.material(theta)

    def physical_parameters(self, theta) -> np.ndarray:
        """E (Pa) of every element followed by nu: the physical units of the stop rule
        (:class:`sfem_filters.filtering.protocol.PhysicalParameters`)."""
        mat = self.material_of_theta(theta)
        return np.concatenate([mat.E, mat.nu])

    def physical_jacobian(self, theta):
        """d(E, nu)/d theta at ``theta``, sparse (2 n_elements, n_params): the rows the stop
        rule measures a step on (:class:`sfem_filters.filtering.protocol.PhysicalJacobian`),
        ``E_e`` times the parameterisation's d log E_e / d theta, then d nu_e / d theta."""
        if self.parameterisation is None:
            return sp.csr_matrix((2 * self.mesh.n_elements, 0))
        mat = self.material_of_theta(theta)
        J = self.parameterisation.element_jacobian(mat)
        return sp.diags(np.concatenate([mat.E, np.ones(mat.n_elements)])) @ J

    def load_response(self, load_matrix, z) -> np.ndarray:
        """Response ``H B(theta) G`` of the next predicted observation to unit loads (m per unit).

        ``load_matrix`` G is (n_dofs, k), global nodal loads in N per unit of each column, held
        over one frame; theta is that of state ``z``
        (:class:`sfem_filters.filtering.protocol.LoadResponse`, used by the score test).
        """
        G = as_float_array("load_matrix", load_matrix, shape=(self.dofmap.n_dofs, None))
        G = self.dofmap.restrict(G.T).T
        system = self.system(self.theta_of(z) if self.estimates_material else None)
        return self._H[:, : self.dim_x] @ system.input_response(G)

    def material_sd(self, theta, P_theta) -> tuple:
        """Posterior standard deviations of each element's log E and of its nu.

        ``var(log E_e) = b_e^T P_E b_e`` through the parameterisation's basis rows ``b_e``, and
        ``sd(nu_e) = nu_e (1 - 2 nu_e) sd(logit 2 nu_e)`` (the delta method at ``theta``).
        Returns ``(sd_log_E, sd_nu)``, each (n_elements,): a relative sd of E and an sd of nu.
        """
        if self.parameterisation is None:
            raise ValueError("P_theta: the material is fixed (parameterisation=None): it has no posterior sd")
        par = self.parameterisation
        P = as_float_array("P_theta", P_theta, shape=(par.n_params, par.n_params))
        k = par.n_E
        BE, Bn = par.basis_E, par.basis_nu
        sd_E = np.sqrt(np.maximum(np.einsum("ij,ij->i", np.asarray(BE @ P[:k, :k]), BE.toarray()), 0.0))
        sd_s = np.sqrt(np.maximum(np.einsum("ij,ij->i", np.asarray(Bn @ P[k:, k:]), Bn.toarray()), 0.0))
        nu = self.material_of_theta(theta).nu
        return sd_E, nu * (1.0 - 2.0 * nu) * sd_s

    def material_of(self, z=None) -> Material:
        """Material of state z: the estimate in the joint EKF, the fixed one otherwise."""
        return self.material_of_theta(self.theta0 if z is None else self.theta_of(z))

    def displacements(self, z) -> np.ndarray:
        """Global displacement vector (m) of state(s) z, shape (..., n_dofs)."""
        z = np.asarray(z, float)
        return self.dofmap.expand(z[..., : self.dim_x // 2])

    def velocities(self, z) -> np.ndarray:
        """Global velocity vector (m/s) of state(s) z, shape (..., n_dofs)."""
        z = np.asarray(z, float)
        return self.dofmap.expand(z[..., self.dim_x // 2: self.dim_x])

    # ------------------------------------------------------------------ mechanics
    def system(self, theta=None) -> ModalSystem:
        """The discretised dynamics for material parameters theta (cached)."""
        mat = self.material if self.parameterisation is None else self.parameterisation.material(
            self.theta0 if theta is None else theta)
        return self._entry(mat)[0]

    def R_at(self, t: int) -> np.ndarray:
        """Measurement noise covariance of frame ``t`` (m^2, m^2/s^2 for velocity rows)."""
        return self.R if self._R_frames is None else np.diag(self._R_frames[t])

    def with_process_noise(self, scale: float) -> "SFEMModel":
        """This model with every process noise covariance (kinematics, effect states, material
        random walk) multiplied by ``scale`` (> 0, dimensionless): ``Q`` becomes ``scale * Q``.

        Shares the mesh, matrices and the cache of discretised dynamics (which do not depend on
        Q) with this model; the linearisation cache, which holds Q, is its own.
        """
        scale = positive("scale", scale)
        out = copy.copy(self)
        out.Q = self.Q * scale
        out._modal_cache = OrderedDict()
        return out

    def with_measurement_noise(self, scale: float) -> "SFEMModel":
        """This model with every measurement noise covariance (R and each frame's R) multiplied
        by ``scale`` (> 0, dimensionless). Shares the mesh, matrices and the cache of discretised
        dynamics with this model; the linearisation cache, which holds R, is its own."""
        scale = positive("scale", scale)
        out = copy.copy(self)
        out.R = self.R * scale
        if self._R_frames is not None:
            out._R_frames = self._R_frames * scale
        out._modal_cache = OrderedDict()
        return out

    def fingerprint(self) -> str:
        """Hash of everything that defines the model (for checkpoints)."""
        h = hashlib.sha256()
        parts = [self.mesh.nodes, self.mesh.elements, self.loads, self.material.E, self.material.nu, self.M,
                 np.array([self.alpha, self.beta, self.frame_interval, self.density, self.thickness]),
                 self.dofmap.fixed, self._G, self._H, self.R, self.Q, self.P0, np.asarray(self.x0, float),
                 self._eta_transition]
        if self._R_frames is not None:
            parts.append(self._R_frames)
        if self.penalty is not None:
            parts.append(self.penalty)
        if self.parameterisation is not None:
            parts += [self.parameterisation.basis_E.toarray(), self.parameterisation.basis_nu.toarray()]
            if self.parameterisation.offset_E is not None:
                parts.append(self.parameterisation.offset_E)
        for a in parts:
            h.update(np.ascontiguousarray(a).tobytes())
        h.update(f"{self.jacobian},{[e.name for e in self.effects]},{self._system_class.__module__}."
                 f"{self._system_class.__qualname__}".encode())
        return h.hexdigest()

    def _entry(self, mat: Material):
        key = (mat.E.tobytes() + mat.nu.tobytes()
               + np.array([self.alpha, self.beta, self.frame_interval]).tobytes())
        hit = self._cache.get(key)
        if hit is not None:
            self._cache.move_to_end(key)
            return hit
        K = self.dofmap.restrict_matrix(stiffness_matrix(self.mesh, mat.E, mat.nu, self.thickness)).toarray()
        if self.penalty is not None:
            K = K + self.penalty
        system = self._system_class(self.M, K, self.alpha, self.beta, self.frame_interval)
        entry = (system, K, mat)
        self._cache[key] = entry
        if len(self._cache) > 4:
            self._cache.popitem(last=False)
        return entry

    def _split(self, z):
        """(z, x, eta, theta) views of a state."""
        z = np.asarray(z, float)
        flat = z.ravel()
        if flat.shape != (self.dim_state,):
            raise ValueError(f"z: expected a state of length {self.dim_state}, got {flat.shape[0]}")
        return z, flat[: self.dim_x], flat[self.dim_x:self.n_restart], flat[self.n_restart:]

    def load(self, z, t) -> np.ndarray:
        """Load over the free dofs (N) held from frame t to t + 1: external plus effects."""
        return self._w[t + 1] + self._G @ self.eta_of(z)

    def _check_frame(self, t, last: int) -> int:
        t = int(t)
        if not 0 <= t <= last:
            raise ValueError(f"t: expected a frame index in [0, {last}], got {t}")
        return t

    def fx(self, z, t):
        """State at frame t + 1 from state z at frame t, Eq. (19): [A x + B w_t; eta; theta]."""
        z, x, eta, theta = self._split(z)
        t = self._check_frame(t, self.n_frames - 2)
        system = self.system(theta if self.parameterisation is not None else None)
        out = np.concatenate([system.step(x, self.load(z, t)), self._eta_transition @ eta, theta])
        return out.reshape(z.shape)

    def sensitivity(self, z, t) -> np.ndarray:
        """M_t = d(A(theta) x + B(theta) w_t)/d theta (Eq. 33), shape (dim_x, dim_theta)."""
        if self.parameterisation is None:
            return np.zeros((self.dim_x, 0))
        z, x, _, theta = self._split(z)
        t = self._check_frame(t, self.n_frames - 2)
        return self._sensitivity_at(theta, x, self.load(z, t))

    def _sensitivity_at(self, theta, x, w) -> np.ndarray:
        """d(A(theta) x + B(theta) w)/d theta for given x (m, m/s) and load w (N)."""
        mat = self.parameterisation.material(theta)
        system, K, _ = self._entry(mat)
        dirs = stiffness_directions(self.mesh, mat, self.thickness)
        dofs = np.concatenate([self._directions_dofs, self._directions_dofs])
        J = self.parameterisation.element_jacobian(mat)          # d(log E_e, nu_e)/d theta
        if self.jacobian == "modal":
            return system.sensitivity(x, w, dirs, dofs, combine=J)
        per_element = reference_sensitivity(self.M, K, self.alpha, self.beta, self.frame_interval, x, w,
                                            [scatter_direction(d, dd, self.dim_x // 2) for d, dd in zip(dirs, dofs)])
        return np.asarray((J.T @ per_element.T).T)

    def transition_derivatives(self, z, t=None) -> np.ndarray:
        """dA'/dtheta_i of the restart block A' = [[A, B G], [0, T_eta]], (dim_theta, n_restart, n_restart).

        Column k of dA/dtheta_i is the sensitivity of ``A e_k`` (no load), column j of
        d(B G)/dtheta_i that of ``B G e_j``: one exact sensitivity (Eq. 33) per restart state,
        so this costs n_restart times :meth:`sensitivity`. Used by Ljung's modification of the
        coupling term (Eq. 40), which needs it for few parameters only.
        """
        if self.parameterisation is None:
            return np.zeros((0, self.n_restart, self.n_restart))
        _, _, _, theta = self._split(z)
        n = self.dim_x // 2
        out = np.zeros((self.dim_theta, self.n_restart, self.n_restart))
        zero_w = np.zeros(n)
        for k in range(self.dim_x):
            e = np.zeros(self.dim_x)
            e[k] = 1.0
            out[:, : self.dim_x, k] = self._sensitivity_at(theta, e, zero_w).T
        for j in range(self.dim_eta):
            out[:, : self.dim_x, self.dim_x + j] = self._sensitivity_at(theta, np.zeros(self.dim_x),
                                                                        self._G[:, j]).T
        return out

    def _stiffness_budget(self) -> float:
        """:func:`~sfem_filters.fem.modal_stiffness.modal_stiffness_budget`, the automatic one read
        once per model: every linearisation of a run takes the same route, whatever else the
        machine's memory does (:data:`~sfem_filters.fem.modal_stiffness.MODAL_STIFFNESS_BYTES`, where
        set, is read every time)."""
        if modal_stiffness.MODAL_STIFFNESS_BYTES is not None:
            return float(modal_stiffness.MODAL_STIFFNESS_BYTES)
        if getattr(self, "_modal_budget", None) is None:
            self._modal_budget = modal_stiffness_budget()
        return self._modal_budget

    def linearise(self, states, sensitivity: bool = True) -> LinearisedModel:
        """The model about a trajectory, in modal coordinates (for the iterated smoother).

        With theta fixed at the trajectory's, the restart state ``r = [U; U'; eta]`` is written as
        ``r = V xi``, ``xi = [q; p; eta]`` with ``q = Phi^T M U`` and ``p = Phi^T M U'``
        (:class:`sfem_filters.fem.statespace.ModalSystem`): the transition is then sparse (the
        2 x 2 modal blocks, Eq. 15, plus the effects' held loads), so a smoother's time update
        costs O(n^2 p), and ``M_t`` (Eq. 33) comes straight out of the modal sensitivity without
        its modal-to-nodal product. ``states`` is (n_frames, dim_state) with one theta; ``M_t`` is
        taken at each frame's kinematic state and load (``sensitivity=False``: theta held fixed,
        no ``M_t``, the exact linear model of that material); the frames' ``M_t`` are taken side by
        side on :class:`~sfem_filters.resources.frame_threads` threads where set (the same numbers).
        The theta-dependent parts are cached for the last two materials. Falls back to
        :func:`sfem_filters.filtering.linearised.linearise_dense` for ``jacobian="expm_frechet"``
        or a discretisation that is not a :class:`ModalSystem`.
        """
        z = as_float_array("states", states, shape=(self.n_frames, self.dim_state))
        nr, nx, p = self.n_restart, self.dim_x, self.dim_theta
        theta = z[0, nr:]
        if p and np.any(z[:, nr:] != theta):
            raise ValueError("states: expected one value of theta along the trajectory (static parameters)")
        system = self.system(theta if self.parameterisation is not None else None)
        if self.jacobian != "modal" or not isinstance(system, ModalSystem):
            return linearise_dense(self, z, sensitivity)
        base = self._modal_coordinates(theta, system)
        T = self.n_frames
        p_out = p if sensitivity else 0
        M = np.zeros((T - 1, nr, p_out))
        if p_out:
            mat = self.parameterisation.material(theta)
            dirs = stiffness_directions(self.mesh, mat, self.thickness)
            dofs = np.concatenate([self._directions_dofs, self._directions_dofs])
            J = self.parameterisation.element_jacobian(mat)
            # one material for every frame: with few parameters, their modal stiffness derivatives
            # once beat the O(n^3) product of every frame's sensitivity (same numbers to round-off)
            G = None
            budget = self._stiffness_budget()
            if 8 * J.shape[1] * (nx // 2) ** 2 <= budget:      # else not even planned (many parameters)
                plan = stiffness_plan(J, dofs)
                if modal_stiffness_pays(plan, T - 1, nx // 2, budget):
                    G = system.modal_stiffness_derivatives(dirs, dofs, J, plan)
            def frame(t):
                M[t, :nx] = system.sensitivity(z[t, :nx], self.load(z[t], t), dirs, dofs, combine=J, modal=True,
                                               modal_stiffness=G)
            frame_map(frame, range(T - 1))          # frames side by side where frame_threads(n) says so
        P0 = np.asarray(self.P0)
        return LinearisedModel(A=base["A"], M=M, c=base["c"], H=base["H"], R=base["R"], Q=base["Q"],
                               xi0=base["xi0"], P0=base["P0"], theta_bar=theta[:p_out].copy(),
                               theta0=self.x0[nr:nr + p_out].copy(), P_theta0=P0[nr:nr + p_out, nr:nr + p_out].copy(),
                               V=base["V"], q_scale=process_profile(self))

    def _modal_coordinates(self, theta, system) -> dict:
        """The theta-dependent, trajectory-independent parts of :meth:`linearise` (cached)."""
        key = np.asarray(theta, float).tobytes()
        hit = self._modal_cache.get(key)
        if hit is not None:
            self._modal_cache.move_to_end(key)
            return hit
        out = {**modal_coordinates(system, self._G, self._eta_transition, self._w, self._H, self.Q, self.P0, self.x0),
               "R": np.array([measurement_cov(self, t) for t in range(self.n_frames)])}
        self._modal_cache[key] = out
        if len(self._modal_cache) > 2:
            self._modal_cache.popitem(last=False)
        return out

    def output_operators(self) -> dict:
        """Linear functions of the restart state whose uncertainty a smoother reports, (k, n_restart):

        ``displacement`` and ``velocity`` (the free dofs, m and m/s), ``strain``, the nodal strains
        (e_xx, e_yy, gamma_xy) of every node, row ``3 i + c``
        (:func:`~sfem_filters.fem.strain.nodal_strain_operator`), and the constructor's ``outputs``
        (:func:`~sfem_filters.fem.restart_state.restart_outputs`).
        """
        return restart_outputs(self.mesh, self.dofmap, self.n_restart, self._outputs)

    def F_jacobian(self, z, t) -> np.ndarray:
        """F_t = [[A, B G, M_t], [0, I, 0], [0, 0, I]] (Eq. 31), the exact Jacobian of :meth:`fx`."""
        z, x, _, theta = self._split(z)
        system = self.system(theta if self.parameterisation is not None else None)
        F = np.eye(self.dim_state)
        nx, nr = self.dim_x, self.n_restart
        system.transition_matrix(out=F[:nx, :nx])
        if self.dim_eta:
            F[:nx, nx:nr] = system.input_response(self._G)
            F[nx:nr, nx:nr] = self._eta_transition
        if self.parameterisation is not None:
            F[:nx, nr:] = self.sensitivity(z, t)
        return F
