"""State-space form of M U'' + C U' + K U = R and its exact discretisation.

The state is ``x = [U; U']`` over the free dofs (m and m/s) and the input is the load R (N).
Two routes give the same numbers:

* :func:`continuous_matrices`, :func:`discretize_zoh` and :func:`reference_sensitivity`
  follow the paper literally (Eqs. (9)-(11), (14)-(16), (33)) with dense matrix exponentials
  and scipy's ``expm_frechet``; they are the reference for tests and benchmarks.
* :class:`ModalSystem` uses the symmetric generalised eigenproblem ``K phi = w^2 M phi``.
  Rayleigh damping ``C = alpha M + beta K`` is diagonal in that basis, so the system splits
  into independent 2 x 2 oscillators whose zero-order-hold exponentials are exact, and the
  derivative of the transition with respect to any stiffness perturbation is the
  Daleckii-Krein form of the exponential's Frechet derivative, evaluated with stable divided
  differences. Nothing here knows about filters or materials: sensitivities are taken with
  respect to element-level stiffness directions.

The dense route is :mod:`~sfem_filters.fem.reference_zoh`, the modal oscillators' closed forms
and the divided differences of exp are :mod:`~sfem_filters.fem.modal_exp`, and the planning of
modal stiffness derivatives is :mod:`~sfem_filters.fem.modal_stiffness`; their public names are
importable from here too.
"""
from __future__ import annotations

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from scipy.linalg import expm

from .._validate import non_negative, positive
from .modal_exp import divided_difference_exp, divided_difference_exp_real, modal_exponentials
from .modal_stiffness import StiffnessPlan, stiffness_plan
from .reference_zoh import continuous_matrices, discretize_zoh, reference_sensitivity

__all__ = ["ModalSystem", "StiffnessPlan", "stiffness_plan", "continuous_matrices", "discretize_zoh",
           "reference_sensitivity", "modal_exponentials", "divided_difference_exp"]


