#!/usr/bin/env bash
# Run one DRVS scenario end to end, without roslaunch.
#
#   scripts/run_scenario.sh WORLD [--timeout S] [--out DIR] [--external-master] [--stay]
#                                 [--camera-source render|topic|colour] [--requests poll|watch] [--rviz]
#                                 [--fused true|false] [--record] [--hosts] [--robot-link RATE]
#                                 [--gateway [--gateway-bind HOST:PORT]] [--sites]
#   scripts/run_scenario.sh --help
#
# Starts a private rosmaster on a free port (or, with --external-master, uses
# the environment's ROS_MASTER_URI), then world_sim, drvs_server, one
# vision_system per camera of WORLD, the scenario recorder and one blind_robot per
# robot of WORLD (__name:= the robot's name), each a plain background process with
# its log in DIR (default out/<world name>). Waits until every robot reached its
# station or failed, or the timeout passes (wall seconds; default 120 s divided by
# the world's real_time_factor), showing its progress (state, distance to goal,
# re-plans, elapsed time; with several robots how many are in each state: one
# updating line on a terminal, a plain line every 5 s and on each change of state
# otherwise); then stops everything it started (also on Ctrl-C), leaves
# DIR/summary.json and DIR/run.png and prints the run's figures (a row per robot
# and per camera, the server's totals). Exits 0 only if every robot reached its
# station without a collision, and names those that did not, or collided, otherwise.
# A world with real_time_factor below 1 runs on ROS simulated time: /use_sim_time
# is set true on the master before any node starts (false for any other world),
# and world_sim, which publishes /clock, starts first.
# Every process it starts is listed in DIR/pids (PID PGID START NAME) while it
# runs, so that scripts/stop_scenario.sh DIR stops them if this script is killed;
# a second run into the same DIR is refused while one is there.
# With --stay, DRVS (server, world_sim, vision systems) and the robots keep running
# after the robots are done, until Ctrl-C, so it can be explored by hand (see the README).
# With --camera-source topic, the simulation drives the vision systems like real
# cameras: one sim_camera per camera publishes its rendered colour and depth
# images, CameraInfo and tf, and each vision_system runs with _source:=topic on
# them (default: render, each vision system renders its own view on demand).
# --camera-source colour is topic with colour-only cameras: each vision_system reads
# the colour image alone (no _depth), so it cannot run elevation (worlds/depot_foreground.yaml).
# With --requests poll or watch, every robot runs with _requests:= that (default:
# the robot's own default, standing requests). With --fused true or false, every
# robot runs with _fused:= that (default: the robot's own default, fused answers).
# With --rviz, RViz opens on the run with rviz/drvs.rviz (needs a display and
# Debian's rviz: make rviz-setup installs it).
# With --gateway, drvs_gateway runs with DRVS (docs/gateway.md) on --gateway-bind (default
# 127.0.0.1:8080; with --hosts, port 8080 of host master), with a tokens file in DIR made for the
# run: the script prints the floor-plan page's URL and the run's token (also in DIR/gateway.token,
# readable by its owner only), which the page asks for.
# With --record, `rosbag record` writes the run to DIR/run.bag: started before
# the other nodes and stopped after them, it holds every DRVS topic (latched ones
# and tf too, so `rosbag play` drives RViz again) and the recorder's samples, from
# which `nodes/drvs_report DIR/run.bag` writes the same summary.json again.
# With --hosts (root only; scripts/hosts.sh), each part runs on a network host of
# its own, a Linux network namespace on a private bridge: the master and
# drvs_server on host master, world_sim and the recorder (and the bag recorder)
# on host sim, the vision systems in groups of CAMERAS_PER_HOST on hosts cameras1,
# cameras2, ..., each robot on a host named as it. Every namespace and link is
# removed on exit, also on Ctrl-C or failure (and by scripts/stop_scenario.sh DIR
# after a kill -9). --robot-link RATE (e.g. 2mbit) limits the first robot's host
# link to RATE both ways (tc tbf), as a robot on a slow wireless link.
# With --sites (root; network hosts as --hosts), a world whose cameras name their site runs as
# that many sites, each with its own master and drvs_server (~site), all servers on one private
# PostgreSQL cluster (scripts/postgres.sh, on host db; DIR/postgres names its folder). The first
# site (of the first camera) has the hosts of --hosts: master, sim, cameras1, ... and the robots;
# another site S has master_S (its master, its server and a drvs_site_link that copies
# /world_sim/poses, and /clock under simulated time, from the first site's master) and
# cameras_S1, .... On host master a drvs_site_link copies each other site's cameras' stats topics
# for the recorder.
set -euo pipefail

