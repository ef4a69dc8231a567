#!/usr/bin/env bash
# Run one DRVS scenario end to end, without roslaunch.
#
#   scripts/run_scenario.sh WORLD [--timeout S] [--out DIR] [--external-master] [--stay]
#                                 [--camera-source render|topic]
#
# Starts a private rosmaster on a free port (or, with --external-master, uses
# the environment's ROS_MASTER_URI), then drvs_server, world_sim, one
# vision_system per camera of WORLD, the scenario recorder and blind_robot, each
# a plain background process with its log in DIR (default out/<world name>).
# Waits until the robot reaches the station, fails, or the timeout (default 120 s)
# passes, showing one updating line of state, distance to goal, re-plans and
# elapsed time; then stops everything it started (also on Ctrl-C) and leaves
# DIR/summary.json and DIR/run.png. Exits 0 only if the robot reached the station.
# With --stay, DRVS (server, world_sim, vision systems) keeps running after the
# robot is done, until Ctrl-C, so it can be explored by hand (see the README).
# With --camera-source topic, the simulation drives the vision systems like real
# cameras: one sim_camera per camera publishes its rendered colour and depth
# images, CameraInfo and tf, and each vision_system runs with _source:=topic on
# them (default: render, each vision system renders its own view on demand).
set -euo pipefail

root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
usage() {
  echo "usage: $0 WORLD [--timeout S] [--out DIR] [--external-master] [--stay] [--camera-source render|topic]" >&2
  exit 2
}

world="" timeout=120 out="" external=0 stay=0 source=render
while [ $# -gt 0 ]; do
  case "$1" in
    --timeout) [ $# -ge 2 ] || usage; timeout=$2; shift 2 ;;
    --out) [ $# -ge 2 ] || usage; out=$2; shift 2 ;;
    --external-master) external=1; shift ;;
    --stay) stay=1; shift ;;
    --camera-source) [ $# -ge 2 ] || usage; source=$2; shift 2 ;;
    -h|--help) usage ;;
    -*) echo "run_scenario: unknown option $1" >&2; usage ;;
    *) [ -z "$world" ] || usage; world=$1; shift ;;
  esac
done
[ -n "$world" ] || usage
[ -f "$world" ] || { echo "run_scenario: world file $world not found" >&2; exit 2; }
[[ "$timeout" =~ ^[0-9]+([.][0-9]+)?$ ]] || { echo "run_scenario: --timeout needs seconds, got $timeout" >&2; exit 2; }
[[ "$source" =~ ^(render|topic)$ ]] || { echo "run_scenario: --camera-source is render or topic, got $source" >&2; exit 2; }
[ -x "$root/.venv/bin/python" ] || { echo "run_scenario: no .venv: run scripts/setup.sh (or make demo) first" >&2; exit 2; }

