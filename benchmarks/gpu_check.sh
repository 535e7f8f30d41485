#!/usr/bin/env bash
# The element kernels on a GPU against the same machine's CPU cores, in one run.
#
#   bash benchmarks/gpu_check.sh OUTDIR
#
# Needs a CUDA jaxlib and a GPU. Runs, each on --device cpu and then --device gpu:
#   1. bench_core at 1,536 hexahedra (8:4, with the host's linear solve) and 12,000
#      hexahedra (20:5, FEBio's mesh of docs/performance.md, kernels, residual and
#      assembly only: --no-solve), one Newton iteration's parts at a 1% dilation;
#   2. coarse surgical case 1 end to end (eyefem --device ... run), and compares the two
#      runs' outcomes (float64 on both: they must agree to round-off).
# Writes OUTDIR/log.txt, OUTDIR/core_*.json and OUTDIR/case1_*_summary.json.
set -u
out=${1:?give an output folder}
mkdir -p "$out"
export PYTHONUNBUFFERED=1 EYEFEM_JAX_CACHE=off
exec > >(tee "$out/log.txt") 2>&1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
python3 -c "import jax, os; print('jax', jax.__version__, jax.devices(), os.cpu_count(), 'cores')"
for dev in cpu gpu; do
  timeout 150 python3 benchmarks/bench_core.py --sizes 8:4 --no-path --repeats 5 \
    --device $dev --json "$out/core_small_$dev.json" | tail -3 || { echo "small $dev failed"; exit 1; }
done
for dev in cpu gpu; do
  timeout 200 python3 benchmarks/bench_core.py --sizes 20:5 --no-path --no-solve --repeats 3 \
    --device $dev --json "$out/core_20_5_$dev.json" | tail -3 || echo "20:5 $dev failed"
done
for dev in gpu cpu; do
  /usr/bin/time -f "case 1 coarse on $dev: %e s wall, %M KB max RSS" timeout 200 \
    python3 -m eyefem.cli.main -q --device $dev run cases/surgery/case1.toml --mesh coarse \
    --no-vtu --out "/tmp/case1_$dev" || echo "case 1 $dev failed"
  cp "/tmp/case1_$dev/summary.json" "$out/case1_${dev}_summary.json" 2>/dev/null
done
python3 - "$out" <<'EOF'
import json, sys
from pathlib import Path
out = Path(sys.argv[1])
try:
    a, b = (json.loads((out / f"case1_{d}_summary.json").read_text()) for d in ("cpu", "gpu"))
except OSError as exc:
    sys.exit(f"no comparison: {exc}")
oa, ob = a.get("outcomes", a), b.get("outcomes", b)
worst = 0.0
for k, v in oa.items():
    if "wall" in k or "time" in k:
        continue
    if isinstance(v, (int, float)) and isinstance(ob.get(k), (int, float)) and v:
        d = abs(ob[k] - v) / abs(v)
        worst = max(worst, d)
        print(f"{k}: cpu {v:.9g} gpu {ob[k]:.9g} rel {d:.1e}")
print(f"worst relative difference of the outcomes, gpu vs cpu: {worst:.1e}")
EOF