root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
stop_script=$(dirname "$0")/stop_scenario.sh  # as the user called this one, for messages
CAMERAS_PER_HOST=8
synopsis="usage: $0 WORLD [--timeout S] [--out DIR] [--external-master] [--stay] [--camera-source render|topic|colour] [--requests poll|watch] [--fused true|false] [--rviz] [--record] [--hosts] [--robot-link RATE] [--gateway [--gateway-bind HOST:PORT]] [--sites]"
help() {
  cat <<EOF
$synopsis
Run one DRVS scenario: a ROS master, world_sim, drvs_server, one vision_system per camera
of WORLD, the scenario recorder and one blind_robot per robot of WORLD; stop them all at the end.
  WORLD                  the world file, e.g. worlds/localisation.yaml
  --timeout S            give up after S wall-clock seconds (default 120 divided by the world's real_time_factor)
  --out DIR              logs, summary.json, trace.json, run.png and pids there (default out/<world name>)
  --external-master      use the master at \$ROS_MASTER_URI (default http://127.0.0.1:11311), not a private one
  --stay                 keep DRVS and the robots running after the robots are done, until Ctrl-C
  --camera-source SOURCE render: each vision system renders its own view (default); topic: a sim_camera
                         per camera publishes images, CameraInfo and tf, which its vision system reads;
                         colour: topic, but the vision systems read no depth (cameras without depth)
  --requests MODE        every robot asks DRVS by poll (one-shot requests) or watch (standing requests);
                         default: the robot's own default (watch)
  --fused true|false     every robot asks for fused answers (one callback per request or watch period)
                         or per-camera ones; default: the robot's own default (true)
  --rviz                 open RViz on the run with rviz/drvs.rviz (needs a display)
  --gateway              run drvs_gateway too (DRVS over HTTP, docs/gateway.md) and print the URL of its live
                         floor-plan page and the run's token (made for the run; also in DIR/gateway.token)
  --gateway-bind H:P     where the gateway listens (default 127.0.0.1:8080; with --hosts, port 8080 of host master)
  --record               record the run's topics into DIR/run.bag (drvs_report DIR/run.bag replays it)
  --hosts                every part on a network host of its own (Linux network namespaces; needs root)
  --robot-link RATE      with --hosts: limit the first robot's link to RATE both ways, e.g. 2mbit
  --sites                the world's sites (its cameras' site:) each with its own master and server, on
                         network hosts (as --hosts), the servers on one PostgreSQL database (needs root)
  -h, --help             print this help and exit
Stop it with Ctrl-C; if this script was killed, $stop_script DIR stops what it started.
Exit code: 0 every robot reached its station without a collision; 1 a robot failed or collided,
the run timed out or a node crashed; 2 a usage error, no master at \$ROS_MASTER_URI, DIR in use by another run, or no
network hosts possible with --hosts or --sites; 130 interrupted.
EOF
}
usage() {  # a usage error: the synopsis on stderr, exit 2
  echo "$synopsis" >&2
  echo "($0 --help describes the options)" >&2
  exit 2
}
fail() {  # fail MESSAGE: one line on stderr, exit 2 (before anything started)
  echo "run_scenario: $1" >&2
  exit 2
}

world="" timeout="" out="" external=0 stay=0 source=render requests="" fused="" rviz=0 record=0 hosts=0 link="" gateway=0 gateway_bind="" sites=0
while [ $# -gt 0 ]; do
  case "$1" in
    --timeout) [ $# -ge 2 ] || usage; timeout=$2; shift 2 ;;
    --out) [ $# -ge 2 ] || usage; out=$2; shift 2 ;;
    --external-master) external=1; shift ;;
    --stay) stay=1; shift ;;
    --rviz) rviz=1; shift ;;
    --record) record=1; shift ;;
    --gateway) gateway=1; shift ;;
    --gateway-bind) [ $# -ge 2 ] || usage; gateway_bind=$2; shift 2 ;;
    --camera-source) [ $# -ge 2 ] || usage; source=$2; shift 2 ;;
    --requests) [ $# -ge 2 ] || usage; requests=$2; shift 2 ;;
    --fused) [ $# -ge 2 ] || usage; fused=$2; shift 2 ;;
    --hosts) hosts=1; shift ;;
    --sites) sites=1 hosts=1; shift ;;
    --robot-link) [ $# -ge 2 ] || usage; link=$2; shift 2 ;;
    -h|--help) help; exit 0 ;;
    -*) echo "run_scenario: unknown option $1" >&2; usage ;;
    *) [ -z "$world" ] || usage; world=$1; shift ;;
  esac
