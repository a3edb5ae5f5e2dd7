#!/usr/bin/env bash
# The GPU checks of docs/populations.md ("On a GPU"), as one script for a lent GPU machine whose
# python3 has torch, numpy, tqdm, filelock and pytest (nothing is installed; the source tree is
# on PYTHONPATH). Writes its logs to ${OUT:-results/gpu-check}. Usage: bash docs/scripts/gpu_check.sh
set -uo pipefail
cd "$(dirname "$0")/../.."
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1
out=${OUT:-results/gpu-check}
mkdir -p "$out"
{ nvidia-smi -L; nproc; python3 -c "import torch; print('torch', torch.__version__)"; } 2>&1 | tee "$out/machine.txt"
# 1. the GPU tests (they skip on a machine without one)
timeout 100 python3 -m pytest tests/test_marl/test_marl_device.py -q -p no:cacheprovider 2>&1 | tee "$out/gpu-tests.log"
# 2. training throughput, one process and one torch thread: one run and a population of six,
#    on the GPU and on this machine's CPU, the function `cacc-bench perf` times
timeout 150 python3 - <<'PY' 2>&1 | tee "$out/throughput.txt"
import json, os, time
from marl.perf import train_throughput
train_throughput("ia2c", steps=500, device="cuda")  # warm-up: CUDA context, kernels
rows = []
for population in (6, 1):
    for algo in ("ia2c", "bdc"):
        for device in ("cuda", "cpu"):
            t0 = time.perf_counter()
            rate = train_throughput(algo, steps=10_000, population=population, device=device)
            rows.append(dict(algo=algo, population=population, device=device,
                             env_steps_per_s=round(rate), wall_s=round(time.perf_counter() - t0, 1)))
            print(json.dumps(rows[-1]), flush=True)
json.dump(rows, open(os.path.join(os.environ.get("OUT", "results/gpu-check"), "throughput.json"), "w"), indent=1)
PY
# 3. the paper protocol in small (7 algorithms x 2 scenarios x 3 seeds, 20,000 steps each, in
#    populations of three over 14 processes), on the GPU and then on the CPU alone
for device in cuda cpu; do
  t0=$(date +%s.%N)
  timeout 140 python3 -m commands train --algo all --scenario catchup-v1,slowdown-v1 \
      --seeds 0,1,2 --tuned --population 3 --device $device --executor process --workers 14 \
      --steps 20000 --out "/tmp/protocol-$device" > "$out/protocol-$device.log" 2>&1
  rc=$?
  echo "protocol on $device: exit $rc, $(python3 -c "import sys,time; print(round(time.time()-float(sys.argv[1]),1))" "$t0") s wall" | tee -a "$out/protocol.txt"
  tail -3 "$out/protocol-$device.log"
done
