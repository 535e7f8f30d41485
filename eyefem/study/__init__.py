"""Population studies: parameter sweeps on a Dask cluster and uncertainty propagation.

- :mod:`eyefem.study.spec`: the sweep file (base case, parameters to vary by grid, list
  or samples, outcomes, gradients) and the planned runs (one parsed case each);
- :mod:`eyefem.study.task`: one run, as executed on a Dask worker;
- :mod:`eyefem.study.sweep`: the orchestration (``eyefem sweep``): submit, collect,
  skip completed runs, write the results table as runs complete;
- :mod:`eyefem.study.table`: the results table (Parquet and CSV, atomic);
- :mod:`eyefem.study.plots`: outcome against parameter plots, the best designs;
- :mod:`eyefem.study.uncertainty`: first-order (adjoint) against sampled statistics.

Dask and pyarrow are optional (``pip install "eyefem[sweep]"``) and imported where used.
"""
