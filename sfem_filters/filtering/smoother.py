"""The fixed-interval (Rauch-Tung-Striebel) smoother of a linearised model, one pass of the cycle.

:func:`smooth` runs the Kalman filter of a
:class:`~sfem_filters.filtering.linearised.LinearisedModel` forward over the frames (the
structured engine's algebra: F = [[A, M_t], [0, I]] block by block with a sparse A, Cholesky
factors of S, the Joseph update) and then the backward pass in Bierman's modified
Bryson-Frazier form (Bierman 1977, ch. X): with the filter's prior ``x_t-``, ``P_t-``, gain
``K_t``, innovation ``e_t`` and covariance ``S_t``, from ``lambda = 0``, ``Lambda = 0`` after
the last frame,

    lambda~_t = (I - K_t H)^T lambda_t - H^T S_t^-1 e_t
    Lambda~_t = (I - K_t H)^T Lambda_t (I - K_t H) + H^T S_t^-1 H
    x_t|T = x_t- - P_t- lambda~_t,          P_t|T = P_t- - P_t- Lambda~_t P_t-
    lambda_{t-1} = F_{t-1}^T lambda~_t,     Lambda_{t-1} = F_{t-1}^T Lambda~_t F_{t-1}.

These are the RTS smoother's estimates exactly (:func:`rts_reference` computes them with the
textbook gains ``G_t = P_t|t F_t^T P_t+1|t^-1`` by Cholesky solves; the tests compare the two)
without any solve with an n x n matrix: smoothed means cost O(n^2) a frame, and covariances are
formed only for the outputs asked for. ``Lambda~_t`` is a sum over the frames after t of
observed rows carried back, so its rank is at most the number of rows observed from t on: while
that is below n it is kept as a factor ``W W^T`` (n x r; the update appends ``H^T L_t^-T``,
``S_t = L_t L_t^T``, to ``(I - K_t H)^T W``), which makes the covariance of c output columns
O(c n r) instead of O(c n^2) (:data:`FACTOR_RANK`). Static parameters are part of the state, so
the smoothed ``theta`` and its covariance are those of the whole cycle.

Memory: smoothed means need only the gains and innovations (n m floats a frame,
``store="mean"``: the disturbance smoother, :func:`smooth_backward`), and that is what
:func:`smooth` keeps when no covariance is asked for, as in every pass of the iterated smoother
but its last. Smoothed covariances need the prior covariance of every frame (n^2 floats a
frame); where those do not fit the memory, only every k-th is kept and the backward pass
recomputes the frames between, a segment at a time (checkpointing, :func:`covariance_interval`),
with the same numbers.

The forward pass is :mod:`~sfem_filters.filtering.forward` (:func:`kalman_forward`), and what a
run keeps and whether it fits the memory is :mod:`~sfem_filters.filtering.memory`
(:func:`check_memory`, :func:`covariance_interval`); their names are importable from here too.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from .forward import STORE, ForwardPass, LinearisedEngine, kalman_forward
from .linearised import LinearisedModel
from .memory import (MEMORY_ADVICE, PEAK_FACTOR, WORKING, InsufficientMemory, available_memory, check_memory,
                     covariance_interval, stored_bytes)

__all__ = ["STORE", "LinearisedEngine", "ForwardPass", "SmoothedPass", "kalman_forward", "smooth_backward", "smooth",
           "rts_reference", "available_memory", "check_memory", "covariance_interval", "stored_bytes", "WORKING",
           "InsufficientMemory", "MEMORY_ADVICE", "PEAK_FACTOR"]

#: The covariance backward pass keeps ``Lambda`` as a factor ``W W^T`` (n x r) while its rank r,
#: the rows observed after the frame, stays below this share of n; then the dense n x n recursion.
#: With r < n the factor's products (O(c n r) per block of c output columns) are the cheaper.
FACTOR_RANK = 1.0


@dataclass(eq=False)
class SmoothedPass:
    """Outcome of :func:`smooth` (coordinates of the linearised model: ``[xi; theta]``)."""

    forward: ForwardPass
    smoothed: np.ndarray           # (n_frames, n) smoothed means
    theta: np.ndarray              # smoothed (whole-cycle) parameters
    P_theta: np.ndarray            # their covariance
    variances: dict = field(default_factory=dict)   # name -> (n_frames, k) smoothed output variances

    def __getattr__(self, name):   # innovation, S, nis, n_obs, log_likelihood, filtered, fit
        if name == "forward":
            raise AttributeError(name)
        return getattr(self.forward, name)



def _transpose_step(A, M, lt, nr):
    """``F^T lambda`` for F = [[A, M], [0, I]]."""
    out = np.empty_like(lt)
    out[:nr] = np.asarray(A.T @ lt[:nr]).ravel()
    out[nr:] = M.T @ lt[:nr] + lt[nr:]
    return out


def _transpose_columns(A, M, W, nr):
    """``F^T W`` for F = [[A, M], [0, I]] and an (n, r) W, column by column as :func:`_transpose_step`."""
    out = np.empty_like(W)
    out[:nr] = np.asarray(A.T @ W[:nr])
    out[nr:] = M.T @ W[:nr] + W[nr:]
    return out


def _dense(H):
    """H as a dense array (a sparse observation matrix densified)."""
    return H.toarray() if sp.issparse(H) else np.asarray(H)


def _congruence_step(A, M, Lam, nr):
    """``F^T Lambda F`` for F = [[A, M], [0, I]], exactly symmetric."""
    Lrr, Lrt, Ltt = Lam[:nr, :nr], Lam[:nr, nr:], Lam[nr:, nr:]
    At = A.T
    AtL = np.asarray(At @ Lrr)
    out = np.empty_like(Lam)
    rr = np.asarray(At @ AtL.T)
    out[:nr, :nr] = 0.5 * (rr + rr.T)
    if Lam.shape[0] > nr:
        LM = Lrr @ M + Lrt
        rt = np.asarray(At @ LM)
        out[:nr, nr:] = rt
        out[nr:, :nr] = rt.T
        tt = M.T @ LM + Lrt.T @ M + Ltt
        out[nr:, nr:] = 0.5 * (tt + tt.T)
    return out


def smooth(lin: LinearisedModel, observations, theta_mean=None, theta_cov=None, *, outputs=None,
           covariance: bool = False, safeguards=None, check_every_frame: bool = True, monitor_nis: bool = False,
           label: int = 0, every: int | None = None) -> SmoothedPass:
    """Kalman filter forward, modified Bryson-Frazier (RTS) smoother backward (module docstring).

    Parameters
    ----------
    lin : LinearisedModel
    observations : (n_frames, m) array
        NaN where a value is missing (those rows are left out of their frame's update).
    theta_mean, theta_cov : arrays, optional
        The prior of theta for this pass (default the model's, ``lin.theta0`` and
        ``lin.P_theta0``); a Levenberg-Marquardt step tightens it about the linearisation.
    outputs : dict, optional
        ``{name: (k, n_r) matrix}`` linear functions of ``xi`` whose smoothed variances are wanted
        (``covariance=True``), e.g. nodal displacements or strains via
        :meth:`LinearisedModel.output_in_xi`.
    covariance : bool
        Run the covariance recursion (O(n^2 (m + p)) a frame) and return the outputs' smoothed
        variances: the outputs' rows are split into blocks that read disjoint columns of xi
        (:func:`_output_blocks`), and a block of c columns and r distinct rows costs
        O(c n k + r c^2) a frame, k the rank of the information matrix (the rows observed from
        the frame on, at most n: module docstring); otherwise means only, from a pass that keeps
        no covariance. The covariance of theta is returned either way (for static parameters it
        is the forward pass's last).
    safeguards, check_every_frame, monitor_nis :
        See :func:`kalman_forward`.
    every : int, optional
        With ``covariance`` (ignored without): frames between the prior covariances kept
        (:func:`kalman_forward`); default :func:`covariance_interval`, 1 where every frame's fit
        the available memory.
        The same numbers whatever it is.
    """
    if covariance and every is None:
        every = covariance_interval(lin.dim_state, lin.n_frames,
                                    observed=int(np.sum(~np.isnan(np.asarray(observations, float)))))
    fwd = kalman_forward(lin, observations, theta_mean, theta_cov, safeguards=safeguards,
                         check_every_frame=check_every_frame, monitor_nis=monitor_nis, label=label,
                         store="covariance" if covariance else "mean", every=every if covariance else 1)
    return smooth_backward(lin, fwd, outputs=outputs, covariance=covariance)


def smooth_backward(lin: LinearisedModel, forward: ForwardPass, *, outputs=None,
                    covariance: bool = False) -> SmoothedPass:
    """The backward half of :func:`smooth`, on a :func:`kalman_forward` pass.

    On a pass run with ``store="mean"`` the smoothed means come from the adjoint ``lambda~_t``
    alone (no prior covariance of any frame): the smoothed initial state ``x_0- - P_0- lambda~_0``
    and the smoothed process noise ``w_t-1|T = -Q_t-1 lambda~_t`` (the disturbance smoother, de Jong
    1988; Durbin & Koopman 2012, sec. 4.5.3) give the trajectory forward,
    ``x_t|T = F_t-1 x_t-1|T + w_t-1|T`` (after a safeguard's repair D of a frame's covariance,
    from ``x_t-1|T - D lambda_t-1``), the same as ``x_t- - P_t- lambda~_t`` to round-off for
    transitions that do not expand (the models' damped ones: round-off grows with the powers of
    an expanding F). Covariances need ``store="covariance"``.
    """
    nr = lin.n_restart
    eng = forward.engine
    if eng.store == "none":
        raise ValueError("forward: expected a pass run with store='covariance' or 'mean' (it keeps what the "
                         "backward pass needs)")
    if eng.store == "mean":
        if covariance:
            raise ValueError("forward: covariance=True needs a pass run with store='covariance' (the prior "
                             "covariance of every frame); this one kept the means' part only")
        return _smooth_means(lin, forward)
    T, n = lin.n_frames, lin.dim_state
    lam = np.zeros(n)
    # Lambda as a factor W W^T while its rank (the observations after the frame) is below n, then dense
    W = np.zeros((n, 0)) if covariance else None
    Lam = None
    outputs = _checked_outputs(outputs, nr) if covariance else {}
    groups = _output_blocks(outputs)
    var = {name: np.zeros((T, L.shape[0])) for name, L in outputs.items()}
    smoothed = np.empty((T, n))
    segment: dict = {}
    for t in range(T - 1, -1, -1):
        if t in eng.priors:
            xb, Pb = eng.priors[t]
        else:
            if t not in segment:
                segment = _replay(lin, eng, t - t % eng.every, t)     # one segment's priors at a time
            xb, Pb = segment.pop(t)
        lt, LamT, WT = lam, Lam, W
        if t in eng.updates:
            mask, e, cho, K, _ = eng.updates[t]
            H = lin.H[mask]
            Sie = sla.cho_solve(cho, e)
            lt = lam.copy()
            lt[:nr] -= H.T @ (K.T @ lam + Sie)
            if covariance and W is not None and W.shape[1] + len(e) >= FACTOR_RANK * n:
                Lam, W, WT = W @ W.T, None, None                         # the factor is no longer the cheaper
            if covariance and W is not None:
                # (I - K H)^T W W^T (I - K H) + H^T S^-1 H = W~ W~^T, W~ = [(I - K H)^T W, H^T L^-T]
                WT = np.empty((n, W.shape[1] + len(e)))
                WT[:, :W.shape[1]] = W
                WT[:nr, :W.shape[1]] -= H.T @ (K.T @ W)
                WT[:, W.shape[1]:] = 0.0
                WT[:nr, W.shape[1]:] = sla.solve_triangular(cho[0], _dense(H), lower=True).T
            elif covariance:
                G = Lam @ K
                GH = G @ H
                LamT = Lam.copy()
                LamT[:, :nr] -= GH
                LamT[:nr, :] -= GH.T
                LamT[:nr, :nr] += H.T @ ((K.T @ G) @ H + sla.cho_solve(cho, H))
                LamT = 0.5 * (LamT + LamT.T)
        smoothed[t] = xb - Pb @ lt
        for cols, rows, members in groups:
            PC = Pb[cols, :]
            if WT is not None:
                PW = PC @ WT
                Ps = Pb[np.ix_(cols, cols)] - PW @ PW.T                 # smoothed covariance of the block's columns
            else:
                Ps = Pb[np.ix_(cols, cols)] - (PC @ LamT) @ PC.T
            v = np.einsum("ij,ij->i", rows @ Ps, rows)
            for name, where, which in members:
                var[name][t, where] = v[which]
        if t > 0:
            A, M = lin.A_at(t - 1), lin.M[t - 1]
            lam = _transpose_step(A, M, lt, nr)
            if covariance and WT is not None:
                W = _transpose_columns(A, M, WT, nr)
            elif covariance:
                Lam = _congruence_step(A, M, LamT, nr)
    # theta is static: its smoothed covariance is that of the last frame's filter (the whole cycle)
    return SmoothedPass(forward=forward, smoothed=smoothed, theta=smoothed[0, nr:].copy(),
                        P_theta=eng.P[nr:, nr:].copy(), variances=var)


def _replay(lin: LinearisedModel, eng: LinearisedEngine, start: int, stop: int) -> dict:
    """The prior means and covariances of frames ``start + 1 .. stop``, recomputed from the
    checkpoint at ``start`` by the forward pass's own steps (and its repairs, where a safeguard
    made one): ``{frame: (x, P)}``."""
    again = LinearisedEngine(lin, lin.theta0, lin.P_theta0, store="none")
    again.reset(*eng.priors[start])
    y, out = eng.observations, {}
    for t in range(start, stop):
        if t in eng.updates:
            again.update(y[t], t, eng.updates[t][0])
        if t in eng.repaired:
            again.reset(*eng.repaired[t])
        again.predict(t)
        out[t + 1] = (again.x.copy(), again.P.copy())
    return out


def _smooth_means(lin: LinearisedModel, forward: ForwardPass) -> SmoothedPass:
    """Smoothed means of a ``store="mean"`` pass: the adjoint backward, then the trajectory
    forward from the smoothed initial state under the smoothed process noise
    (:func:`smooth_backward`)."""
    nr, eng = lin.n_restart, forward.engine
    T, n = lin.n_frames, lin.dim_state
    adjoint = np.empty((T, n))
    carried = {}                                   # lambda_t = F^T lambda~_t+1 at repaired frames
    lam = np.zeros(n)
    for t in range(T - 1, -1, -1):
        if t in eng.repaired:
            carried[t] = lam.copy()
        lt = lam
        if t in eng.updates:
            mask, e, cho, K, _ = eng.updates[t]
            H = lin.H[mask]
            lt = lam.copy()
            lt[:nr] -= H.T @ (K.T @ lam + sla.cho_solve(cho, e))
        adjoint[t] = lt
        if t > 0:
            lam = _transpose_step(lin.A_at(t - 1), lin.M[t - 1], lt, nr)
    x0, P0 = eng.initial
    smoothed = np.empty((T, n))
    smoothed[0] = x0 - P0 @ adjoint[0]
    for t in range(1, T):
        prev = smoothed[t - 1]
        if t - 1 in eng.repaired:
            # a repair D of the filtered covariance at t-1 moves the next prior by F D F^T, and so
            # the step: x_t|T = F (x_t-1|T - D lambda_t-1) + w_t-1|T (the covariance pass's numbers)
            prev = prev - eng.repaired[t - 1] @ carried[t - 1]
        xr = np.asarray(lin.A_at(t - 1) @ prev[:nr]).ravel() + lin.c[t - 1] - lin.Q_at(t - 1) @ adjoint[t, :nr]
        if lin.n_params:
            xr += lin.M[t - 1] @ (prev[nr:] - lin.theta_bar)
        smoothed[t, :nr], smoothed[t, nr:] = xr, prev[nr:]
    return SmoothedPass(forward=forward, smoothed=smoothed, theta=smoothed[0, nr:].copy(),
                        P_theta=eng.P[nr:, nr:].copy())


def _checked_outputs(outputs, nr: int) -> dict:
    """The output operators as dense (k, nr) float arrays (sparse ones densified); a ValueError
    names an output of another shape."""
    out = {}
    for name, L in (outputs or {}).items():
        L = L.toarray() if sp.issparse(L) else np.asarray(L, float)
        if L.ndim != 2 or L.shape[1] != nr:
            raise ValueError(f"outputs: expected (k, {nr}) matrices on xi, got {name!r} with shape {L.shape}")
        out[name] = L
    return out


def _output_blocks(outputs) -> list:
    """The outputs' rows in blocks that read disjoint columns of xi, each block's distinct rows once.

    Two rows are in one block when their supports (non-zero columns) are joined by a chain of
    rows sharing a column (the connected components of the bipartite row-column graph), so the
    blocks' column sets are disjoint and forming the smoothed covariance of each block's
    columns costs at most what one covariance of their union would. In vibration modes, for
    example, displacements read the modal displacements and velocities the modal velocities:
    two blocks of half the columns each, instead of every output reading all of them. Rows
    repeated within a block (an output that is a selection of another's rows) are computed
    once; rows of zeros read nothing and have variance 0.

    ``outputs``: ``{name: (k, n) array}`` (:func:`_checked_outputs`). Returns ``[(cols, rows, [(name,
    where, which), ...]), ...]``: the block's columns, its distinct rows restricted to them, and for
    each output the positions ``where`` of its rows in the block and ``which`` distinct row each one is.
    """
    names, mats = list((outputs or {}).keys()), list((outputs or {}).values())
    if not mats or not sum(m.shape[0] for m in mats):
        return []
    L = np.vstack(mats)
    owner = np.repeat(np.arange(len(mats)), [m.shape[0] for m in mats])
    position = np.concatenate([np.arange(m.shape[0]) for m in mats])
    R, C = L.shape
    B = sp.csr_matrix(L != 0, dtype=np.int8)
    graph = sp.bmat([[sp.csr_matrix((R, R), dtype=np.int8), B], [B.T, sp.csr_matrix((C, C), dtype=np.int8)]],
                    format="csr")
    _, label = connected_components(graph, directed=False)
    blocks = []
    for comp in np.unique(label[:R]):
        cols = np.flatnonzero(label[R:] == comp)
        if cols.size == 0:
            continue                                            # rows of zeros: variance 0
        in_block = np.flatnonzero(label[:R] == comp)
        rows, which = np.unique(L[np.ix_(in_block, cols)], axis=0, return_inverse=True)
        which = np.asarray(which).ravel()
        members = [(names[k], position[in_block[owner[in_block] == k]], which[owner[in_block] == k])
                   for k in np.unique(owner[in_block])]
        blocks.append((cols, rows, members))
    return blocks


def rts_reference(lin: LinearisedModel, observations, theta_mean=None, theta_cov=None):
    """The textbook RTS smoother, dense, for tests: returns smoothed means (n_frames, n) and
    covariances (n_frames, n, n).

    Forward Kalman filter with F = [[A, M], [0, I]] formed densely; backward
    ``G_t = P_t|t F_t^T P_t+1|t^-1`` (a Cholesky solve), ``x_t|T = x_t|t + G_t (x_t+1|T - x_t+1|t)``,
    ``P_t|T = P_t|t + G_t (P_t+1|T - P_t+1|t) G_t^T``.
    """
    nr, p, T = lin.n_restart, lin.n_params, lin.n_frames
    y = np.asarray(observations, float)
    n = nr + p
    x = np.concatenate([lin.xi0, lin.theta0 if theta_mean is None else theta_mean])
    P = sla.block_diag(lin.P0, lin.P_theta0 if theta_cov is None else theta_cov)
    Hf = np.hstack([lin.H, np.zeros((lin.dim_obs, p))])
    xf, Pf, xp, Pp, Fs = [], [], [None], [None], []
    for t in range(T):
        if t > 0:
            A = lin.A_at(t - 1)
            F = np.eye(n)
            F[:nr, :nr] = A.toarray() if sp.issparse(A) else A
            F[:nr, nr:] = lin.M[t - 1]
            off = np.concatenate([lin.c[t - 1] - lin.M[t - 1] @ lin.theta_bar, np.zeros(p)])
            x = F @ x + off
            P = F @ P @ F.T + sla.block_diag(lin.Q_at(t - 1), np.zeros((p, p)))
            Fs.append(F)
            xp.append(x.copy())
            Pp.append(P.copy())
        mask = ~np.isnan(y[t])
        if mask.any():
            H = Hf[mask]
            S = H @ P @ H.T + lin.R[t][np.ix_(mask, mask)]
            K = sla.cho_solve(sla.cho_factor(S), H @ P).T
            x = x + K @ (y[t, mask] - H @ x)
            IKH = np.eye(n) - K @ H
            P = IKH @ P @ IKH.T + K @ lin.R[t][np.ix_(mask, mask)] @ K.T
        xf.append(x.copy())
        Pf.append(P.copy())
    xs, Ps = [None] * T, [None] * T
    xs[-1], Ps[-1] = xf[-1], Pf[-1]
    for t in range(T - 2, -1, -1):
        G = sla.cho_solve(sla.cho_factor(Pp[t + 1]), Fs[t] @ Pf[t]).T
        xs[t] = xf[t] + G @ (xs[t + 1] - xp[t + 1])
        Ps[t] = Pf[t] + G @ (Ps[t + 1] - Pp[t + 1]) @ G.T
    return np.array(xs), np.array(Ps)
