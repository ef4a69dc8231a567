#!/usr/bin/env bash
# Stop what a scripts/run_scenario.sh run into DIR started, from DIR/pids.
#
#   scripts/stop_scenario.sh [--list] [--quiet] DIR
#
# run_scenario.sh records every process it starts in DIR/pids, one line each,
# PID PGID START NAME, in start order, its own line (NAME run_scenario) first.
# START is the process's start time (/proc/PID/stat, field 22): a pid that the
# system has since given to another process is left alone.
#
# If the run's script still runs, it is asked to stop (SIGINT, as Ctrl-C) and
# cleans up itself. What a killed script (kill -9) left is stopped here: the
# nodes newest first, then the bag recorder, then the private rosmaster, each
# step SIGINT, then SIGTERM, then SIGKILL, with short deadlines; then whatever is
# left of the script's process group, if the script led one. Then DIR/pids is
# removed, the database of a --sites run (DIR/postgres names its folder: stopped with
# scripts/postgres.sh, then removed) and the network hosts of a --hosts run (DIR/hosts names
# their prefix: scripts/hosts.sh's hosts_cleanup). Says what it stopped; exits 0 also when
# nothing was running. run_scenario.sh stops its own processes through this script too.
set -euo pipefail

usage() {
  cat <<EOF
usage: $0 [--list] [--quiet] DIR
Stop every process that a scripts/run_scenario.sh run into DIR started (listed in DIR/pids),
also after the script itself was killed; exit 0, also when nothing was running.
  --list      only print the run's processes that still run (PID NAME), stop nothing
  --quiet     print nothing
  -h, --help  print this help
EOF
}

list=0 quiet=0 dir=""
while [ $# -gt 0 ]; do
  case "$1" in
    -h | --help) usage; exit 0 ;;
    --list) list=1; shift ;;
    --quiet) quiet=1; shift ;;
    -*) echo "stop_scenario: unknown option $1" >&2; usage >&2; exit 2 ;;
    *) [ -z "$dir" ] || { usage >&2; exit 2; }; dir=$1; shift ;;
  esac
done
[ -n "$dir" ] || { usage >&2; exit 2; }
file=$dir/pids
say() { [ $quiet -eq 1 ] || echo "stop_scenario: $*"; }

remove_database() {  # the database of a --sites run, once the servers are stopped; before its host goes
  local folder
  [ -f "$dir/postgres" ] || return 0
  read -r folder <"$dir/postgres"
  if [[ "$folder" == /tmp/drvs-sites.* ]] && [ -d "$folder" ]; then
    if [ -d "$folder/data" ]; then
      bash "$(dirname "${BASH_SOURCE[0]}")/postgres.sh" stop "$folder" 2>/dev/null || true
      cp "$folder/server.log" "$dir/postgres_server.log" 2>/dev/null || true
    fi
    rm -rf "$folder"
  fi
  rm -f "$dir/postgres"
  say "stopped the database in $folder and removed it"
}

remove_hosts() {  # the network namespaces of a --hosts run, once its processes are stopped
  local prefix
  [ -f "$dir/hosts" ] || return 0
  read -r prefix <"$dir/hosts"
  # shellcheck source=scripts/hosts.sh
  source "$(dirname "${BASH_SOURCE[0]}")/hosts.sh"
  HOSTS_PREFIX=$prefix hosts_cleanup
  rm -f "$dir/hosts"
  say "removed the network hosts $prefix-*"
}

if [ ! -f "$file" ]; then
  [ $list -eq 0 ] || exit 0
  if [ -f "$dir/hosts" ] || [ -f "$dir/postgres" ]; then remove_database; remove_hosts; else say "nothing was running: no $file"; fi
  exit 0
fi

started() {  # started PID: set start_time to its start time; fail if it is gone or a zombie
  local line fields  # builtins only: no fork, so that a group of processes is signalled at once
  read -r line 2>/dev/null <"/proc/$1/stat" || return 1
  read -r -a fields <<<"${line##*) }"
  [ "${fields[0]}" != Z ] || return 1
  start_time=${fields[19]}
}

runs() {  # runs PID START: the process recorded so still runs (same pid, same start time)
  started "$1" && [ "$start_time" = "$2" ]
}
alive() { runs "${pids[$1]}" "${starts[$1]}"; }  # alive INDEX

