"""The paper's synthetic comparison through the Python API, driving filterpy by hand.

Run:  python examples/synthetic_comparison.py
"""
import numpy as np

from sfem_filters import cyclic_estimate
from sfem_filters.benchmark import (
    STRATEGIES,
    benchmark_model,
    ks_test,
    pinned_benchmark,
)
from sfem_filters.fem import nodal_strains

bench = pinned_benchmark(seed=0)                 # mesh, loads, noisy boundary data, ground truth
truth_eyy = bench.strain[8, :, 1]                # e_yy at frame 9 (index 8)

# 1. One filterpy ExtendedKalmanFilter over the sequence, with the true material fixed.
model = benchmark_model(bench, "perfect_kf")
ekf = model.make_ekf()                           # filterpy EKF with x0, P0, Q, R from the model
states = []
for t, y in enumerate(bench.observations):
    if t > 0:
        ekf.predict(u=t - 1)                     # exact transition from frame t-1 to t
    ekf.update(y.reshape(-1, 1), model.H_jacobian, model.hx, args=t, hx_args=t)
    states.append(ekf.x.ravel().copy())
U = model.displacements(np.array(states))
print("filterpy by hand, perfect material: KS D =", round(ks_test(truth_eyy, nodal_strains(bench.mesh, U)[8, :, 1]).D, 4))

# 2. The three strategies are configurations of the same model; the joint EKF loops over the
#    periodic sequence until the material converges.
for strategy in STRATEGIES:
    model = benchmark_model(bench, strategy)
    result = cyclic_estimate(model, bench.observations, progress=True, description=strategy)
    U = model.displacements(result.states)
    eyy = nodal_strains(bench.mesh, U)[8, :, 1]
    ks = ks_test(truth_eyy, eyy)
    line = f"{strategy:<11} loops={result.loops:<3d} KS D={ks.D:.4f} p={ks.p_asymptotic:.4f} H={ks.H}"
    if model.estimates_material:
        E = model.material_of_theta(result.theta).E
        line += f"  mean E middle {E[bench.middle].mean() / 1e3:.1f} kPa (true 105), outside {E[~bench.middle].mean() / 1e3:.1f} kPa (true 75)"
    print(line)
