#!/bin/bash
cd /work/main
while pgrep -f "cacc-bench tune --algos dcea" >/dev/null; do sleep 20; done
echo "A start $(date)"
.venv/bin/cacc-bench train --algo ia2c,fprint,dial,commnet,wac --scenario catchup-v1 --seeds 1,2 --tuned --executor process --workers 2 --out results/seeds --resume
echo "A done $(date)"
