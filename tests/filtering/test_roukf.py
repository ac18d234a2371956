"""The reduced-order UKF where its reduced covariance does not hold: a model whose misfit is process
noise (what the filter leaves out) drags its parameters out of range, and the error says so."""
from __future__ import annotations

import numpy as np
import pytest

from sfem_filters.filtering import CyclicEKF
from sfem_filters.filtering.linear import LinearObservation

LIMIT = 3.0      # the synthetic model's admissible parameter range, |theta| <= LIMIT


class DriftModel(LinearObservation):
    """x_{t+1} = x_t + theta (+ process noise q), y = x: a drift parameter beside a kinematic state
    whose frame-to-frame steps are mostly process noise. Like the stiffness assembly of the FEM
    model, :meth:`fx` rejects a parameter outside its admissible range (``|theta| > LIMIT``)
    and, with ``fail_at``, any state at that frame (a model error that is not a divergence)."""

    def __init__(self, q: float, n_frames: int = 12, fail_at: int | None = None):
        self.n_restart, self.dim_state, self.dim_obs, self.n_frames = 1, 2, 1, n_frames
        self.estimates_material = True
        self._H = np.array([[1.0, 0.0]])
        self.x0 = np.zeros(2)
        self.P0 = np.diag([1.0, 1.0])
        self.Q = np.diag([q, 0.0])
        self.R = np.array([[0.01]])
        self.F = np.array([[1.0, 1.0], [0.0, 1.0]])
        self.fail_at = fail_at

    def fx(self, z, t):
        z = np.asarray(z, float).ravel()
        if abs(z[1]) > LIMIT:
            raise ValueError(f"theta: expected |theta| <= {LIMIT}, got {z[1]:.3g}")
        if t == self.fail_at:
            raise ValueError("fail_at: a model error unrelated to the estimate")
        return self.F @ z

    def F_jacobian(self, z, t):
        return self.F


def zigzag(n_frames: int, step: float = 6.0) -> np.ndarray:
    """Observations 0, step, 0, step, ...: steps of +-step, no drift (theta = 0 on average)."""
    return (step * (np.arange(n_frames) % 2)).reshape(-1, 1)


def test_reduced_order_ukf_names_the_missing_process_noise_when_its_material_diverges():
    y = zigzag(12)
    model = DriftModel(q=36.0)
    # the EKF with the model's process noise puts the zigzag into the kinematics: theta stays in range
    ekf = CyclicEKF(max_loops=1, engine="structured").run(model, y)
    assert abs(ekf.theta[0]) < 1.0
    # without process noise the EKF hands the zigzag to theta and leaves the admissible range:
    # the failure is the missing Q, which the reduced-order UKF leaves out by construction
    with pytest.raises(ValueError, match="theta: expected"):
        CyclicEKF(max_loops=1, engine="structured").run(DriftModel(q=0.0), y)
    with pytest.raises(ValueError, match="reduced-order UKF") as info:
        CyclicEKF(max_loops=1, engine="roukf").run(model, y)
    msg = str(info.value)
    assert "process noise" in msg and "'structured'" in msg and "estimator" in msg
    assert "frame 1" in msg                              # the step out of frame 1, after its update
    assert "NIS/dof" in msg
    # the model's own error is kept as the cause
    assert isinstance(info.value.__cause__, ValueError) and "theta: expected" in str(info.value.__cause__)


def test_a_model_error_without_inconsistent_innovations_is_passed_on_unchanged():
    y = np.zeros((12, 1))                                # what the model predicts: NIS small
    with pytest.raises(ValueError, match="^fail_at: a model error unrelated") as info:
        CyclicEKF(max_loops=1, engine="roukf").run(DriftModel(q=36.0, fail_at=4), y)
    assert info.value.__cause__ is None
