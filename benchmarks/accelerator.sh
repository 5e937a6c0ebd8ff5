#!/usr/bin/env bash
# The benchmarks that say what an accelerator (a CUDA GPU) buys, in one bounded run.
#
#   JAXFACE_SHARED=../shared bash benchmarks/accelerator.sh [RESULTS_DIR] [FIT_S SYNTH_S PBD_S]
#
# Runs, each under its own time limit (seconds, defaults 330 / 110 / 70) so that one slow
# part cannot take the others' time, and in this order:
#   1. bench_fit.py on subject bs900 (no round trip, no B2): subject build, one scan alone cold
#      and warm, the 10 expression scans as one batch (on an accelerator the inner solves of a
#      batch are one jax.vmap, jaxface.fit.inner.batch_mode), the batch again once compiled,
#      accuracy against the truth meshes, then the same scans one at a time (singles_over_batch,
#      singles_over_warm_batch);
#   2. bench_synth.py (float32, ICT face): one synthesis, vmap throughput, forward Jacobian,
#      reverse pass;
#   3. bench_pbd.py --quick on the 100k-vertex sheet and the ICT face: projections per second.
# Each benchmark's output goes to RESULTS_DIR/<name>.log (default benchmarks/results/accelerator)
# and its JSON beside it; env.txt records the JAX version and devices. Nothing here needs a
# GPU: on a CPU it measures the CPU. The numbers from the H200 are in the README (Benchmarks).
set -u
cd "$(dirname "$0")/.."
R="${1:-benchmarks/results/accelerator}"
FIT_S="${2:-330}"
SYNTH_S="${3:-110}"
PBD_S="${4:-70}"
mkdir -p "$R"
rm -f "$R/summary.txt"
export PYTHONUNBUFFERED=1 MPLBACKEND=Agg

python3 - >"$R/env.txt" 2>&1 <<'EOF'
import importlib, platform
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
print("python", platform.python_version(), "| jax", jax.__version__, "| backend", jax.default_backend())
print("devices", [getattr(d, "device_kind", str(d)) for d in jax.devices()])
for name in ("jaxlib", "equinox", "optimistix", "lineax", "numpy", "scipy", "trimesh"):
    m = importlib.import_module(name)
    print(name, getattr(m, "__version__", "?"))
import jaxface
from jaxface.fit.inner import batch_mode
print("jaxface", jaxface.__file__, "| batch mode", batch_mode())
x = jnp.ones((4, 4), jnp.float64) @ jnp.ones((4, 4), jnp.float64)
print("float64 matmul ok:", float(x[0, 0]) == 4.0)
EOF
rc=$?
cat "$R/env.txt"
if [ "$rc" -ne 0 ]; then
  echo "accelerator.sh: the environment check failed (see $R/env.txt)" >&2
  exit 1
fi

run() {  # run NAME LIMIT ARGS...
  local name="$1" limit="$2"
  shift 2
  local t0=$SECONDS
  echo "== $name (limit ${limit} s)"
  rm -f "benchmarks/results/$name.json"
  timeout --signal=INT --kill-after=10 "$limit" python3 "benchmarks/$name.py" "$@" 2>&1 | tee "$R/$name.log"
  local code=${PIPESTATUS[0]}
  echo "== $name: exit $code after $((SECONDS - t0)) s" | tee -a "$R/summary.txt"
  [ -f "benchmarks/results/$name.json" ] && [ "$R" != "benchmarks/results" ] && cp "benchmarks/results/$name.json" "$R/"
  return 0
}

run bench_fit "$FIT_S" --subjects bs900 --no-round-trip --no-b2 --warm-batch --results "$R"
run bench_synth "$SYNTH_S" --repeat 5 --footprint-clusters ""
run bench_pbd "$PBD_S" --quick --sizes 100k,ict
cat "$R/summary.txt"
