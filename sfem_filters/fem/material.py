"""Material fields and their estimation parameters.

The filter never sees E and nu directly: it estimates unconstrained parameters
``theta = [theta_E, theta_nu]`` mapped linearly to per-element ``s_E = log(E / 1 Pa)`` and
``s_nu = logit(2 nu)``, so every estimate is admissible by construction (E > 0 and
0 < nu < 0.5), never clipped. The linear maps (bases) give per-element, per-region or
smooth low-dimensional parameterisations with one code path.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .._validate import as_float_array, check_material, integer, positive


#: Beyond these, exp overflows or sigmoid rounds to 1 (nu = 0.5 exactly) in double precision.
LOG_E_LIMIT = 700.0
LOGIT_NU_LIMIT = 36.0


def logit2(nu):
    """``logit(2 nu)``: maps 0 < nu < 0.5 onto the real line."""
    s = 2.0 * np.asarray(nu, float)
    return np.log(s) - np.log1p(-s)


def inv_logit2(s):
    """Inverse of :func:`logit2`: ``nu = sigmoid(s) / 2``, always in (0, 0.5)."""
    s = np.asarray(s, float)
    return 0.5 / (1.0 + np.exp(-s))


def dnu_ds(nu):
    """d nu / d logit(2 nu) = nu (1 - 2 nu)."""
    nu = np.asarray(nu, float)
    return nu * (1.0 - 2.0 * nu)


@dataclass(frozen=True)
class Material:
    """Per-element linear isotropic material.

    Parameters
    ----------
    E : (n_elements,) array
        Young's modulus of each element in Pa (> 0).
    nu : (n_elements,) array
        Poisson's ratio of each element (0 < nu < 0.5).
    """

    E: np.ndarray
    nu: np.ndarray

    def __post_init__(self):
        E, nu = check_material(np.atleast_1d(self.E), np.atleast_1d(self.nu))
        if E.shape != nu.shape:
            raise ValueError(f"nu: expected the shape of E {E.shape}, got {nu.shape}")
        object.__setattr__(self, "E", E)
        object.__setattr__(self, "nu", nu)

    @classmethod
    def uniform(cls, n_elements: int, E: float, nu: float) -> "Material":
        """The same E (Pa) and nu in every element."""
        n_elements = integer("n_elements", n_elements, 1)
        return cls(np.full(n_elements, float(E)), np.full(n_elements, float(nu)))

    @property
    def n_elements(self) -> int:
        """Number of elements (the length of ``E`` and ``nu``)."""
        return len(self.E)


@dataclass(frozen=True)
class Parameterisation:
    """Linear map from estimation parameters to per-element log E and logit(2 nu).

    ``s_E = basis_E @ theta_E`` and ``s_nu = basis_nu @ theta_nu`` with sparse or dense
    (n_elements, k) bases. Build it with :meth:`per_element`, :meth:`per_region` or
    :meth:`from_basis`.
    """

    basis_E: sp.csr_matrix
    basis_nu: sp.csr_matrix
    names: tuple = ()
    offset_E: np.ndarray | None = None     # s_E = offset_E + basis_E theta_E (default 0)
    level_index: int | None = None         # the column of basis_E that is the global stiffness level

    @classmethod
    def per_element(cls, n_elements: int) -> "Parameterisation":
        """One log E and one logit(2 nu) per element (the paper's choice)."""
        n_elements = integer("n_elements", n_elements, 1)
        eye = sp.identity(n_elements, format="csr")
        return cls(eye, eye, tuple(f"element {e}" for e in range(n_elements)))

    @classmethod
    def per_region(cls, labels) -> "Parameterisation":
        """One log E and one logit(2 nu) per region; ``labels`` gives each element's region."""
        labels = np.asarray(labels)
        if labels.ndim != 1 or labels.size == 0:
            raise ValueError(f"labels: expected one label per element, got shape {labels.shape}")
        uniq, idx = np.unique(labels, return_inverse=True)
        B = sp.csr_matrix((np.ones(len(labels)), (np.arange(len(labels)), idx)),
                          shape=(len(labels), len(uniq)))
        return cls(B, B, tuple(f"region {u}" for u in uniq))

    @classmethod
    def relative_regions(cls, labels, E_reference: float) -> "Parameterisation":
        """Relative stiffness between regions and a Poisson's ratio per region.

        ``log E = log E_reference + C theta_E`` with zero-mean contrasts C over the regions
        (area-unweighted), so the mean log E stays at ``E_reference`` (Pa): absolute stiffness
        is not identifiable from displacements without a force or pressure measurement, and
        this keeps the filter from drifting along that direction.
        """
        labels = np.asarray(labels)
        if labels.ndim != 1 or labels.size == 0:
            raise ValueError(f"labels: expected one label per element, got shape {labels.shape}")
        positive("E_reference", E_reference, "Pa")
        uniq, idx = np.unique(labels, return_inverse=True)
        R = len(uniq)
        if R < 2:
            raise ValueError(f"labels: expected at least two regions for relative stiffness, got {R}")
        ind = sp.csr_matrix((np.ones(len(labels)), (np.arange(len(labels)), idx)), shape=(len(labels), R))
        # orthonormal contrasts: columns of an orthonormal basis of the complement of ones
        q, _ = np.linalg.qr(np.column_stack([np.ones(R), np.eye(R)[:, : R - 1]]))
        contrasts = q[:, 1:]
        return cls(sp.csr_matrix(ind @ contrasts), ind, tuple(f"region {u}" for u in uniq),
                   offset_E=np.full(len(labels), np.log(float(E_reference))))

    @classmethod
    def from_basis(cls, basis_E, basis_nu=None) -> "Parameterisation":
        """Smooth or any other linear basis, (n_elements, k) arrays (same for nu if omitted)."""
        bE = sp.csr_matrix(as_float_array("basis_E", basis_E, shape=(None, None)))
        bnu = bE if basis_nu is None else sp.csr_matrix(
            as_float_array("basis_nu", basis_nu, shape=(bE.shape[0], None)))
        return cls(bE, bnu)

    @classmethod
    def smooth(cls, centroids, length: float, modes_E: int, modes_nu: int,
               E_reference: float | None = None) -> "Parameterisation":
        """Leading eigenvectors of a spatial correlation kernel over element centroids.

        The kernel is squared-exponential, ``exp(-d^2 / (2 length^2))``; its leading
        eigenvectors are the smoothest fields the mesh carries (a truncated Karhunen-Loeve
        expansion of a Gaussian field with that correlation). Each mode is scaled to unit RMS
        over the elements, so a parameter of 0.3 moves log E by 0.3 RMS, as a per-element
        prior of 0.3 would. With ``E_reference`` (Pa) the stiffness is relative, as in
        :meth:`relative_regions`: the E modes are those of the kernel centred to zero mean
        (orthogonal to a uniform change) and ``log E = log E_reference + basis_E theta_E``.

        Parameters
        ----------
        centroids : (n_elements, 2) array
            Element centroids in m.
        length : float
            Correlation length in m.
        modes_E, modes_nu : int
            Number of modes of log E and of logit(2 nu) (>= 1).
        E_reference : float, optional
            Reference Young's modulus in Pa: relative stiffness.
        """
        c = as_float_array("centroids", centroids, shape=(None, 2))
        n = len(c)
        positive("length", length, "m")
        modes_E = integer("modes_E", modes_E, 1)
        modes_nu = integer("modes_nu", modes_nu, 1)
        limit = n - 1 if E_reference is not None else n
        if modes_E > limit or modes_nu > n:
            raise ValueError(f"modes_E, modes_nu: expected at most {limit} and {n} modes for {n} elements, "
                             f"got {modes_E} and {modes_nu}")
        d2 = np.sum((c[:, None, :] - c[None, :, :]) ** 2, axis=2)
        kernel = np.exp(-d2 / (2.0 * float(length) ** 2))

        def leading(Kmat, k):
            lam, V = np.linalg.eigh(0.5 * (Kmat + Kmat.T))
            V = V[:, ::-1][:, :k]
            V = V * np.sign(V[np.argmax(np.abs(V), axis=0), np.arange(k)])   # deterministic sign
            return V * np.sqrt(n)

        offset = None
        if E_reference is not None:
            positive("E_reference", E_reference, "Pa")
            C = np.eye(n) - 1.0 / n
            bE = leading(C @ kernel @ C, modes_E)
            offset = np.full(n, np.log(float(E_reference)))
        else:
            bE = leading(kernel, modes_E)
        bnu = leading(kernel, modes_nu)
        names = tuple(f"E mode {i}" for i in range(modes_E)) + tuple(f"nu mode {i}" for i in range(modes_nu))
        return cls(sp.csr_matrix(bE), sp.csr_matrix(bnu), names, offset_E=offset)

    def with_level(self, E_reference: float | None = None) -> "Parameterisation":
        """This map plus one parameter for the global stiffness level (the last E parameter).

        ``log E_e = offset_e + b_e theta_E + level``: a relative map (regions, smooth basis) gets
        the absolute level it lacks, and an absolute one (per element) a level its parameters
        share, so that a prior can leave the level wide while keeping the contrasts tight. With
        ``E_reference`` (Pa) and no offset yet, the offset becomes ``log E_reference`` (the level
        and every parameter are then 0 at that uniform material). Identifiable only with a
        measured force scale (a cavity pressure): displacements alone do not fix it.
        """
        if self.level_index is not None:
            raise ValueError("with_level: this parameterisation already has a stiffness level")
        offset = self.offset_E
        if offset is None and E_reference is not None:
            offset = np.full(self.n_elements, np.log(positive("E_reference", E_reference, "Pa")))
        bE = sp.hstack([self.basis_E, sp.csr_matrix(np.ones((self.n_elements, 1)))], format="csr")
        names = (self.names[: self.n_E] + ("E level",) + self.names[self.n_E:]) if len(self.names) == self.n_params \
            else ()
        return Parameterisation(bE, self.basis_nu, names, offset_E=offset, level_index=self.n_E)

    def level_functional(self) -> tuple:
        """``(a, c)`` with the mean over elements of log E equal to ``a @ theta + c``."""
        a = np.zeros(self.n_params)
        a[: self.n_E] = np.asarray(self.basis_E.mean(axis=0)).ravel()
        c = 0.0 if self.offset_E is None else float(np.mean(self.offset_E))
        return a, c

    @property
    def n_elements(self) -> int:
        """Number of elements the map covers (rows of the bases)."""
        return self.basis_E.shape[0]

    @property
    def n_E(self) -> int:
        """Number of log E parameters (columns of ``basis_E``, a stiffness level included); they come first in theta."""
        return self.basis_E.shape[1]

    @property
    def n_params(self) -> int:
        """Number of parameters: the :attr:`n_E` log E ones followed by the logit(2 nu) ones."""
        return self.basis_E.shape[1] + self.basis_nu.shape[1]

    def material(self, theta) -> Material:
        """Per-element material of parameters ``theta`` (length :attr:`n_params`)."""
        theta = np.asarray(theta, float).ravel()
        if theta.shape != (self.n_params,):
            raise ValueError(f"theta: expected {self.n_params} parameters, got {theta.shape[0]}")
        sE = self.basis_E @ theta[: self.n_E] + (0.0 if self.offset_E is None else self.offset_E)
        snu = self.basis_nu @ theta[self.n_E:]
        if not np.all(np.isfinite(theta)):
            raise FloatingPointError("theta: expected finite material parameters, got NaN or inf")
        if np.any(np.abs(sE) > LOG_E_LIMIT) or np.any(snu > LOGIT_NU_LIMIT):
            raise FloatingPointError(
                f"theta: log E in [{sE.min():.3g}, {sE.max():.3g}] and logit(2 nu) up to {snu.max():.3g} "
                f"leave the range where E and nu < 0.5 are representable in floating point "
                f"(|log E| <= {LOG_E_LIMIT}, logit(2 nu) <= {LOGIT_NU_LIMIT}): the estimate diverged")
        return Material(np.exp(sE), inv_logit2(snu))

    def theta_of(self, material: Material) -> np.ndarray:
        """Parameters whose material best fits ``material`` (least squares in s_E, s_nu)."""
        if material.n_elements != self.n_elements:
            raise ValueError(f"material: expected {self.n_elements} elements, got {material.n_elements}")
        out = []
        sE = np.log(material.E) - (0.0 if self.offset_E is None else self.offset_E)
        for B, s in ((self.basis_E, sE), (self.basis_nu, logit2(material.nu))):
            out.append(np.linalg.lstsq(B.toarray(), s, rcond=None)[0])
        return np.concatenate(out)

    def element_jacobian(self, material: Material) -> sp.csr_matrix:
        """d(log E_e, nu_e)/d theta as a sparse (2 n_elements, n_params) matrix.

        Rows 0..n-1 are d log E_e / d theta, rows n..2n-1 are d nu_e / d theta; the
        element stiffness sensitivities ``E_e dK_e/dE_e`` and ``dK_e/dnu_e`` times this
        matrix give dK/dtheta (the chain rule of section 2.5 through the parameterisation).
        """
        return sp.block_diag([self.basis_E, sp.diags(dnu_ds(material.nu)) @ self.basis_nu],
                             format="csr")


def correlated_prior(param: Parameterisation, centroids, length: float, std_E: float = 0.3,
                     std_nu: float = 1.0) -> np.ndarray:
    """A spatially correlated prior covariance P3(0) of the parameters (alternative to diagonal).

    Per element, ``log E`` (and, independently, ``logit 2 nu``) is a Gaussian field with a
    squared-exponential correlation ``exp(-d^2 / (2 length^2))`` between element centroids
    (``d`` and ``length`` in metres) and standard deviation ``std_E`` (``std_nu``); mapped to
    the parameters through the pseudo-inverse of the parameterisation's bases.

    Returns
    -------
    (n_params, n_params) symmetric positive semi-definite array
    """
    c = as_float_array("centroids", centroids, shape=(param.n_elements, 2))
    positive("length", length, "m")
    positive("std_E", std_E)
    positive("std_nu", std_nu)
    d2 = np.sum((c[:, None, :] - c[None, :, :]) ** 2, axis=2)
    K = np.exp(-d2 / (2.0 * length ** 2))
    blocks = []
    for B, sd in ((param.basis_E, std_E), (param.basis_nu, std_nu)):
        Bp = np.linalg.pinv(B.toarray())
        C = sd ** 2 * Bp @ K @ Bp.T
        blocks.append(0.5 * (C + C.T))
    n_E = param.n_E
    out = np.zeros((param.n_params, param.n_params))
    out[:n_E, :n_E] = blocks[0]
    out[n_E:, n_E:] = blocks[1]
    return out