done
[ -n "$world" ] || usage
[ -f "$world" ] || fail "world file $world not found"
[ -z "$timeout" ] || [[ "$timeout" =~ ^[0-9]+([.][0-9]+)?$ ]] || fail "--timeout needs seconds, got $timeout"
[[ "$source" =~ ^(render|topic|colour)$ ]] || fail "--camera-source is render, topic or colour, got $source"
[[ "$requests" =~ ^(|poll|watch)$ ]] || fail "--requests is poll or watch, got $requests"
[[ "$fused" =~ ^(|true|false)$ ]] || fail "--fused is true or false, got $fused"
[ -z "$link" ] || [ $hosts -eq 1 ] || fail "--robot-link needs --hosts"
[ -z "$gateway_bind" ] || [ $gateway -eq 1 ] || fail "--gateway-bind needs --gateway"
[ -z "$gateway_bind" ] || [[ "$gateway_bind" =~ ^(\[[0-9a-fA-F:]+\]|[^:]+):[0-9]+$ ]] || fail "--gateway-bind needs HOST:PORT, got $gateway_bind"
[ $sites -eq 0 ] || [ $external -eq 0 ] || fail "--sites runs a master per site: not with --external-master"
[ $hosts -eq 0 ] || [ $external -eq 0 ] || fail "--hosts runs its own master on host master: not with --external-master"
[ -x "$root/.venv/bin/python" ] || fail "no .venv: run scripts/setup.sh (or make demo) first"
# Every problem of the world file at once, before anything starts (nodes/drvs_check_world).
checked=$("$root/.venv/bin/python" "$root/nodes/drvs_check_world" "$world" 2>&1) || { echo "$checked" >&2; exit 2; }
if [ $rviz -eq 1 ]; then
  command -v rviz >/dev/null || bash "$root/scripts/setup.sh" --rviz || fail "--rviz: installing rviz failed"
  [ -n "${DISPLAY:-}" ] || fail "--rviz needs a display, and DISPLAY is not set"
fi
if [ $hosts -eq 1 ]; then
  # shellcheck source=scripts/hosts.sh
  source "$root/scripts/hosts.sh"
  reason=$(hosts_check) || fail "$([ $sites -eq 1 ] && echo --sites || echo --hosts): cannot make network hosts here: $reason"
fi

world=$(cd "$(dirname "$world")" && pwd)/$(basename "$world")
out=${out:-$root/out/$(basename "$world" .yaml)}
mkdir -p "$out"
out=$(cd "$out" && pwd)