class ModalSystem:
    """Exact zero-order-hold dynamics of ``M U'' + (alpha M + beta K) U' + K U = R`` in modes.

    Parameters
    ----------
    M, K : (n, n) arrays (dense or sparse)
        Mass (kg) and stiffness (N/m) over the free dofs; K must be positive definite
        (fix dofs or add penalty springs).
    alpha : float
        Mass-proportional Rayleigh coefficient in 1/s.
    beta : float
        Stiffness-proportional Rayleigh coefficient in s.
    T : float
        Frame interval in s.

    Notes
    -----
    With ``K Phi = M Phi diag(w^2)``, ``Phi^T M Phi = I``, the modal coordinates
    ``q = Phi^T M U`` obey ``q_i'' + c_i q_i' + w_i^2 q_i = phi_i^T R`` with
    ``c_i = alpha + beta w_i^2``. Each mode's exact transition ``E_i = e^{S_i T}`` and
    held-input response ``g_i = int_0^T e^{S_i s} ds e_2``, ``S_i = [[0, 1], [-w_i^2, -c_i]]``,
    are closed forms (:func:`modal_exponentials`).
    """

    #: modes whose two eigenvalues are closer than this (relative) are near critical damping;
    #: their 2 x 2 eigenvectors are ill-conditioned, so they take the block-exponential route.
    critical_tol = 1e-3

    def __init__(self, M, K, alpha: float, beta: float, T: float):
        self.T = positive("T", T, "s")
        self.alpha = non_negative("alpha", alpha, "1/s")
        self.beta = non_negative("beta", beta, "s")
        M = np.asarray(M.toarray() if hasattr(M, "toarray") else M, float)
        K = np.asarray(K.toarray() if hasattr(K, "toarray") else K, float)
        self.M = M
        w2, Phi = sla.eigh(K, M)
        scale = max(abs(w2).max(), 1e-300)
        if w2.min() <= 1e-14 * scale:
            raise ValueError(
                "K: expected a positive definite stiffness over the free dofs, got a singular or "
                f"indefinite one (smallest / largest eigenvalue {w2.min() / scale:.1e}): rigid-body motion "
                "is free (fix dofs or add penalty springs), or a material estimate has diverged")
        self.w2 = w2
        self.Phi = Phi
        # Phi^T M with a sparse M (a FEM mass matrix has ~20 entries per row): ~10x cheaper
        self.PhiTM = (sp.csr_matrix(M).T @ Phi).T if np.count_nonzero(M) < 0.1 * M.size else Phi.T @ M
        self.c = self.alpha + self.beta * w2
        self.E, self.g = modal_exponentials(w2, self.c, self.T)
        # Eigenvalues of each S_i: lam1 = -c/2 - sqrt(c^2/4 - w^2) (the larger in modulus),
        # lam2 = w^2 / lam1 (their product is w^2): no cancellation when overdamped.
        sig = self.c / 2.0
        root = np.sqrt((sig ** 2 - w2).astype(complex))
        lam1 = -sig - root
        lam2 = w2 / lam1
        self.lam = np.stack([lam1, lam2], axis=1)
        self.critical = np.abs(lam1 - lam2) < self.critical_tol * np.abs(lam1)
        self._dd = None                 # divided differences of exp over the eigenvalues (lazy)

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_dd"] = None             # a cache, made again where needed: pickles stay small
        return state

    @property
    def n(self) -> int:
        """Number of free dofs (the size of M and K); the state ``[U; U']`` has 2 n entries."""
        return self.M.shape[0]

    def step(self, x, w):
        """State one frame later, ``A x + B w`` (Eq. 14), x = [U; U'] in m, m/s, w in N."""
        n = self.n
        x = np.asarray(x, float)
        q = self.PhiTM @ x[:n]
        p = self.PhiTM @ x[n:]
        f = self.Phi.T @ np.asarray(w, float)
        qn = self.E[:, 0, 0] * q + self.E[:, 0, 1] * p + self.g[:, 0] * f
        pn = self.E[:, 1, 0] * q + self.E[:, 1, 1] * p + self.g[:, 1] * f
        return np.concatenate([self.Phi @ qn, self.Phi @ pn])

    def transition_matrix(self, out=None) -> np.ndarray:
        """A = e^{A_c T} (Eq. 15), dense (2n, 2n).

        ``out``: a (2n, 2n) float array (or a view with unit column stride, e.g. the top-left
        block of F) to write A into, without a temporary copy.
        """
        n, Phi, PTM = self.n, self.Phi, self.PhiTM
        A = np.empty((2 * n, 2 * n)) if out is None else out
        if A.shape != (2 * n, 2 * n):
            raise ValueError(f"out: expected shape {(2 * n, 2 * n)}, got {A.shape}")
        scaled = np.empty_like(Phi)
        for r in range(2):
            for s in range(2):
                np.multiply(Phi, self.E[:, r, s], out=scaled)
                np.matmul(scaled, PTM, out=A[r * n:(r + 1) * n, s * n:(s + 1) * n])
        return A

    def input_response(self, G) -> np.ndarray:
        """``B @ G`` for a (n, k) load matrix G, without forming B."""
        f = self.Phi.T @ np.asarray(G, float)
        return np.vstack([self.Phi @ (self.g[:, r, None] * f) for r in range(2)])

    def input_matrix(self) -> np.ndarray:
        """B = int_0^T e^{A_c s} ds B_c (Eq. 16), dense (2n, n)."""
        return np.vstack([(self.Phi * self.g[:, r]) @ self.Phi.T for r in range(2)])

    def modal_stiffness_derivatives(self, dK_elements, dofs, combine, plan: "StiffnessPlan | None" = None
                                    ) -> np.ndarray:
        """``G_k = Phi^T dK^(k) Phi`` for the combined parameters, stored as (N, k, N): ``[i, k, j]``.

        ``dK^(k) = sum_p combine[p, k] dK_p`` with ``dK_p`` the element matrix ``dK_elements[p]``
        scattered to its free dofs (as in :meth:`sensitivity`). With it, :meth:`sensitivity`
        (``modal_stiffness=``) contracts the Frechet pairs with ``G`` directly and skips its
        O(n^3) product per call: worth it when the same material serves many states (a
        smoother's linearisation, one per frame) and k is small. Made as :func:`stiffness_plan`
        says: one product per parameter over the dofs ``dK^(k)`` touches, or one per group of
        directions with the same row of ``combine`` (a region's elements), combined row block by
        row block (peak memory about ``(k + groups) N^2`` floats).

        Parameters
        ----------
        dK_elements : (P, 6, 6) array
            ``dK/dp_j`` on the 6 dofs of one element (N/m per unit p_j).
        dofs : (P, 6) int array
            Free-dof index of each of those 6 dofs, -1 where the dof is fixed.
        combine : (P, k) array or sparse matrix
            The chain rule to the k parameters (as in :meth:`sensitivity`).
        plan : StiffnessPlan, optional
            :func:`stiffness_plan` of ``combine`` and ``dofs``, if already made.

        Returns
        -------
        (N, k, N) array (N/m per unit parameter, in mass-normalised modal coordinates)
        """
        n, Phi = self.n, self.Phi
        dK = np.asarray(dK_elements, float)
        if dK.ndim != 3 or dK.shape[1:] != (6, 6):
            raise ValueError(f"dK_elements: expected shape (P, 6, 6), got {dK.shape}")
        plan = stiffness_plan(combine, dofs) if plan is None else plan
        dofs = np.asarray(dofs)
        if dofs.shape != (len(dK), 6):
            raise ValueError(f"dofs: expected shape ({len(dK)}, 6) like dK_elements, got {dofs.shape}")
        if plan.n_directions != len(dK):
            raise ValueError(f"combine: expected {len(dK)} rows (one per direction of dK_elements), got "
                             f"{plan.n_directions}")
        if dofs.max(initial=-1) >= n:
            raise ValueError(f"dofs: expected free-dof indices below {n} (or -1), got {dofs.max()}")
        k = plan.n_params

        def projected(p, weights):
            """Phi^T (sum_p weights_p dK_p) Phi over the dofs the directions p touch."""
            rr = np.broadcast_to(dofs[p][:, :, None], (len(p), 6, 6))
            cc = np.broadcast_to(dofs[p][:, None, :], (len(p), 6, 6))
            ok = (rr >= 0) & (cc >= 0)
            vals = (weights[:, None, None] * dK[p])[ok]
            touched, inv = np.unique(np.concatenate([rr[ok], cc[ok]]), return_inverse=True)
            m = len(touched)
            dKm = sp.csr_matrix((vals, (inv[:len(vals)], inv[len(vals):])), shape=(m, m))
            Pt = Phi[touched]
            return Pt.T @ np.asarray(dKm @ Pt)

        G = np.empty((n, k, n))
        if plan.by_group:
            rows = plan.rows
            Gg = np.empty((len(rows), n, n))
            for g in range(len(rows)):
                p = np.flatnonzero(plan.group == g)
                Gg[g] = projected(p, np.ones(len(p)))
            # G[i, k, j] = sum_g rows[g, k] Gg[g, i, j], a product per block of rows i
            step = max(1, 2 ** 22 // max(k * n, 1))
            for lo in range(0, n, step):
                blk = Gg[:, lo:lo + step, :]
                G[lo:lo + step] = (rows.T @ blk.reshape(len(rows), -1)).reshape(k, -1, n).transpose(1, 0, 2)
            return G
        Cc = plan.by_param
        for j in range(k):
            lo, hi = Cc.indptr[j], Cc.indptr[j + 1]
            G[:, j, :] = projected(Cc.indices[lo:hi], Cc.data[lo:hi])
        return G

    def sensitivity(self, x, w, dK_elements, dofs, chunk: int = 256, combine=None, modal: bool = False,
                    modal_stiffness=None) -> np.ndarray:
        """Exact d(A x + B w)/d p for element-level stiffness perturbations (Eq. 33).

        Parameters
        ----------
        x : (2n,) array
            State at the start of the interval (m, m/s).
        w : (n,) array
            Load held over the interval (N).
        dK_elements : (P, 6, 6) array
            ``dK/dp_j`` restricted to the 6 dofs of one element (N/m per unit p_j).
        dofs : (P, 6) int array
            Free-dof index of each of those 6 dofs, -1 where the dof is fixed.
        chunk : int
            Parameters processed at once (bounds memory at ``chunk * 12 * n`` floats).
        combine : (P, k) array or sparse matrix, optional
            Return ``result @ combine`` (e.g. the chain rule to k material parameters),
            contracted before the final modal-to-nodal product: cheaper when k << P.
        modal : bool
            Return the derivative in the modal coordinates ``[q; p] = [Phi^T M U; Phi^T M U']``
            (the rows are ``W d(A x + B w)`` with ``W = diag(Phi^T M, Phi^T M)``), skipping the final
            modal-to-nodal products.
        modal_stiffness : (N, k, N) array, optional
            :meth:`modal_stiffness_derivatives` of the same ``dK_elements``, ``dofs`` and
            ``combine`` (which must be given): the result is then ``-T sum_j G[i, k, j] h[i, j]``
            plus the static part, O(k N^2) instead of the O(n^3) product, the same numbers to
            round-off.

        Returns
        -------
        (2n, P) array, or (2n, k) with ``combine``

        Notes
        -----
        Write the held-input motion about the static solution ``x_s = [K^-1 w; 0]``:
        ``A x + B w = x_s + e^{A_c T}(x - x_s)``. Its derivative is
        ``(I - A) dx_s + L(A_c T, dA_c T)(x - x_s)`` with ``dx_s = [-K^-1 dK U_s; 0]``.
        In modes, ``dA_c`` has 2 x 2 blocks ``-k_ij e_2 [1, beta]`` with
        ``k = Phi^T dK Phi``, and the Daleckii-Krein formula gives the Frechet derivative
        from divided differences of exp over the eigenvalues of the 2 x 2 blocks. Because
        ``k`` of an element has rank <= 3 through 6 rows of Phi, all parameters cost
        O(n^3) once per step plus O(n) each.
        """
        n, N, T = self.n, self.n, self.T
        Phi = self.Phi
        x = np.asarray(x, float)
        f = Phi.T @ np.asarray(w, float)
        q_s = f / self.w2
        y = np.stack([self.PhiTM @ x[:n] - q_s, self.PhiTM @ x[n:]], axis=1)      # (N, 2)
        h = self._frechet_pairs(y)                                                 # (N, N, 2)
        static = np.stack([1.0 - self.E[:, 0, 0], -self.E[:, 1, 0]]) / self.w2      # (2, N)
        if modal_stiffness is not None:
            if combine is None:
                raise ValueError("modal_stiffness: given without combine, which it was made with")
            G = modal_stiffness
            if G.shape != (N, combine.shape[1], N):
                raise ValueError(f"modal_stiffness: expected shape {(N, combine.shape[1], N)}, got {G.shape}")
            # sum_p combine[p, k] W_p^T Y_p = G_k o h, and W_p^T U_s = G_p q_s (U_s = Phi q_s):
            # both in one pass over G, with q_s as a third column beside the pairs
            hq = np.empty((N, N, 3))
            hq[:, :, :2] = h
            hq[:, :, 2] = q_s
            zq = np.matmul(G, hq)                                                  # (N, k, 3)
            z = zq[:, :, :2] * -T
            z -= zq[:, :, 2:] * static.T[:, None, :]
            return np.vstack([z[:, :, 0], z[:, :, 1]]) if modal else np.vstack([Phi @ z[:, :, 0], Phi @ z[:, :, 1]])
        # Y[d, k, i] = sum_j Phi[d, j] h[i, j, k] in one product; a zero row stands for fixed
        # dofs (index -1). Dof-major, so that gathering an element's 6 rows copies whole rows.
        Y = np.empty((n + 1, 2, N))
        np.matmul(Phi, h.transpose(1, 2, 0).reshape(N, 2 * N), out=Y[:n].reshape(n, 2 * N))
        Y[n] = 0.0
        Phi_pad = np.vstack([Phi, np.zeros((1, N))])
        U_s = np.append(Phi @ q_s, 0.0)
        dK_elements = np.asarray(dK_elements, float)
        dofs = np.where(np.asarray(dofs) < 0, n, dofs)
        P = len(dK_elements)
        k = P if combine is None else combine.shape[1]
        acc = np.zeros((k, 2, N)) if combine is not None else None
        out = np.empty((2 * n, k))
        for start in range(0, P, chunk):
            sl = slice(start, min(start + chunk, P))
            Kd, dd = dK_elements[sl], dofs[sl]
            # W_p = dK_p^T Phi_e (6 x N): the element's stiffness direction applied once to the
            # mode shapes (N columns), not to Y (2N columns).
            W = np.matmul(Kd.transpose(0, 2, 1), Phi_pad[dd])                     # (p, 6, N)
            z = np.einsum("pdi,pdki->pki", W, Y[dd])                               # (p, 2, N)
            z *= -T
            # static part (I - A) dx_s, dx_s = [-K^-1 dK U_s; 0]: dq_s = -(W^T U_s) / w^2
            WU = np.einsum("pdi,pd->pi", W, U_s[dd])                               # (p, N)
            z -= WU[:, None, :] * static
            if combine is not None:
                # (k x p) @ (p x 2N): a sparse-dense or BLAS product, never a dense einsum
                acc += np.asarray(combine[sl].T @ z.reshape(len(z), -1)).reshape(k, 2, N)
                continue
            out[:n, sl] = z[:, 0, :].T if modal else Phi @ z[:, 0, :].T
            out[n:, sl] = z[:, 1, :].T if modal else Phi @ z[:, 1, :].T
        if combine is not None:
            out[:n] = acc[:, 0, :].T if modal else Phi @ acc[:, 0, :].T
            out[n:] = acc[:, 1, :].T if modal else Phi @ acc[:, 1, :].T
        return out

    def modal_transition(self) -> "sp.csr_matrix":
        """The transition in modal coordinates ``[q; p]``: four diagonals of the 2 x 2 blocks ``E_i``.

        ``W A = A_modal W`` with ``W = diag(Phi^T M, Phi^T M)``: sparse (2n, 2n), 4n entries.
        """
        E = self.E
        return sp.bmat([[sp.diags(E[:, 0, 0]), sp.diags(E[:, 0, 1])],
                        [sp.diags(E[:, 1, 0]), sp.diags(E[:, 1, 1])]], format="csr")

    def modal_input(self, G) -> np.ndarray:
        """``W B G`` for a (n, k) load matrix G: the held-load response in modal coordinates."""
        f = self.Phi.T @ np.asarray(G, float)
        if f.ndim == 1:
            return np.concatenate([self.g[:, 0] * f, self.g[:, 1] * f])
        return np.vstack([self.g[:, 0, None] * f, self.g[:, 1, None] * f])

    def _frechet_pairs(self, y) -> np.ndarray:
        """h[i, j] = int_0^1 e^{S_i T (1-s)} e_2 [1, beta] e^{S_j T s} ds y_j, shape (N, N, 2).

        Daleckii-Krein in the eigenbases of the 2 x 2 blocks: with ``S_i = V_i diag(lam_i) V_i^-1``,
        ``h[i, j] = sum_ab (V_i)_{:a} (V_i^-1 e_2)_a D(lam_ia T, lam_jb T) ([1, beta] V_j)_b (V_j^-1 y_j)_b``,
        D the divided difference of exp. Two structures make it cheap:

        * overdamped modes have real eigenvalues, so between two of them everything is real
          (:func:`~sfem_filters.fem.modal_exp.divided_difference_exp_real`, no complex arithmetic);
        * the eigenvalues, eigenvectors and coefficients of an underdamped mode come in
          conjugate pairs, so its second row term is the conjugate of the first and
          ``h[i, j] = 2 Re(first term)``: half the divided differences.
        """
        T, beta = self.T, self.beta
        lam = self.lam                                                             # (N, 2)
        N = len(lam)
        lam1, lam2 = lam[:, 0], lam[:, 1]
        gap = np.where(self.critical, 1.0, lam2 - lam1)
        # S = V diag(lam) V^-1 with V = [[1, 1], [lam1, lam2]].
        a = np.stack([-1.0 / gap, 1.0 / gap], axis=1)                             # V^-1 e_2
        eta = np.stack([(lam2 * y[:, 0] - y[:, 1]) / gap,
                        (-lam1 * y[:, 0] + y[:, 1]) / gap], axis=1)               # V^-1 y
        u = (1.0 + beta * lam) * eta                                               # ([1, beta] V) * V^-1 y
        la = lam * a                                                               # row weights of h[..., 1]
        real = (lam1.imag == 0) & (lam2.imag == 0)
        dd = self._divided_differences()
        h = np.empty((2, N, N))                                                    # [h0, h1], contiguous
        if real.all():
            self._pairs_real(dd["RR"], a.real, la.real, u.real, h)
        else:
            R, C = np.flatnonzero(real), np.flatnonzero(~real)
            if R.size:
                if R[-1] - R[0] + 1 == R.size:          # one run of modes (the usual case): in place
                    rs = slice(R[0], R[-1] + 1)
                    self._pairs_real(dd["RR"], a[R].real, la[R].real, u[R].real, h[:, rs, rs])
                else:
                    hr = np.empty((2, R.size, R.size))
                    self._pairs_real(dd["RR"], a[R].real, la[R].real, u[R].real, hr)
                    h[np.ix_([0, 1], R, R)] = hr
                # rows R, columns C: real rows (both eigenvalues), complex columns
                D0 = dd["RC"]
                s0 = D0[0] * u[C, 0] + D0[1] * u[C, 1]
                s1 = D0[2] * u[C, 0] + D0[3] * u[C, 1]
                hc = np.stack([(a[R, 0, None] * s0 + a[R, 1, None] * s1).real,
                               (la[R, 0, None] * s0 + la[R, 1, None] * s1).real])
                h[np.ix_([0, 1], R, C)] = hc
            # rows C (underdamped): the first eigenvalue only, twice the real part
            s = dd["C"][0] * u[:, 0] + dd["C"][1] * u[:, 1]
            h[0, C] = 2.0 * (a[C, 0, None] * s).real
            h[1, C] = 2.0 * (la[C, 0, None] * s).real
        h = np.moveaxis(h, 0, 2)
        crit = np.flatnonzero(self.critical)
        if crit.size:
            h[crit, :, :] = self._pairs_by_expm(crit, np.arange(N), y)
            h[:, crit, :] = self._pairs_by_expm(np.arange(N), crit, y)
        return h

    def _divided_differences(self) -> dict:
        """The divided differences of exp over the blocks' eigenvalues times T that
        :meth:`_frechet_pairs` needs, made once per system (they do not depend on the state):
        ``"RR"``, the four real ``D(lam_a T, lam_b T)`` between overdamped modes; ``"RC"``, the four
        complex ones from overdamped rows to underdamped columns; ``"C"``, the two from the first
        eigenvalue of each underdamped mode to every mode's first and second."""
        if self._dd is None:
            T, lam = self.T, self.lam
            real = (lam[:, 0].imag == 0) & (lam[:, 1].imag == 0)
            R, C = np.flatnonzero(real), np.flatnonzero(~real)
            lamT = lam[R].real * T
            dd = {"RR": [divided_difference_exp_real(lamT[:, ra], lamT[:, b]) for ra in range(2) for b in range(2)]}
            if C.size:
                dd["RC"] = [divided_difference_exp(lam[R, ra, None] * T, lam[None, C, b] * T) for ra in range(2)
                            for b in range(2)]
                dd["C"] = [divided_difference_exp(lam[C, 0, None] * T, lam[None, :, b] * T) for b in range(2)]
            self._dd = dd
        return self._dd

    @staticmethod
    def _pairs_real(D, a, la, u, out):
        """out[0] = sum_ab a_ia D_ab u_jb, out[1] = the same with lam_ia a_ia, all real
        (``D = [D_00, D_01, D_10, D_11]``)."""
        s0 = D[0] * u[:, 0]
        t = D[1] * u[:, 1]
        s0 += t
        s1 = D[2] * u[:, 0]
        np.multiply(D[3], u[:, 1], out=t)
        s1 += t
        np.multiply(a[:, 0, None], s0, out=out[0])
        out[0] += np.multiply(a[:, 1, None], s1, out=t)
        np.multiply(la[:, 0, None], s0, out=out[1])
        out[1] += np.multiply(la[:, 1, None], s1, out=t)

    def _pairs_by_expm(self, rows, cols, y) -> np.ndarray:
        """The same h for the given rows x cols through 4 x 4 block exponentials (Van Loan)."""
        T, beta = self.T, self.beta
        S = np.zeros((len(self.w2), 2, 2))
        S[:, 0, 1] = 1.0
        S[:, 1, 0] = -self.w2
        S[:, 1, 1] = -self.c
        I, J = np.meshgrid(rows, cols, indexing="ij")
        X = np.zeros(I.shape + (4, 4))
        X[..., :2, :2] = S[I] * T
        X[..., 2:, 2:] = S[J] * T
        X[..., 1, 2] = 1.0
        X[..., 1, 3] = beta
        G = expm(X.reshape(-1, 4, 4)).reshape(I.shape + (4, 4))[..., :2, 2:]
        return np.einsum("ijab,ijb->ija", G, y[J])