# The run's processes that still run, in start order.
pids=() groups=() starts=() names=() script_pid="" script_group=""
while read -r pid pgid start name; do
  [[ "$pid" =~ ^[0-9]+$ && "$pgid" =~ ^[0-9]+$ && "$start" =~ ^[0-9]+$ ]] || continue
  [ "$name" != run_scenario ] || script_pid=$pid script_group=$pgid
  runs "$pid" "$start" || continue
  pids+=("$pid") groups+=("$pgid") starts+=("$start") names+=("$name")
done <"$file"

if [ $list -eq 1 ]; then
  for i in "${!pids[@]}"; do echo "${pids[$i]} ${names[$i]}"; done
  exit 0
fi

signal() {  # signal SIG INDEX: the process, or its whole group if it leads one of its own
  local pid=${pids[$2]}
  if [ "${groups[$2]}" = "$pid" ] && kill -s "$1" -- "-$pid" 2>/dev/null; then return 0; fi
  kill -s "$1" "$pid" 2>/dev/null || true
}

ignores_int() {  # ignores_int INDEX: the process ignores SIGINT (as rosmaster started in the background does)
  local key mask
  while read -r key mask; do
    [ "$key" != SigIgn: ] || return $((0x$mask & 2 ? 0 : 1))
  done 2>/dev/null <"/proc/${pids[$1]}/status"
  return 1
}

stop() {  # stop INDEX...: SIGINT (a clean shutdown), then SIGTERM, then SIGKILL, each with a deadline
  local step sig i deadline sent left got=()
  for step in INT:5 TERM:3 KILL:2; do
    sig=${step%:*} sent=() left=0
    for i in "$@"; do
      alive "$i" || continue
      left=1
      [ "$sig" != INT ] || ! ignores_int "$i" || continue  # straight to SIGTERM
      [ -z "${got[$i]:-}" ] || say "${names[$i]} (pid ${pids[$i]}) did not stop on SIG${got[$i]}: sent SIG$sig"
      signal "$sig" "$i"
      sent+=("$i") got[i]=$sig
    done
    [ $left -eq 1 ] || return 0
    deadline=$((SECONDS + ${step#*:}))
    while [ ${#sent[@]} -gt 0 ] && [ $SECONDS -lt $deadline ]; do
      left=0
      for i in "${sent[@]}"; do alive "$i" && left=1; done
      [ $left -eq 1 ] || break
      sleep 0.1
    done
  done
}

nodes=() bag=() master=() stopped=()
for ((i = ${#pids[@]} - 1; i >= 0; i--)); do
  case ${names[$i]} in
    run_scenario)
      # A script that still runs stops its own run (unless it is the one calling).
      [ "${pids[$i]}" != "$PPID" ] || continue
      # SIGINT as Ctrl-C; SIGTERM (the same trap) if it was started ignoring SIGINT (cmd &).
      sig=INT
      ! ignores_int "$i" || sig=TERM
      say "run_scenario (pid ${pids[$i]}) still runs: asking it to stop (SIG$sig)"
      kill -s "$sig" "${pids[$i]}" 2>/dev/null || true
      for _ in $(seq 300); do alive "$i" || break; sleep 0.1; done
      stop "$i"
      stopped+=("run_scenario (pid ${pids[$i]})")
      ;;
    rosmaster | rosmaster_*) master+=("$i") ;;  # rosmaster_SITE: another site's (--sites)
    bag_recorder) bag+=("$i") ;;
    *) nodes+=("$i") ;;
  esac
done
# The nodes newest first; then the bag recorder, which so records them to their end and
# closes the bag; the master last.
for part in nodes bag master; do
  declare -n indices=$part
  [ ${#indices[@]} -eq 0 ] || stop "${indices[@]}"
  for i in "${indices[@]}"; do stopped+=("${names[$i]} (pid ${pids[$i]})"); done
  unset -n indices
done

# What is left of a killed script's own process group (a helper it was running). The
# group's number is not given to another process while one of its members lives.
if [ -n "$script_pid" ] && [ "$script_group" = "$script_pid" ] && ! started "$script_pid"; then
  members=0
  for pid in $(pgrep -g "$script_group" || true); do
    if started "$pid"; then members=$((members + 1)); fi  # not counting zombies
  done
  if [ "$members" -gt 0 ]; then
    kill -s TERM -- "-$script_group" 2>/dev/null || true
    sleep 0.5
    kill -s KILL -- "-$script_group" 2>/dev/null || true
    stopped+=("$members more of its process group $script_group")
  fi
fi

rm -f "$file"
remove_database
remove_hosts
if [ ${#stopped[@]} -eq 0 ]; then
  say "nothing was running for $dir; removed $file"
else
  list=$(printf ', %s' "${stopped[@]}")
  say "stopped ${list#, } in $dir"
fi
