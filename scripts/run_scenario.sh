#!/usr/bin/env bash
# Run one DRVS scenario end to end, without roslaunch.
#
#   scripts/run_scenario.sh WORLD [--timeout S] [--out DIR] [--external-master] [--stay]
#                                 [--camera-source render|topic] [--rviz] [--record]
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
# With --rviz, RViz opens on the run with rviz/drvs.rviz (needs a display and
# Debian's rviz: make rviz-setup installs it).
# With --record, `rosbag record` writes the run to DIR/run.bag: started before
# the other nodes and stopped after them, it holds every DRVS topic (latched ones
# and tf too, so `rosbag play` drives RViz again) and the recorder's samples, from
# which `nodes/drvs_report DIR/run.bag` writes the same summary.json again.
set -euo pipefail

root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
usage() {
  echo "usage: $0 WORLD [--timeout S] [--out DIR] [--external-master] [--stay] [--camera-source render|topic] [--rviz] [--record]" >&2
  exit 2
}

world="" timeout=120 out="" external=0 stay=0 source=render rviz=0 record=0
while [ $# -gt 0 ]; do
  case "$1" in
    --timeout) [ $# -ge 2 ] || usage; timeout=$2; shift 2 ;;
    --out) [ $# -ge 2 ] || usage; out=$2; shift 2 ;;
    --external-master) external=1; shift ;;
    --stay) stay=1; shift ;;
    --rviz) rviz=1; shift ;;
    --record) record=1; shift ;;
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
if [ $rviz -eq 1 ]; then
  command -v rviz >/dev/null || bash "$root/scripts/setup.sh" --rviz || { echo "run_scenario: --rviz: installing rviz failed" >&2; exit 2; }
  [ -n "${DISPLAY:-}" ] || { echo "run_scenario: --rviz needs a display, and DISPLAY is not set" >&2; exit 2; }
fi

