#!/usr/bin/env bash
# Levels of the mesh study that the 2-core machine cannot hold, or takes hours on, run side
# by side on a GPU machine (element kernels in JAX, factorisation in cuDSS; one process per
# run, all at once):
#
#   bash benchmarks/gpu_levels.sh OUTDIR CASEFILE:LEVEL [CASEFILE:LEVEL ...]
#
# e.g. bash benchmarks/gpu_levels.sh out cases/surgery/case5.toml:finest \
#        cases/surgery/case5.toml:ultrafine
# Each is benchmarks/mesh_convergence.py run-one (the study's summary, with its wall time
# and peak memory); its summary.json is copied to OUTDIR/<case file's stem>_<level>.json:
# put it in RUNS/<case>/<level>/summary.json to tabulate it with the others. Each run is
# cut after EYEFEM_GPU_TIMEOUT seconds (default 540). Needs a CUDA jaxlib, CuPy and cuDSS
# (pip install -e ".[gpu]"; EYEFEM_CUDSS_LIB names libcudss.so.0 elsewhere, with the
# folder of the CUDA 13 wheels' libraries, site-packages/nvidia/cu13/lib, on
# LD_LIBRARY_PATH so that it finds their cuBLAS). Measured on one H200 (docs/convergence.md,
# "The sixth level"): case 5 on ultrafine 296 s, 12.4 GB host memory, about 8 s per Newton
# iteration; a case that takes ~100 iterations there (case 1) needs a longer cut.
set -u
out=${1:?give an output folder}
shift
mkdir -p "$out"
export PYTHONUNBUFFERED=1 EYEFEM_JAX_CACHE=off XLA_PYTHON_CLIENT_PREALLOCATE=false
exec > >(tee -a "$out/log.txt") 2>&1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
python3 -c "import jax, os; print('jax', jax.__version__, jax.devices(), os.cpu_count(), 'cores')"
python3 -c "from eyefem.solve import cudss; cudss._runtime(); print('cudss available')" || exit 1
work=$(mktemp -d)
pids=()
for job in "$@"; do
  case_file=${job%:*} level=${job##*:}
  name=$(basename "$case_file" .toml)_$level
  mkdir -p "$work/$name"
  (/usr/bin/time -f "$name: %e s wall, %M KB max RSS" timeout "${EYEFEM_GPU_TIMEOUT:-540}" \
     python3 benchmarks/mesh_convergence.py run-one "$case_file" "$level" "$work/$name" \
     > "$work/$name.log" 2>&1
   echo "$name: exit $?"; grep -v "INFO  " "$work/$name.log" | tail -4
   grep "progress:" "$work/$name.log" | tail -1
   cp "$work/$name/summary.json" "$out/$name.json" 2>/dev/null) &
  pids+=($!)
done
wait "${pids[@]}"  # not a bare wait: it would also wait for the log's tee
