#!/bin/bash
# One arm of a training-recipe A/B on a `drivesim run REC` workspace: train its run's train config again on the
# workspace's own world with overrides (same seed and 40-min limit unless overridden), then evaluate the final policy
# and its warm start on seeds 0-999 as bench_table1 does (no baselines), so the rows compare with that drive's
# Table I rows on the same seeds.
# usage: recording_arm.sh WORKSPACE RUN NAME [--set KEY=VALUE ...]
#   RUN: the workspace's run folder whose config.json "train" object is retrained (the chain's own run)
set -euo pipefail
ws=$1; run=$2; name=$3; shift 3
drivesim=${DRIVESIM:-drivesim}
cd "$ws"
config=$(mktemp --suffix=.json)
python3 -c "import json, sys; json.dump(json.load(open(sys.argv[1]))['train'], open(sys.argv[2], 'w'))" \
    "$run/config.json" "$config"
before=$(ls -d runs/overtake-* | sort | tail -1)
$drivesim --workspace . train overtake --config "$config" "$@"
new=$(ls -d runs/overtake-* | sort | tail -1)
[ "$new" != "$before" ] || { echo "no new run folder" >&2; exit 1; }
for policy in "$new" "$new/checkpoints/warm_start.pt"; do
    suffix=$([ "$policy" = "$new" ] && echo "" || echo "-warm")
    $drivesim --workspace . eval --policy "$policy" --episodes 1000 --name "arm-$name$suffix" --record none \
        --set baseline_episodes=0 --force
done
echo "arm $name: $new"
