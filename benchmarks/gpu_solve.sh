#!/usr/bin/env bash
# The whole Newton iteration on a GPU: the element kernels (JAX) and the factorisation
# and back-solves (cuDSS, eyefem.solve.cudss), in one run.
#
#   bash benchmarks/gpu_solve.sh OUTDIR
#
# Needs a CUDA jaxlib, CuPy and cuDSS: EYEFEM_CUDSS_LIB names libcudss.so.0 where the
# nvidia-cudss-cu13 wheel is not installed (its libcublas.so.13 must be on the loader's
# path). Runs:
#   1. tests/test_cudss.py (the backend against scipy and SuperLU);
#   2. default surgical case 4 end to end, eyefem --device gpu run (wall time, Newton
#      iterations, outcomes: compare them with docs/surgery_results.md);
#   3. eyefem --device gpu stability on that run (ARPACK on cuDSS's solves);
#   4. bench_core on FEBio's mesh (20:5, 12,000 hexahedra): one whole Newton iteration
#      and the whole load path, kernels and solve on the GPU.
# Writes OUTDIR/log.txt, OUTDIR/case4_gpu_summary.json, OUTDIR/core_20_5_cudss.json.
#
#   bash benchmarks/gpu_solve.sh OUTDIR plan
#
# instead runs default surgical case 1 and the README's planning example (default mesh)
# on the GPU: OUTDIR/log.txt, OUTDIR/case1_gpu_summary.json, OUTDIR/plan_gpu.json (plan_summary.json).
set -u
out=${1:?give an output folder}
mkdir -p "$out"
export PYTHONUNBUFFERED=1 EYEFEM_JAX_CACHE=off XLA_PYTHON_CLIENT_PREALLOCATE=false
exec > >(tee "$out/log.txt") 2>&1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
python3 -c "import jax, cupy, os; print('jax', jax.__version__, jax.devices(), 'cupy', cupy.__version__, os.cpu_count(), 'cores')"
python3 -c "from eyefem.solve import cudss; print('cudss available:', cudss.available()); cudss.available() or cudss._runtime()" || exit 1
if [ "${2:-}" = plan ]; then
  /usr/bin/time -f "case 1 default on gpu + cudss: %e s wall, %M KB max RSS" timeout 200 \
    python3 -m eyefem.cli.main -q --device gpu run cases/surgery/case1.toml --no-vtu \
    --out /tmp/case1_gpu || echo "case 1 failed"
  cp /tmp/case1_gpu/summary.json "$out/case1_gpu_summary.json" 2>/dev/null
  /usr/bin/time -f "planning example on gpu + cudss: %e s wall, %M KB max RSS" timeout 400 \
    python3 -m optimize.plan cases/surgery/case1.toml --target-indentation 0.8 --iop-max 25 \
    --vars tightening,suture_width --device gpu --out /tmp/plan_gpu || echo "plan failed"
  cp /tmp/plan_gpu/plan_summary.json "$out/plan_gpu.json" 2>/dev/null
  exit 0
fi
timeout 120 python3 -m pytest -q -rs -p no:cacheprovider tests/test_cudss.py || echo "test_cudss failed"
/usr/bin/time -f "case 4 default on gpu + cudss: %e s wall, %M KB max RSS" timeout 300 \
  python3 -m eyefem.cli.main --device gpu run cases/surgery/case4.toml --no-vtu \
  --out /tmp/case4_gpu 2>&1 | grep -v "INFO        \|progress:" || echo "case 4 failed"
cp /tmp/case4_gpu/summary.json "$out/case4_gpu_summary.json" 2>/dev/null
timeout 150 python3 -m eyefem.cli.main -q --device gpu stability cases/surgery/case4.toml \
  --out /tmp/case4_gpu --stage tighten --modes 4 --deformation || echo "stability failed"
timeout 200 python3 benchmarks/bench_core.py --sizes 20:5 --repeats 3 --device gpu \
  --backend cudss --json "$out/core_20_5_cudss.json" | tail -4 || echo "20:5 failed"
