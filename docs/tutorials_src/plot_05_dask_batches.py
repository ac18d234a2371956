"""
Many runs on Dask
=================

A noise draw of the synthetic comparison or a sequence file of the measured workflow is one
**job**; :func:`~sfem_filters.batch.run_batch` runs a list of jobs on a scheduler and keeps one
result file per job in a folder, written as each finishes. The same job gives the same bytes on
any scheduler; a rerun skips the jobs whose result is already there (same configuration, inputs
and version: the job's *fingerprint*), so a killed batch resumes where it stopped.

*Setting.* Quick: two noise seeds on a local Dask cluster with one worker. Full: Table 1 over 100
noise draws, ``sfem-filters compare --seed 0-99 --summary`` (one worker per core), or here
``SFEM_DOCS_QUICK=0`` (100 seeds, two workers).
"""

# %%
# Jobs and a local cluster
# ------------------------
# ``scheduler="local"`` starts a Dask ``LocalCluster`` (``workers`` processes, one thread each,
# default one per core) and closes it at the end; ``"serial"`` runs the jobs in this process.
# The worker processes start by importing the script that made the cluster, so a script must
# run its batch under ``if __name__ == "__main__":`` (as any script using multiprocessing).
import os
import tempfile

import matplotlib.pyplot as plt

from sfem_filters.batch import compare_jobs, run_batch
from sfem_filters.benchmark import format_summary, summarise

QUICK = os.environ.get("SFEM_DOCS_QUICK", "1") != "0"
seeds = range(2) if QUICK else range(100)

folder = tempfile.mkdtemp()
jobs = compare_jobs(seeds, refine=1, noise_mm=0.1)          # one job per noise seed
print([job.name for job in jobs])
if __name__ == "__main__":
    report = run_batch(jobs, folder, scheduler="local", workers=1 if QUICK else 2, progress=False)
    print(report.summary_line())
    print("files:", sorted(os.listdir(folder)))

# %%
# A rerun skips what is done
# --------------------------
# Same jobs, same folder: nothing runs, the stored results are read back. (``"serial"`` here,
# since there is nothing to distribute.)
if __name__ == "__main__":
    again = run_batch(jobs, folder, scheduler="serial", progress=False)
    print(again.summary_line())
    print("ran:", again.ran, " skipped:", again.skipped)

# %%
# Table 1 over the draws
# ----------------------
# ``report.records`` are the stored results; :func:`~sfem_filters.benchmark.summarise` turns
# them into the rejection rate of each strategy with its Wilson interval.
if __name__ == "__main__":
    results = [report.records[job.name]["result"] for job in jobs]
    summary = summarise(results)
    print(format_summary(summary))

    strategies = summary["strategies"]
    fig, ax = plt.subplots(figsize=(6.5, 3))
    for k, (name, v) in enumerate(strategies.items()):
        lo, hi = v["interval"]
        ax.errorbar(v["rate"], k, xerr=[[v["rate"] - lo], [hi - v["rate"]]], fmt="o", capsize=4)
    ax.set_yticks(range(len(strategies)), list(strategies))
    ax.set_xlim(-0.05, 1.05)
    ax.set_xlabel(f"KS rejection rate over {len(results)} draws (95% Wilson interval)")
    fig.tight_layout()

# %%
# On a cluster
# ------------
# Any running Dask scheduler works: start one by hand (``dask scheduler`` on one machine,
# ``dask worker tcp://10.0.0.5:8786 --nthreads 1`` on each of the others) or with dask-jobqueue
# on an HPC queue, and give its address. Not executed here::
#
#     report = run_batch(jobs, "out/batch", scheduler="tcp://10.0.0.5:8786")
#
# or on the command line::
#
#     sfem-filters compare --seed 0-99 --summary --scheduler tcp://10.0.0.5:8786 --batch-dir out/batch
#
# The result folder must be reachable by this process; the workers send their results back to
# it. ``dense`` batches work the same way, one job per sequence file.
