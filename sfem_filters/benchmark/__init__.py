"""The paper's synthetic experiment (section 3.1), pinned, and the comparison of strategies on it.

The benchmark follows ``shared/specs/synthetic-benchmark.md``; the strategies are
configurations of one :class:`sfem_filters.model.SFEMModel`:

>>> from sfem_filters.benchmark import benchmark_model, ks_test, pinned_benchmark
>>> bench = pinned_benchmark(seed=0)                  # mesh, loads, noisy data, ground truth
>>> bench.observations.shape                          # 16 frames x 26 boundary displacements
(16, 26)
>>> model = benchmark_model(bench, "joint_ekf")      # or "uniform_kf", "perfect_kf"
>>> model.dim_theta                                   # log E and logit(2 nu) of 48 elements
96
>>> round(ks_test(bench.strain[8, :, 1], bench.strain[8, :, 1]).D, 3)
0.0

:func:`run_comparison` runs the strategies and measures them (Table 1); :func:`format_table`
prints the table. Modules: :mod:`~sfem_filters.benchmark.pinned`,
:mod:`~sfem_filters.benchmark.comparison`, :mod:`~sfem_filters.benchmark.statistics` (the
two-sample KS test with MATLAB's asymptotic p, Wilson intervals),
:mod:`~sfem_filters.benchmark.summary` (Table 1 over many noise draws: :func:`summarise` the
``as_json()`` of each seed's comparison, :func:`format_summary` prints rejection rates with
their Wilson intervals).
"""
from .comparison import LABELS, PAPER_TABLE1, REPORT_FRAME, Comparison, StrategyRun, format_table, run_comparison, \
    run_strategy
from .pinned import STRATEGIES, Benchmark, benchmark_model, pinned_benchmark
from .statistics import KSResult, kolmogorov_asymptotic_p, ks_test, wilson_interval
from .summary import SUMMARY_QUANTITIES, format_summary, summarise
from .strain_scoring import StrainScore, score_strain

__all__ = ["Benchmark", "pinned_benchmark", "benchmark_model", "STRATEGIES", "Comparison", "StrategyRun",
           "run_comparison", "run_strategy", "format_table", "LABELS", "PAPER_TABLE1", "REPORT_FRAME", "KSResult",
           "ks_test", "kolmogorov_asymptotic_p", "wilson_interval", "summarise", "format_summary", "SUMMARY_QUANTITIES",
           "StrainScore", "score_strain"]
