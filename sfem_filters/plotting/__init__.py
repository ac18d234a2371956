"""Figures (PNG, matplotlib's Agg backend) of every workflow; nothing else imports this package.

Each ``*_figures(result, directory)`` writes its set of figures and returns their paths:

>>> from sfem_filters.plotting import comparison_figures, dense_figures, observe_figures
>>> paths = comparison_figures(run_comparison(seed=0), "out/figures")   # doctest: +SKIP

Modules: :mod:`~sfem_filters.plotting.comparison` (the paper's Figs. 1-5, and ``summary_figure`` of D and p
over many noise draws),
:mod:`~sfem_filters.plotting.measured` (residual, strain, material and NIS of the measured-data
workflow), :mod:`~sfem_filters.plotting.frontend` (tracked contours, velocity coherence),
:mod:`~sfem_filters.plotting.strain` (segment and global strain curves with bands, peak rings, from a
strain report's JSON).
"""
from .comparison import comparison_figures, summary_figure
from .frontend import observe_figures
from .measured import dense_figures
from .strain import strain_figures

__all__ = ["comparison_figures", "summary_figure", "dense_figures", "observe_figures", "strain_figures"]
