#!/usr/bin/env bash
# Run one DRVS scenario end to end, without roslaunch.
#
#   scripts/run_scenario.sh WORLD [--timeout S] [--out DIR] [--external-master] [--stay]
#                                 [--camera-source render|topic] [--rviz] [--record]
#   scripts/run_scenario.sh --help
#
# Starts a private rosmaster on a free port (or, with --external-master, uses
# the environment's ROS_MASTER_URI), then drvs_server, world_sim, one
# vision_system per camera of WORLD, the scenario recorder and blind_robot, each
# a plain background process with its log in DIR (default out/<world name>).
# Waits until the robot reaches the station, fails, or the timeout (default 120 s)
# passes, showing its progress (state, distance to goal, re-plans, elapsed time:
# one updating line on a terminal, a plain line every 5 s and on each change of
# state otherwise); then stops everything it started (also on Ctrl-C) and leaves
# DIR/summary.json and DIR/run.png. Exits 0 only if the robot reached the station.
# Every process it starts is listed in DIR/pids (PID PGID START NAME) while it
# runs, so that scripts/stop_scenario.sh DIR stops them if this script is killed;
# a second run into the same DIR is refused while one is there.
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
stop_script=$(dirname "$0")/stop_scenario.sh  # as the user called this one, for messages
synopsis="usage: $0 WORLD [--timeout S] [--out DIR] [--external-master] [--stay] [--camera-source render|topic] [--rviz] [--record]"
help() {
  cat <<EOF
$synopsis
Run one DRVS scenario: a ROS master, drvs_server, world_sim, one vision_system per camera
of WORLD, the scenario recorder and blind_robot; stop them all at the end.
  WORLD                  the world file, e.g. worlds/localisation.yaml
  --timeout S            give up after S seconds (default 120)
  --out DIR              logs, summary.json, trace.json, run.png and pids there (default out/<world name>)
  --external-master      use the master at \$ROS_MASTER_URI (default http://127.0.0.1:11311), not a private one
  --stay                 keep DRVS and the robot running after the robot is done, until Ctrl-C
  --camera-source SOURCE render: each vision system renders its own view (default); topic: a sim_camera
                         per camera publishes images, CameraInfo and tf, which its vision system reads
  --rviz                 open RViz on the run with rviz/drvs.rviz (needs a display)
  --record               record the run's topics into DIR/run.bag (drvs_report DIR/run.bag replays it)
  -h, --help             print this help and exit
Stop it with Ctrl-C; if this script was killed, $stop_script DIR stops what it started.
Exit code: 0 the robot reached the station; 1 it failed, timed out or a node crashed;
2 a usage error, no master at \$ROS_MASTER_URI, or DIR in use by another run; 130 interrupted.
EOF
}
usage() {  # a usage error: the synopsis on stderr, exit 2
  echo "$synopsis" >&2
  echo "($0 --help describes the options)" >&2
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
    -h|--help) help; exit 0 ;;
    -*) echo "run_scenario: unknown option $1" >&2; usage ;;
    *) [ -z "$world" ] || usage; world=$1; shift ;;
  esac
done
[ -n "$world" ] || usage
[ -f "$world" ] || { echo "run_scenario: world file $world not found" >&2; exit 2; }
[[ "$timeout" =~ ^[0-9]+([.][0-9]+)?$ ]] || { echo "run_scenario: --timeout needs seconds, got $timeout" >&2; exit 2; }
[[ "$source" =~ ^(render|topic)$ ]] || { echo "run_scenario: --camera-source is render or topic, got $source" >&2; exit 2; }
[ -x "$root/.venv/bin/python" ] || { echo "run_scenario: no .venv: run scripts/setup.sh (or make demo) first" >&2; exit 2; }
# Every problem of the world file at once, before anything starts (nodes/drvs_check_world).
checked=$("$root/.venv/bin/python" "$root/nodes/drvs_check_world" "$world" 2>&1) || { echo "$checked" >&2; exit 2; }
if [ $rviz -eq 1 ]; then
  command -v rviz >/dev/null || bash "$root/scripts/setup.sh" --rviz || { echo "run_scenario: --rviz: installing rviz failed" >&2; exit 2; }
  [ -n "${DISPLAY:-}" ] || { echo "run_scenario: --rviz needs a display, and DISPLAY is not set" >&2; exit 2; }
fi

world=$(cd "$(dirname "$world")" && pwd)/$(basename "$world")
out=${out:-$root/out/$(basename "$world" .yaml)}
mkdir -p "$out"
out=$(cd "$out" && pwd)

# DIR/pids: every process this run starts (PID PGID START NAME, START its start time in
# /proc/PID/stat), for scripts/stop_scenario.sh. A run whose processes still run keeps DIR;
# a stale list is replaced. The lock on DIR makes checking and claiming one step.
pidfile=$out/pids
exec 8<"$out"
flock 8
running=$(bash "$root/scripts/stop_scenario.sh" --list "$out")
if [ -n "$running" ]; then
  script=$(grep -m1 ' run_scenario$' <<<"$running" || true)
  if [ -n "$script" ]; then
    echo "run_scenario: $out is in use by another run (run_scenario pid ${script%% *}); stop it with Ctrl-C there, or $stop_script $out" >&2
  else
    read -r pid name <<<"$running"
    echo "run_scenario: $out is in use: a killed run left $(wc -l <<<"$running") process(es) running ($name pid $pid, ...); stop them with $stop_script $out" >&2
  fi
  exit 2