# The world's cameras, robots, whether it runs on simulated time, and the default timeout.
facts=$("$root/.venv/bin/python" -c 'import math, sys
from drvs.sim.world_file import load_world
world = load_world(sys.argv[1])
print(" ".join(c.name for c in world.vision_systems))
print(" ".join(r.name for r in world.robots))
print(int(world.real_time_factor < 1))
print(math.ceil(120 / world.real_time_factor))
print(" ".join(dict.fromkeys(c.site for c in world.vision_systems if c.site)))
print(" ".join(c.site for c in world.vision_systems))' "$world")
{ read -r cameras; read -r robots; read -r sim_time; read -r default_timeout; read -r site_names; read -r camera_sites; } <<<"$facts"
[ $sites -eq 0 ] || [ -n "$site_names" ] \
  || fail "--sites: no camera of $world names its site (site: a, site: b, ...; worlds/README.md)"
timeout=${timeout:-$default_timeout}

# DIR/pids: every process this run starts (PID PGID START NAME, START its start time in
# /proc/PID/stat), for scripts/stop_scenario.sh. A run whose processes still run keeps DIR;
# a stale list is replaced. The lock on DIR makes checking and claiming one step.
pidfile=$out/pids
exec 8<"$out"
flock 8
running=$(bash "$root/scripts/stop_scenario.sh" --list "$out")
if [ -z "$running" ] && { [ -f "$out/hosts" ] || [ -f "$out/postgres" ]; }; then
  bash "$root/scripts/stop_scenario.sh" --quiet "$out"  # the network hosts a killed run left
elif [ -n "$running" ]; then
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
stop_all() {  # stop every process of the run and remove its hosts (scripts/stop_scenario.sh: newest first, the master last)
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

# The sites: with --sites the world's, the first one's (the first camera's) the site of the
# simulation, the robots, the recorders; without, one (main). Each camera's site and host.
# With --hosts: host master (the master, drvs_server, this script's helpers), host sim
# (world_sim, the recorders), hosts cameras1, cameras2, ... (CAMERAS_PER_HOST vision systems
# each) and a host per robot, named as it; with --sites, host db (the database) and for each
# further site S host master_S (its master, server and site link) and cameras_S1, ....
# DIR/hosts names them for scripts/stop_scenario.sh.
if [ $sites -eq 1 ]; then read -r first_site _ <<<"$site_names"; else first_site=main site_names=main; fi
declare -A site_of=() host_of=() site_count=()  # camera -> its site, its host; site -> cameras there so far
read -r -a each_site <<<"$camera_sites"
i=0
for camera in $cameras; do
  site=$first_site
  [ $sites -eq 0 ] || site=${each_site[$i]}
  count=${site_count[$site]:-0}
  group=$((count / CAMERAS_PER_HOST + 1))
  if [ "$site" = "$first_site" ]; then host_of[$camera]=cameras$group; else host_of[$camera]=cameras_$site$group; fi
  site_of[$camera]=$site site_count[$site]=$((count + 1)) i=$((i + 1))
done
at_master=()  # the words that run a command on host master (none without --hosts)
declare -A site_ip=()  # site -> the address of its master's host (--hosts)
if [ $hosts -eq 1 ]; then
  hosts_init "drvs$$" || exit 1
  echo "$HOSTS_PREFIX" >"$out/hosts"
  master_ip=$(hosts_add master) || exit 1
  site_ip[$first_site]=$master_ip
  hosts_add sim >/dev/null || exit 1
  if [ $sites -eq 1 ]; then
    db_ip=$(hosts_add db) || exit 1
    for site in $site_names; do
      [ "$site" = "$first_site" ] || site_ip[$site]=$(hosts_add "master_$site") || exit 1
    done
  fi
  for host in $(printf '%s\n' "${host_of[@]}" | sort -u); do hosts_add "$host" >/dev/null || exit 1; done
  for robot in $robots; do hosts_add "$robot" >/dev/null || exit 1; done
  [ -z "$link" ] || hosts_limit "${robots%% *}" "$link" || exit 1
  mapfile -t at_master < <(hosts_command master)
fi

master_answers() {  # master_answers SECONDS: whether the master at $ROS_MASTER_URI answers by then
  "${at_master[@]}" "$py" - "$1" <<'EOF'
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

start() {  # start NAME HOST COMMAND...: a background process (on HOST with --hosts) logging to $out/NAME.log, listed in DIR/pids
  local name=$1 host=$2 via=()
  shift 2
  [ $hosts -eq 0 ] || mapfile -t via < <(hosts_command "$host")
  "${via[@]}" "$@" >"$out/$name.log" 2>&1 &
  pids+=($!) names+=("$name")
  note_pid "$name" $!
}

if [ $external -eq 0 ]; then
  if [ $hosts -eq 1 ]; then
    port=11311 address=$master_ip  # alone on its host
  else
    port=$("$py" -c 'from drvs.testing.harness import free_port; print(free_port())') address=127.0.0.1
  fi
  export ROS_MASTER_URI="http://$address:$port/"
  export ROS_HOME="$out/ros_home" ROS_LOG_DIR="$out/ros_log"
  start rosmaster master rosmaster --core -p "$port"
  master_answers 20 || { echo "run_scenario: the private rosmaster on port $port does not answer; see $out/rosmaster.log" >&2; exit 1; }
fi
# Each site's master; another site's nodes log in DIR/ros_log_SITE.
declare -A master_of=([$first_site]=$ROS_MASTER_URI)
on_site() {  # on_site SITE COMMAND...: COMMAND (a function too) with SITE's ROS_MASTER_URI and ROS_LOG_DIR
  local site=$1
  shift
  if [ "$site" = "$first_site" ]; then "$@"; else ROS_MASTER_URI=${master_of[$site]} ROS_LOG_DIR=$out/ros_log_$site "$@"; fi
}
for site in $site_names; do
  [ "$site" != "$first_site" ] || continue
  master_of[$site]=http://${site_ip[$site]}:11311/
  on_site "$site" start "rosmaster_$site" "master_$site" rosmaster --core -p 11311
  on_site "$site" master_answers 20 \
    || { echo "run_scenario: site $site's rosmaster does not answer; see $out/rosmaster_$site.log" >&2; exit 1; }
done
echo "run_scenario: stop with Ctrl-C, or $stop_script $out if this script is killed"
# The world decides /use_sim_time (also on an external master a slower world's run had set),
# before any node starts: each reads it once, at its start.
for site in $site_names; do
  on_site "$site" "${at_master[@]}" "$py" -c 'import os, sys, xmlrpc.client
xmlrpc.client.ServerProxy(os.environ["ROS_MASTER_URI"]).setParam("/run_scenario", "/use_sim_time", sys.argv[1] == "1")' "$sim_time"
done
# --sites: one database for every site's server, a private cluster on host db (scripts/postgres.sh)
# in a folder of /tmp that its owner, the user drvs-pg, reaches; DIR/postgres names the folder, so
# that scripts/stop_scenario.sh stops the cluster and removes it.
server_args=()
if [ $sites -eq 1 ]; then
  pg_dir=$(mktemp -d /tmp/drvs-sites.XXXXXX)
  echo "$pg_dir" >"$out/postgres"
  dsn=$(hosts_exec db bash "$root/scripts/postgres.sh" start "$pg_dir" --listen "$db_ip/${HOSTS_SUBNET#*/}" 2>"$out/postgres.log" | tail -n 1) \
    || { echo "run_scenario: --sites: the database did not start; see $out/postgres.log" >&2; exit 1; }
  server_args=(_registry:="$dsn" _site:="$first_site")
fi

if [ $record -eq 1 ]; then
  # Listed in DIR/pids as bag_recorder: stopped after every node. Ready once it subscribes to every topic.
  topics="/drvs/registry /drvs/markers /drvs/stats /drvs/objects /world_sim/poses /world_sim/ground_truth
    /scenario_recorder/samples /diagnostics /tf /tf_static /rosout /clock"
  for robot in $robots; do topics+=" /$robot/status /$robot/path /$robot/map /$robot/pose /$robot/cmd_vel"; done
  for camera in $cameras; do topics+=" /$camera/stats"; done
  # The program `rosbag record` runs, started directly: SIGINT reaches it (not a wrapper
  # that fails on the SIGINT it finds ignored in a background job) and its end is the bag's.
  # In a session of its own, so that a Ctrl-C in the terminal reaches it only through stop_all.
  record_bin=$("$py" -c 'import roslib.packages; print((roslib.packages.find_node("rosbag", "record") or [""])[0])')
  [ -x "$record_bin" ] || { echo "run_scenario: --record needs Debian's python3-rosbag (scripts/setup.sh installs it)" >&2; exit 2; }
  at_sim=()
  [ $hosts -eq 0 ] || mapfile -t at_sim < <(hosts_command sim)
  # shellcheck disable=SC2086
  setsid "${at_sim[@]}" "$record_bin" -O "$out/run.bag" __name:=bag_recorder $topics >"$out/bag_recorder.log" 2>&1 &
  note_pid bag_recorder $! $!
  "${at_master[@]}" "$py" - $topics <<'EOF' || { echo "run_scenario: rosbag record did not start; see $out/bag_recorder.log" >&2; exit 1; }
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

# Colour-only cameras: foreground's reference, each camera's view of the empty floor, rendered
# as drvs_calibrate --reference would photograph it (learnt from the first frames, it would
# hold the obstacles standing there).
if [ "$source" = colour ]; then
  "$py" - "$world" "$out" <<'EOF' || fail "could not render the cameras' empty floor into $out"
import sys
from dataclasses import replace

import cv2

from drvs.sim.scene import Scene
from drvs.sim.world_file import load_world
from drvs.vision.camera import PinholeCamera

world = load_world(sys.argv[1])
with Scene(replace(world, robots=(), objects=())) as scene:
    for config in world.vision_systems:
        rgb = scene.render(PinholeCamera.from_config(config)).rgb
        cv2.imwrite(f'{sys.argv[2]}/reference_{config.name}.png', cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
EOF
fi

# world_sim first: under simulated time it drives the clock the others wait for.
start world_sim sim "$py" "$root/nodes/world_sim" __name:=world_sim _world:="$world"
start drvs_server master "$py" "$root/nodes/drvs_server" __name:=drvs "${server_args[@]}"
# Every other site: its server on the same database, and a site link that brings the simulation's
# topics its cameras render from (docs/nodes/drvs_site_link.md); on host master a link that brings
# its cameras' stats to the recorder.
copied=/world_sim/poses
[ "$sim_time" -eq 0 ] || copied+=,/clock
for site in $site_names; do
  [ "$site" != "$first_site" ] || continue
  on_site "$site" start "drvs_server_$site" "master_$site" \
    "$py" "$root/nodes/drvs_server" __name:=drvs _registry:="$dsn" _site:="$site"
  on_site "$site" start "site_link_$site" "master_$site" \
    "$py" "$root/nodes/drvs_site_link" __name:=site_link _master:="${master_of[$first_site]}" _topics:="$copied"
  stats=""
  for camera in $cameras; do [ "${site_of[$camera]}" != "$site" ] || stats+=,/$camera/stats; done
  start "site_link_from_$site" master "$py" "$root/nodes/drvs_site_link" __name:="site_link_from_$site" \
    _master:="${master_of[$site]}" _topics:="${stats#,}"
done
for camera in $cameras; do
  host=${host_of[$camera]} site=${site_of[$camera]}
  if [ "$source" != render ]; then
    depth=$([ "$source" = topic ] && echo true || echo false)
    on_site "$site" start "sim_$camera" "$host" \
      "$py" "$root/nodes/sim_camera" __name:="sim_$camera" _world:="$world" _cameras:="$camera"
    reference=$([ "$source" = colour ] && echo "$out/reference_$camera.png" || true)
    on_site "$site" start "$camera" "$host" \
      "$py" "$root/nodes/vision_system" __name:="$camera" _source:=topic _depth:=$depth _reference:="$reference" \
      image:="/$camera/image_raw" camera_info:="/$camera/camera_info" depth:="/$camera/depth/image_raw"
  else
    on_site "$site" start "$camera" "$host" \
      "$py" "$root/nodes/vision_system" __name:="$camera" _world:="$world"
  fi
done
# The case study starts once DRVS is up: every camera registered with the server (with --sites,
# those of every site, through its own server: the first site's server has them from the database).
"${at_master[@]}" "$py" - "$cameras" <<'EOF' || { echo "run_scenario: the vision systems did not register; see $out/vs*.log" >&2; exit 1; }
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
  start rviz master rviz -d "$root/rviz/drvs.rviz"
fi
if [ $gateway -eq 1 ]; then
  # A token made for this run: the page asks for it (docs/gateway.md, "The floor-plan page").
  [ -n "$gateway_bind" ] || { if [ $hosts -eq 1 ]; then gateway_bind=$master_ip:8080; else gateway_bind=127.0.0.1:8080; fi; }
  rm -f "$out/gateway-tokens.json" "$out/gateway.token"
  (umask 077 && "$py" "$root/nodes/drvs_token" add page --file "$out/gateway-tokens.json" >"$out/gateway.token" 2>"$out/drvs_token.log") \
    || { echo "run_scenario: --gateway: making a token failed" >&2; exit 1; }
  start drvs_gateway master "$py" "$root/nodes/drvs_gateway" __name:=drvs_gateway _bind:="$gateway_bind" \
    _tokens:="$out/gateway-tokens.json"
  gateway_url=http://$gateway_bind
  "${at_master[@]}" "$py" - "$gateway_url/v1/openapi.json" <<'EOF' || { echo "run_scenario: drvs_gateway did not answer at $gateway_url; see $out/drvs_gateway.log" >&2; exit 1; }
import sys, urllib.request
from drvs.testing.harness import wait_for
def answers():
    try:
        with urllib.request.urlopen(sys.argv[1], timeout=1) as response:
            return response.status == 200
    except OSError:
        return False
wait_for(answers, 20.0, 'drvs_gateway to answer', interval=0.2)
EOF
  echo "run_scenario: the floor plan: $gateway_url/ (token $(cat "$out/gateway.token"), also in $out/gateway.token)"
fi
start recorder sim "$py" "$root/nodes/scenario_recorder" __name:=scenario_recorder _world:="$world" _out:="$out"
recorder_pid=${pids[-1]}
robot_args=(_world:="$world")
[ -z "$requests" ] || robot_args+=(_requests:="$requests")
[ -z "$fused" ] || robot_args+=(_fused:="$fused")
[ $stay -eq 1 ] || robot_args+=(_once:=true)
robot_pids=()
for robot in $robots; do
  start "$robot" "$robot" "$py" "$root/nodes/blind_robot" __name:="$robot" "${robot_args[@]}"
  robot_pids+=("${pids[-1]}")
done
if [ $stay -eq 0 ]; then
  awaited=("${robot_pids[@]}")  # each exits when its robot is done: 0 arrived
else
  # The robots stay up after they are done, so that their callback services are there to be
  # called by hand; a watcher of their status ends the wait: 0 every one arrived, 1 not.
  # shellcheck disable=SC2086
  start robot_done sim "$py" "$root/scripts/wait_robot_done.py" $robots
  awaited=("${pids[-1]}")
fi

echo "run_scenario: $(basename "$world") with robots ${robots// /, } and cameras ${cameras// /, } ($source${requests:+, $requests requests}${fused:+, fused $fused}${link:+, the first robot on a $link link}); logs in $out"
if [ $sites -eq 1 ]; then
  described=()
  for site in $site_names; do
    here=""
    for camera in $cameras; do [ "${site_of[$camera]}" != "$site" ] || here+=", $camera"; done
    described+=("$site (master ${master_of[$site]}, cameras ${here#, })")
  done
  echo "run_scenario: sites $(printf '%s; ' "${described[@]}" | sed 's/; $//'); one database at host db ($db_ip)"
fi
started=$SECONDS
result=timeout
declare -A ended=()  # pid of an awaited process -> its exit code
shown_state="" shown_at=-5
while [ $((SECONDS - started)) -lt "${timeout%.*}" ]; do
  for pid in "${awaited[@]}"; do
    if [ -z "${ended[$pid]:-}" ] && ! kill -0 "$pid" 2>/dev/null; then
      code=0
      wait "$pid" || code=$?
      ended[$pid]=$code
    fi
  done
  if [ ${#ended[@]} -eq ${#awaited[@]} ]; then result=done; break; fi
  for i in "${!pids[@]}"; do
    # Closing the RViz window is the user's choice, not a crash; an awaited process ends.
    if ! kill -0 "${pids[$i]}" 2>/dev/null && [ "${names[$i]}" != rviz ] \
      && ! [[ " ${awaited[*]} " == *" ${pids[$i]} "* ]]; then
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
if [ -f "$out/summary.json" ]; then
  "$py" -c 'import json, sys
from drvs.sim.report import figures_table
print(figures_table(json.load(open(sys.argv[1]))))' "$out/summary.json" | sed 's/^/run_scenario: /'
fi
# Which robots did not reach their stations: from their own exit codes, or the watcher's lines.
not_done=() failed=()
if [ $stay -eq 0 ]; then
  i=0
  for robot in $robots; do
    code=${ended[${robot_pids[$i]}]:-}
    if [ -z "$code" ]; then not_done+=("$robot"); elif [ "$code" -ne 0 ]; then failed+=("$robot"); fi
    i=$((i + 1))
  done
elif [ "$result" = done ] && [ "${ended[${awaited[0]}]}" -ne 0 ]; then
  mapfile -t failed < <(cut -d' ' -f1 "$out/robot_done.log")
fi
[ "$result" != done ] || [ ${#failed[@]} -gt 0 ] || result=reached
[ "$result" != done ] || result=failed
# A collision fails a blind robot's mission, even when every robot reached its station.
collided=""
if [ -f "$out/summary.json" ]; then
  collided=$("$py" -c 'import json, sys
from drvs.sim.report import collision_failure
print(collision_failure(json.load(open(sys.argv[1]))))' "$out/summary.json")
fi
[ -z "$collided" ] || [ "$result" != reached ] || result=collided
if [ $stay -eq 1 ] && [ "$result" != crashed ]; then
  case $result in
    reached) outcome="every robot reached its station" ;;
    failed) outcome="did not reach the station: ${failed[*]}" ;;
    collided) outcome="every robot reached its station, with collisions: $collided" ;;
    *) outcome="timed out after $timeout s" ;;
  esac
  echo "run_scenario: $outcome; DRVS and the robots keep running at $ROS_MASTER_URI until Ctrl-C"
  while true; do sleep 1; done
fi
stop_all

[ "$result" != reached ] || echo "run_scenario: every robot reached its station after $finished s (${robots// /, })"
for robot in "${failed[@]}"; do
  if [ $stay -eq 0 ]; then
    echo "run_scenario: $robot failed: $(tail -n 3 "$out/$robot.log" | tr '\n' ' ')" >&2
  else
    echo "run_scenario: $(grep -m1 "^$robot " "$out/robot_done.log")" >&2
  fi
done
[ "$result" != timeout ] || echo "run_scenario: timed out after $timeout s${not_done:+; not done: ${not_done[*]}}" >&2
[ -z "$collided" ] || echo "run_scenario: $collided" >&2
[ -f "$out/summary.json" ] && echo "run_scenario: summary $out/summary.json, picture $out/run.png"
[ -f "$out/run.bag" ] && [ $record -eq 1 ] && echo "run_scenario: bag $out/run.bag (nodes/drvs_report $out/run.bag)"
[ "$result" = reached ]
