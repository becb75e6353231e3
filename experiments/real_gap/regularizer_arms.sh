#!/bin/bash
# One arm of the imitation-regularizer study: train a run's train config again on its workspace's world with a seed
# and overrides, then evaluate the final policy and its warm start on seeds 0-99 (no baselines). The per-side table:
#   experiments/real_gap/failure_phases.py --eval expert=WS/eval/EXPERT --eval NAME=WS/eval/exp-NAME ...
# usage: regularizer_arms.sh WORKSPACE TRAIN_CONFIG_JSON NAME SEED [--set KEY=VALUE ...]
#   TRAIN_CONFIG_JSON: the "train" object of a run's config.json (the demo run's, for the study's figures)
set -euo pipefail
ws=$1; config=$2; name=$3; seed=$4; shift 4
drivesim=${DRIVESIM:-drivesim}
cd "$ws"
$drivesim --workspace . train overtake --config "$config" --set seed="$seed" --set time_limit_s=3000 "$@"
run=$(ls -d runs/overtake-* | sort | tail -1)
for policy in "$run" "$run/checkpoints/warm_start.pt"; do
    suffix=$([ "$policy" = "$run" ] && echo "" || echo "-warm")
    $drivesim --workspace . eval --policy "$policy" --episodes 100 --name "exp-$name$suffix" --record none \
        --set baseline_episodes=0
done