world=$(cd "$(dirname "$world")" && pwd)/$(basename "$world")
out=${out:-$root/out/$(basename "$world" .yaml)}
mkdir -p "$out"
out=$(cd "$out" && pwd)
rm -f "$out"/*.log "$out"/summary.json "$out"/run.png "$out"/status.line
[ $record -eq 0 ] || rm -f "$out"/run.bag "$out"/run.bag.active

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

stop_pids() {  # stop_pids PID...: in this order SIGINT (a clean shutdown), then SIGTERM, then SIGKILL
  local pid deadline
  [ $# -gt 0 ] || return 0
  for sig in INT TERM KILL; do
    local alive=0
    for pid in "$@"; do
      if kill -0 "$pid" 2>/dev/null; then kill -s "$sig" "$pid" 2>/dev/null || true; alive=1; fi
    done
    [ $alive -eq 1 ] || break
    deadline=$((SECONDS + 5))
    while [ $SECONDS -lt $deadline ]; do
      alive=0
      for pid in "$@"; do kill -0 "$pid" 2>/dev/null && alive=1; done
      [ $alive -eq 1 ] || break
      sleep 0.1
    done
  done
}

master_pid="" bag_pid=""
stop_all() {
  local i nodes=()
  trap - EXIT INT TERM
  # The nodes newest first; then the bag recorder, which so records them to their end
  # and closes the bag (indexed run.bag, no run.bag.active); the master last.
  for ((i = ${#pids[@]} - 1; i >= 0; i--)); do
    [ "${pids[$i]}" = "$master_pid" ] || nodes+=("${pids[$i]}")
  done
  stop_pids "${nodes[@]}"
  [ -z "$bag_pid" ] || stop_pids "$bag_pid"
  [ -z "$master_pid" ] || stop_pids "$master_pid"
  wait 2>/dev/null || true
}
trap stop_all EXIT
trap 'echo; echo "run_scenario: interrupted" >&2; stop_all; exit 130' INT TERM

if [ $external -eq 0 ]; then
  port=$("$py" -c 'from drvs.testing.harness import free_port; print(free_port())')
  export ROS_MASTER_URI="http://127.0.0.1:$port/"
  export ROS_HOME="$out/ros_home" ROS_LOG_DIR="$out/ros_log"
  start rosmaster rosmaster --core -p "$port"
  master_pid=${pids[-1]}
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

if [ $record -eq 1 ]; then
  # Not in pids: stop_all stops it after every node. Ready once it subscribes to every topic.
  topics="/drvs/registry /drvs/markers /world_sim/poses /world_sim/ground_truth /robot/status /robot/path
    /robot/map /robot/pose /robot/cmd_vel /scenario_recorder/samples /diagnostics /tf /tf_static /rosout"
  for camera in $cameras; do topics+=" /$camera/stats"; done
  # The program `rosbag record` runs, started directly: SIGINT reaches it (not a wrapper
  # that fails on the SIGINT it finds ignored in a background job) and its end is the bag's.
  # In a session of its own, so that a Ctrl-C in the terminal reaches it only through stop_all.
  record_bin=$("$py" -c 'import roslib.packages; print((roslib.packages.find_node("rosbag", "record") or [""])[0])')
  [ -x "$record_bin" ] || { echo "run_scenario: --record needs Debian's python3-rosbag (scripts/setup.sh installs it)" >&2; exit 2; }
  # shellcheck disable=SC2086
  setsid "$record_bin" -O "$out/run.bag" __name:=bag_recorder $topics >"$out/bag_recorder.log" 2>&1 &
  bag_pid=$!
  "$py" - $topics <<'EOF' || { echo "run_scenario: rosbag record did not start; see $out/bag_recorder.log" >&2; exit 1; }
import os, sys, xmlrpc.client
from drvs.testing.harness import wait_for
def subscribed():
    with xmlrpc.client.ServerProxy(os.environ['ROS_MASTER_URI']) as master:
        _, _, (_, subscribers, _) = master.getSystemState('/run_scenario')
    nodes = dict(subscribers)
    return all('/bag_recorder' in nodes.get(topic, ()) for topic in sys.argv[1:])
wait_for(subscribed, 20.0, 'rosbag record to subscribe', interval=0.1)
EOF
fi

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
if [ $rviz -eq 1 ]; then
  start rviz rviz -d "$root/rviz/drvs.rviz"
fi
start recorder "$py" "$root/nodes/scenario_recorder" __name:=scenario_recorder _world:="$world" _out:="$out"
recorder_pid=${pids[-1]}
if [ $stay -eq 0 ]; then
  start robot "$py" "$root/nodes/blind_robot" __name:=robot _world:="$world" _once:=true
  robot_pid=${pids[-1]}
else
  # The robot stays up after it is done, so its callback service is there to be
  # called by hand; a watcher of its status ends the wait: 0 arrived, 1 failed.
  start robot "$py" "$root/nodes/blind_robot" __name:=robot _world:="$world"
  start robot_done "$py" "$root/scripts/wait_robot_done.py"
  robot_pid=${pids[-1]}
fi

echo "run_scenario: $(basename "$world") with ${cameras// /, } ($source); logs in $out"
started=$SECONDS
result=timeout
while [ $((SECONDS - started)) -lt "${timeout%.*}" ]; do
  if ! kill -0 "$robot_pid" 2>/dev/null; then
    if wait "$robot_pid"; then result=reached; else result=failed; fi
    break
  fi
  for i in "${!pids[@]}"; do
    # Closing the RViz window is the user's choice, not a crash.
    if ! kill -0 "${pids[$i]}" 2>/dev/null && [ "${pids[$i]}" != "$robot_pid" ] && [ "${names[$i]}" != rviz ]; then
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
  echo "run_scenario: robot $result; DRVS and the robot keep running at $ROS_MASTER_URI until Ctrl-C"
  while true; do sleep 1; done
fi
stop_all

case $result in
  reached) echo "run_scenario: the robot reached the station after $finished s" ;;
  failed) echo "run_scenario: the robot failed: $(tail -n 3 "$out/robot.log" | tr '\n' ' ')" >&2 ;;
  timeout) echo "run_scenario: timed out after $timeout s" >&2 ;;
esac
[ -f "$out/summary.json" ] && echo "run_scenario: summary $out/summary.json, picture $out/run.png"
[ -f "$out/run.bag" ] && [ $record -eq 1 ] && echo "run_scenario: bag $out/run.bag (nodes/drvs_report $out/run.bag)"
[ "$result" = reached ]
