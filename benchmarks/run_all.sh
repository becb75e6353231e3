#!/usr/bin/env bash
# Run every benchmark in sequence on a quiet machine and merge the figures into benchmarks/RESULTS.md.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
$PY benchmarks/bench_render.py
$PY benchmarks/bench_synth.py
$PY benchmarks/bench_ingest.py
$PY benchmarks/bench_video_sfm.py
$PY benchmarks/bench_poses.py
$PY benchmarks/bench_depth.py
$PY benchmarks/bench_preprocess_world.py
.venv/bin/drivesim --workspace "$(mktemp -d)" bench fidelity --seed 0 --frames 32 --view-frames 6 --markdown benchmarks/results/fidelity.md \
  --figure benchmarks/results/fidelity.png
$PY benchmarks/bench_train_speed.py --world "${DEMO_WORLD:-/tmp/ws-demo/world}"
$PY benchmarks/bench_eval.py --episodes 1000 --world "${DEMO_WORLD:-/tmp/ws-demo/world}"
$PY benchmarks/bench_record.py --world small --world "${DEMO_WORLD:-/tmp/ws-demo/world}" --repeats 3
# Learning under wall-clock budgets (~2 h): lane 15 min, overtake 60 min, lane on KITTI 15 min, cutin 30 min.
if [ -n "${LEARNING:-}" ]; then $PY experiments/learning/bench_learning.py ${KITTI_WORLD:+--kitti-world "$KITTI_WORLD"}; fi
$PY benchmarks/collect_results.py
