#!/usr/bin/env bash
# The bag replay of docs/robot_integration.md, counted: rtabmap_loop as a 4 Hz bag, the extractor with the packaged
# extractor.yaml (best effort), the matcher in mapping mode, `lln-bag play` with its defaults.
# Prints the keyframes stored (of 84) and the WARN lines that say why any frame was not stored.
#   bash bench/bench_replay.sh [PLAYER_PROFILE.xml]   # a profile for the player (default: lln-bag's own)
#   EXTRACTOR_ARGS='-p reliability:=reliable -p frame_queue:=100' bash bench/bench_replay.sh   # for bags
set -euo pipefail
cd "$(dirname "$0")/.."
B=.venv/bin
W=$(mktemp -d)
trap 'rm -rf "$W"' EXIT
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-$((50 + RANDOM % 40))} ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
unset FASTRTPS_DEFAULT_PROFILES_FILE FASTDDS_DEFAULT_PROFILES_FILE
$B/lln-bag from-images ../shared/data/rtabmap_loop "$W/bag" --glob '*.jpg' --topic /camera/image_raw --rate 4 >/dev/null
# shellcheck disable=SC2086
$B/extractor --ros-args --params-file config/extractor.yaml -r image:=/camera/image_raw ${EXTRACTOR_ARGS:-} \
  > "$W/extractor.log" 2>&1 &
E=$!
$B/matcher --ros-args --params-file config/matcher.yaml -p map_path:="$W/map.db" -p mode:=mapping \
  -r query:=landmarks > "$W/matcher.log" 2>&1 &
M=$!
if [ $# -ge 1 ]; then export FASTRTPS_DEFAULT_PROFILES_FILE=$(realpath "$1"); fi
$B/lln-bag play "$W/bag" --wait-subscribers 1 --wait-timeout 120 > "$W/play.log" 2>&1
unset FASTRTPS_DEFAULT_PROFILES_FILE
sleep 20   # the last extractions and answers
kill -INT $E $M
wait $E $M || true
echo "player: $(head -1 "$W/play.log"); extractor args: ${EXTRACTOR_ARGS:-none}"
echo "stored $(.venv/bin/python -c "from lln_ros.mapstore import MapStore; print(len(MapStore.open('$W/map.db')))") of 84 frames; load $(cut -d' ' -f1 /proc/loadavg) on $(nproc) cores"
grep -h -E 'WARN|ERROR' "$W/extractor.log" "$W/matcher.log" | sed 's/^\[[A-Z]*\] \[[0-9.]*\] //' | sort | uniq -c | sort -rn | head -5