world=$(cd "$(dirname "$world")" && pwd)/$(basename "$world")
out=${out:-$root/out/$(basename "$world" .yaml)}
mkdir -p "$out"
out=$(cd "$out" && pwd)
rm -f "$out"/*.log "$out"/summary.json "$out"/run.png "$out"/status.line

if [ $external -eq 0 ]; then unset ROS_MASTER_URI; fi
# shellcheck source=scripts/env.sh
source "$root/scripts/env.sh"
py="$root/.venv/bin/python"
export PYTHONUNBUFFERED=1

pids=() names=()
start() {  # start NAME COMMAND...: a background process logging to $out/NAME.log
  local name=$1; shift
  "$@" >"$out/$name.log" 2>&1 &
  pids+=($!) names+=("$name")
}

stop_all() {
  local i pid deadline
  trap - EXIT INT TERM
  [ ${#pids[@]} -gt 0 ] || return 0
  # Newest first, SIGINT (rospy's clean shutdown), then SIGTERM, then SIGKILL.
  for sig in INT TERM KILL; do
    local alive=0
    for ((i = ${#pids[@]} - 1; i >= 0; i--)); do
      pid=${pids[$i]}
      if kill -0 "$pid" 2>/dev/null; then kill -s "$sig" "$pid" 2>/dev/null || true; alive=1; fi
    done
    [ $alive -eq 1 ] || break
    deadline=$((SECONDS + 5))
    while [ $SECONDS -lt $deadline ]; do
      alive=0
      for pid in "${pids[@]}"; do kill -0 "$pid" 2>/dev/null && alive=1; done
      [ $alive -eq 1 ] || break
      sleep 0.1
    done
  done
  wait 2>/dev/null || true
}
trap stop_all EXIT
trap 'echo; echo "run_scenario: interrupted" >&2; stop_all; exit 130' INT TERM

if [ $external -eq 0 ]; then
  port=$("$py" -c 'from drvs.testing.harness import free_port; print(free_port())')
  export ROS_MASTER_URI="http://127.0.0.1:$port/"
  export ROS_HOME="$out/ros_home" ROS_LOG_DIR="$out/ros_log"
  start rosmaster rosmaster --core -p "$port"
fi
# Wait (with a deadline) until the master answers.
"$py" - <<'EOF' || { echo "run_scenario: no ROS master answers at $ROS_MASTER_URI" >&2; exit 1; }
import os, sys
from drvs.testing.harness import wait_for
import xmlrpc.client
def answers():
    try:
        with xmlrpc.client.ServerProxy(os.environ['ROS_MASTER_URI']) as master:
            return master.getPid('/run_scenario')[0] == 1
    except OSError:
        return False
wait_for(answers, 20.0, 'the ROS master')
EOF

cameras=$("$py" -c 'import sys; from drvs.world import load_world
print(" ".join(c.name for c in load_world(sys.argv[1]).vision_systems))' "$world")

start drvs_server "$py" "$root/nodes/drvs_server" __name:=drvs
start world_sim "$py" "$root/nodes/world_sim" __name:=world_sim _world:="$world"
for camera in $cameras; do
  if [ "$source" = topic ]; then
    start "sim_$camera" "$py" "$root/nodes/sim_camera" __name:="sim_$camera" _world:="$world" _cameras:="$camera"
    start "$camera" "$py" "$root/nodes/vision_system" __name:="$camera" _source:=topic _depth:=true \
      image:="/$camera/image_raw" camera_info:="/$camera/camera_info" depth:="/$camera/depth/image_raw"
  else
    start "$camera" "$py" "$root/nodes/vision_system" __name:="$camera" _world:="$world"
  fi
done
# The case study starts once DRVS is up: every camera registered with the server.
"$py" - "$cameras" <<'EOF' || { echo "run_scenario: the vision systems did not register; see $out/vs*.log" >&2; exit 1; }
import sys, threading
import rospy
from drvs.msg import Registry
wanted = {f'/{name}/detect_object_boundary' for name in sys.argv[1].split()}
done = threading.Event()
def on_registry(msg):
    if wanted <= {entry.service_name for entry in msg.vision_systems}:
        done.set()
rospy.init_node('run_scenario_wait', anonymous=True, disable_signals=True)
rospy.Subscriber('/drvs/registry', Registry, on_registry)
sys.exit(0 if done.wait(60.0) else 1)
EOF
start recorder "$py" "$root/nodes/scenario_recorder" __name:=scenario_recorder _world:="$world" _out:="$out"
start robot "$py" "$root/nodes/blind_robot" __name:=robot _world:="$world" _once:=true
robot_pid=${pids[-1]} recorder_pid=${pids[-2]}

echo "run_scenario: $(basename "$world") with ${cameras// /, } ($source); logs in $out"
started=$SECONDS
result=timeout
while [ $((SECONDS - started)) -lt "${timeout%.*}" ]; do
  if ! kill -0 "$robot_pid" 2>/dev/null; then
    if wait "$robot_pid"; then result=reached; else result=failed; fi
    break
  fi
  for i in "${!pids[@]}"; do
    if ! kill -0 "${pids[$i]}" 2>/dev/null && [ "${pids[$i]}" != "$robot_pid" ]; then
      echo; echo "run_scenario: ${names[$i]} exited early; see $out/${names[$i]}.log" >&2
      result=crashed; break 2
    fi
  done
  line=$(cat "$out/status.line" 2>/dev/null || echo "starting")
  printf '\r\033[K%s | elapsed %3ds' "$line" $((SECONDS - started))
  sleep 0.5
done
printf '\r\033[K'
finished=$((SECONDS - started))

# The recorder writes summary.json and run.png when it is told to stop.
kill -s INT "$recorder_pid" 2>/dev/null || true
for _ in $(seq 100); do kill -0 "$recorder_pid" 2>/dev/null || break; sleep 0.1; done
if [ $stay -eq 1 ] && [ "$result" != crashed ]; then
  echo "run_scenario: robot $result; DRVS keeps running at $ROS_MASTER_URI until Ctrl-C"
  while true; do sleep 1; done
fi
stop_all

case $result in
  reached) echo "run_scenario: the robot reached the station after $finished s" ;;
  failed) echo "run_scenario: the robot failed: $(tail -n 3 "$out/robot.log" | tr '\n' ' ')" >&2 ;;
  timeout) echo "run_scenario: timed out after $timeout s" >&2 ;;
esac
[ -f "$out/summary.json" ] && echo "run_scenario: summary $out/summary.json, picture $out/run.png"
[ "$result" = reached ]
