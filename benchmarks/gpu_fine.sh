#!/usr/bin/env bash
# The fine eye level (32 elements per patch edge, 25,166 hexahedra) of surgical cases 1
# and 4 on a GPU (kernels and cuDSS), for the mesh convergence study (docs/convergence.md):
#
#   bash benchmarks/gpu_fine.sh OUTDIR
#
# Runs benchmarks/mesh_convergence.py run-one for each (the study's run folder layout)
# and copies summary.json, stages.csv and surgery_history.csv of each to
# OUTDIR/<case>_fine_*; put them in RUNS/<case>/fine to tabulate them with the others.
set -u
out=${1:?give an output folder}
mkdir -p "$out"
export PYTHONUNBUFFERED=1 EYEFEM_JAX_CACHE=off XLA_PYTHON_CLIENT_PREALLOCATE=false
exec > >(tee "$out/log.txt") 2>&1
python3 -c "from eyefem.solve import cudss; print('cudss available:', cudss.available()); cudss.available() or cudss._runtime()" || exit 1
timeout 60 python3 -m pytest -q -p no:cacheprovider tests/test_cudss.py || echo "test_cudss failed"
for case in case1 case4; do
  /usr/bin/time -f "$case fine on gpu + cudss: %e s wall, %M KB max RSS" timeout 420 \
    python3 benchmarks/mesh_convergence.py run-one cases/surgery/$case.toml fine /tmp/$case-fine \
    2>&1 | grep -v "INFO        \|progress:" || echo "$case fine failed"
  for f in summary.json stages.csv surgery_history.csv; do
    cp /tmp/$case-fine/$f "$out/${case}_fine_$f" 2>/dev/null
  done
done