fi
read -r stat </proc/$$/stat
read -r -a fields <<<"${stat##*) }"
group=${fields[2]}  # this script's process group, which its nodes share (Ctrl-C reaches them all)
echo "# run_scenario.sh: PID PGID START NAME of every process of the run in $out" >"$pidfile"
note_pid() {  # note_pid NAME PID [PGID]: its line in DIR/pids
  local stat fields
  read -r stat 2>/dev/null <"/proc/$2/stat" || return 0  # gone already: nothing to stop
  read -r -a fields <<<"${stat##*) }"
  echo "$2 ${3:-$group} ${fields[19]} $1" >>"$pidfile"
}
note_pid run_scenario $$
exec 8<&-

tty=0
[ ! -t 1 ] || tty=1  # the progress line is redrawn in place on a terminal only
pids=() names=()
stop_all() {  # stop every process of the run (scripts/stop_scenario.sh: newest first, the master last)
  trap - EXIT INT TERM HUP
  bash "$root/scripts/stop_scenario.sh" --quiet "$out" || true
  wait 2>/dev/null || true
}
trap stop_all EXIT
trap '[ $tty -eq 0 ] || echo; echo "run_scenario: interrupted" >&2; stop_all; exit 130' INT TERM HUP

master_given=${ROS_MASTER_URI:-}
if [ $external -eq 0 ]; then unset ROS_MASTER_URI; fi
# shellcheck source=scripts/env.sh
source "$root/scripts/env.sh"
py="$root/.venv/bin/python"
export PYTHONUNBUFFERED=1

master_answers() {  # master_answers SECONDS: whether the master at $ROS_MASTER_URI answers by then
  "$py" - "$1" <<'EOF'
import http.client, os, socket, sys, time, xmlrpc.client
from xml.parsers.expat import ExpatError

socket.setdefaulttimeout(1.0)
deadline = time.monotonic() + float(sys.argv[1])
while True:
    try:
        with xmlrpc.client.ServerProxy(os.environ['ROS_MASTER_URI']) as master:
            answered = master.getPid('/run_scenario')[0] == 1
    except (OSError, ValueError, http.client.HTTPException, xmlrpc.client.Error, ExpatError):
        answered = False  # not (yet) a master there
    if answered or time.monotonic() >= deadline:
        sys.exit(0 if answered else 1)
    time.sleep(0.1)
EOF
}
if [ $external -eq 1 ] && ! master_answers 3; then
  [ -n "$master_given" ] || note=" (ROS_MASTER_URI is not set: scripts/env.sh's default)"
  echo "run_scenario: --external-master: no ROS master answers at $ROS_MASTER_URI${note:-}; start roscore there, or point ROS_MASTER_URI at a running master (without --external-master this script starts its own)" >&2
  exit 2
fi

rm -f "$out"/*.log "$out"/summary.json "$out"/run.png "$out"/status.line
[ $record -eq 0 ] || rm -f "$out"/run.bag "$out"/run.bag.active

start() {  # start NAME COMMAND...: a background process logging to $out/NAME.log, listed in DIR/pids
  local name=$1; shift
  "$@" >"$out/$name.log" 2>&1 &
  pids+=($!) names+=("$name")
  note_pid "$name" $!
}

if [ $external -eq 0 ]; then
  port=$("$py" -c 'from drvs.testing.harness import free_port; print(free_port())')
  export ROS_MASTER_URI="http://127.0.0.1:$port/"
  export ROS_HOME="$out/ros_home" ROS_LOG_DIR="$out/ros_log"
  start rosmaster rosmaster --core -p "$port"
  master_answers 20 || { echo "run_scenario: the private rosmaster on port $port does not answer; see $out/rosmaster.log" >&2; exit 1; }
fi
echo "run_scenario: stop with Ctrl-C, or $stop_script $out if this script is killed"

cameras=$("$py" -c 'import sys; from drvs.world import load_world
print(" ".join(c.name for c in load_world(sys.argv[1]).vision_systems))' "$world")

if [ $record -eq 1 ]; then
  # Listed in DIR/pids as bag_recorder: stopped after every node. Ready once it subscribes to every topic.
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
  note_pid bag_recorder $! $!
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
shown_state="" shown_at=-5
while [ $((SECONDS - started)) -lt "${timeout%.*}" ]; do
  if ! kill -0 "$robot_pid" 2>/dev/null; then
    if wait "$robot_pid"; then result=reached; else result=failed; fi
    break
  fi
  for i in "${!pids[@]}"; do
    # Closing the RViz window is the user's choice, not a crash.
    if ! kill -0 "${pids[$i]}" 2>/dev/null && [ "${pids[$i]}" != "$robot_pid" ] && [ "${names[$i]}" != rviz ]; then
      [ $tty -eq 0 ] || echo
      echo "run_scenario: ${names[$i]} exited early; see $out/${names[$i]}.log" >&2
      result=crashed; break 2
    fi
  done
  line=$(cat "$out/status.line" 2>/dev/null || echo "state starting")
  elapsed=$((SECONDS - started))
  if [ $tty -eq 1 ]; then
    printf '\r\033[K%s | elapsed %3ds' "$line" $elapsed
  elif [ "${line%% |*}" != "$shown_state" ] || [ $elapsed -ge $((shown_at + 5)) ]; then
    # Not a terminal (a log file, a pipe): a plain line every 5 s and on each change of state.
    echo "run_scenario: $line | elapsed ${elapsed}s"
    shown_state=${line%% |*} shown_at=$elapsed
  fi
  sleep 0.5
done
[ $tty -eq 0 ] || printf '\r\033[K'
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
