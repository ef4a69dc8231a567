# Separate network hosts on one machine: Linux network namespaces on a private bridge.
# A library: source it (scripts/run_scenario.sh --hosts, drvs/testing/netns.py), do not run it.
#
#   source scripts/hosts.sh
#   reason=$(hosts_check) || { echo "cannot make hosts: $reason" >&2; exit 2; }
#   trap 'stop_my_processes; hosts_cleanup' EXIT
#   trap 'exit 130' INT TERM HUP         # signals end the script through the EXIT trap
#   hosts_init [PREFIX]                  # sets HOSTS_PREFIX (default drvs$$) and HOSTS_SUBNET
#   master_ip=$(hosts_add master)        # namespace PREFIX-master, address 10.A.B.1
#   hosts_add robot1 >/dev/null
#   hosts_limit robot1 2mbit             # optional: a slow (wireless) link
#   export ROS_MASTER_URI=http://$master_ip:11311/
#   hosts_exec master rosmaster --core -p 11311 &
#   hosts_exec robot1 nodes/blind_robot __name:=robot1 &
#
# Layout: namespace PREFIX holds only the bridge br0; each host is namespace PREFIX-NAME with
# lo and eth0, one end of a veth pair whose other end (hN, N the host's number) is a port of
# br0. Nothing is created in the root namespace, whose links, addresses and routes stay as
# they were; the root namespace has no route to the hosts and the hosts have none out (no
# default route, no IPv6 address but lo's ::1): a host reaches exactly the other hosts'
# addresses. Hosts get 10.A.B.1, 10.A.B.2, ... in a random 10.A.B.0/24 that neither the root
# namespace nor any other namespace uses (two runs that pick the same one at the same moment
# still cannot meet: each has its own bridge).
#
# State lives in the kernel only (namespace names, br0's alias holds the subnet): each
# function can run in a subshell or a new bash with just HOSTS_PREFIX set, and
# `HOSTS_PREFIX=P hosts_cleanup` removes what a killed run left. Call hosts_add one at a
# time (numbers are taken from the bridge's ports). Every function returns non-zero with a
# one-line message on stderr, "hosts_FUNCTION: problem", on bad input or failure; safe
# under `set -euo pipefail`. Call hosts_init in the script itself, not in $(...): it sets
# HOSTS_PREFIX and HOSTS_SUBNET.
#
# Traps belong to the caller: the library sets none, since a script has one EXIT trap and
# the order matters. Stop the processes on the hosts first, then call hosts_cleanup (it
# kills with SIGKILL whatever still runs in a namespace of the prefix, because a namespace
# with a process in it lives on, and with it its links).

# Source once: a HOSTS_PREFIX from the environment must not make hosts_cleanup delete
# namespaces this script did not make.
unset HOSTS_PREFIX HOSTS_SUBNET

hosts_check() {  # hosts_check: return 0 if hosts can be made here, else print the reason (one line) and return 1
  local probe="drvsprobe$$r$RANDOM" error
  if ! command -v ip >/dev/null; then
    echo "the ip command (iproute2) is not installed"
    return 1
  fi
  if [ "$EUID" -ne 0 ]; then
    echo "network namespaces need root (running as uid $EUID)"
    return 1
  fi
  if ! error=$(ip netns add "$probe" 2>&1); then
    echo "cannot create a network namespace: ${error//$'\n'/ }"
    return 1
  fi
  error=$(printf 'link add br0 type bridge\nlink add h1 type veth peer name eth0\n' | ip -n "$probe" -b - 2>&1) \
    || error="cannot create a bridge and a veth pair in a namespace: ${error//$'\n'/ }"
  ip netns del "$probe"
  [ -z "$error" ] || { echo "$error"; return 1; }
}

hosts_init() {  # hosts_init [PREFIX]: the bridge namespace PREFIX on a free 10.A.B.0/24; sets HOSTS_PREFIX, HOSTS_SUBNET
  local prefix=${1:-drvs$$} used subnet tries ns error
  if ! [[ "$prefix" =~ ^[A-Za-z0-9_]{1,24}$ ]]; then
    echo "hosts_init: prefix '$prefix' must be 1 to 24 letters, digits or _ (it starts every namespace name: PREFIX-HOST)" >&2
    return 1
  fi
  if [ -n "$(_hosts_namespaces "$prefix")" ]; then
    echo "hosts_init: namespaces of prefix $prefix exist already (another run's? HOSTS_PREFIX=$prefix hosts_cleanup removes them)" >&2
    return 1
  fi
  used=$(for ns in $(ip netns list | cut -d' ' -f1); do ip -n "$ns" -4 -o addr show 2>/dev/null || true; done)
  for ((tries = 0; tries < 50; tries++)); do
    subnet=10.$((RANDOM % 256)).$((RANDOM % 256))
    # Free: no address of any namespace in it, and no route of the root namespace in or
    # around it but the default route.
    grep -q " inet ${subnet//./\\.}\\." <<<"$used" && continue
    [ -z "$(ip -4 route show table all root "$subnet.0/24")" ] || continue
    [ -z "$(ip -4 route show table all match "$subnet.0/24" | grep -v '^default ')" ] || continue
    break
  done
  if [ "$tries" -eq 50 ]; then
    echo "hosts_init: found no free 10.A.B.0/24 in 50 tries (ip -4 route show table all)" >&2
    return 1
  fi
  if ! error=$(ip netns add "$prefix" 2>&1); then
    echo "hosts_init: cannot create network namespace $prefix: ${error//$'\n'/ }" >&2
    return 1
  fi
  # addrgenmode before up, on a line of its own: otherwise br0 gets an IPv6 link-local address.
  if ! error=$(printf 'link add br0 type bridge\nlink set br0 addrgenmode none\nlink set br0 alias %s up\n' \
    "$subnet.0/24" | ip -n "$prefix" -b - 2>&1); then
    ip netns del "$prefix"
    echo "hosts_init: cannot create the bridge in namespace $prefix: ${error//$'\n'/ }" >&2
    return 1
  fi
  HOSTS_PREFIX=$prefix HOSTS_SUBNET=$subnet.0/24
}

hosts_add() {  # hosts_add NAME: host namespace PREFIX-NAME on the bridge; print its address
  local name=${1:-} links subnet number=1 ns error
  _hosts_ready hosts_add || return 1
  if ! [[ "$name" =~ ^[A-Za-z0-9_]{1,32}$ ]]; then
    echo "hosts_add: host name '$name' must be 1 to 32 letters, digits or _" >&2
    return 1
  fi
  ns=$HOSTS_PREFIX-$name
  if [ -e "/run/netns/$ns" ]; then
    echo "hosts_add: host $name exists already ($(hosts_ip "$name"))" >&2
    return 1
  fi
  links=$(ip -n "$HOSTS_PREFIX" -o link show)
  [[ "$links" =~ alias\ ([0-9.]+)\.0/24 ]] || { echo "hosts_add: bridge of $HOSTS_PREFIX has no subnet alias" >&2; return 1; }
  subnet=${BASH_REMATCH[1]}
  while [[ "$links" =~ (^|$'\n')[0-9]+:\ h$number@ ]]; do number=$((number + 1)); done
  [ "$number" -le 254 ] || { echo "hosts_add: $HOSTS_PREFIX has 254 hosts already, the most a /24 holds" >&2; return 1; }
  if ! error=$(ip netns add "$ns" 2>&1); then
    echo "hosts_add: cannot create network namespace $ns: ${error//$'\n'/ }" >&2
    return 1
  fi
  if ! error=$(printf 'link add h%s type veth peer name eth0 netns %s\nlink set h%s master br0 addrgenmode none up\n' \
    "$number" "$ns" "$number" | ip -n "$HOSTS_PREFIX" -b - 2>&1) \
    || ! error=$(printf 'link set lo up\naddr add %s/24 dev eth0\nlink set eth0 addrgenmode none up\n' \
      "$subnet.$number" | ip -n "$ns" -b - 2>&1); then
    ip netns del "$ns"
    echo "hosts_add: cannot connect host $name to the bridge: ${error//$'\n'/ }" >&2
    return 1
  fi
  echo "$subnet.$number"
}

hosts_ip() {  # hosts_ip NAME: print the host's address
  _hosts_ip hosts_ip "${1:-}"
}

hosts_limit() {  # hosts_limit NAME RATE: token bucket (tc tbf) at RATE (e.g. 2mbit) on the host's link, both directions
  local name=${1:-} rate=${2:-} number error
  if ! [[ "$rate" =~ ^[0-9]+([.][0-9]+)?(bit|kbit|mbit|gbit)$ ]]; then
    echo "hosts_limit: rate '$rate' must be a number with bit, kbit, mbit or gbit (e.g. 2mbit)" >&2
    return 1
  fi
  number=$(_hosts_ip hosts_limit "$name") || return 1
  number=${number##*.}
  # Each direction is a qdisc on the egress of one end of the veth pair: eth0 in the host
  # (what the host sends), hN at the bridge (what it receives); no ingress shaping (ifb)
  # needed. The bucket holds a few full packets; up to 200 ms of traffic queue, the rest
  # is dropped, as a saturated wireless link would.
  if ! error=$(tc -n "$HOSTS_PREFIX-$name" qdisc replace dev eth0 root tbf rate "$rate" burst 8kb latency 200ms 2>&1) \
    || ! error=$(tc -n "$HOSTS_PREFIX" qdisc replace dev "h$number" root tbf rate "$rate" burst 8kb latency 200ms 2>&1); then
    echo "hosts_limit: tc tbf on host $name: ${error//$'\n'/ }" >&2
    return 1
  fi
}

hosts_command() {  # hosts_command NAME: print, one per line, the words that run a command on the host
  _hosts_command hosts_command "${1:-}"
}

hosts_exec() {  # hosts_exec NAME COMMAND...: run COMMAND on the host (in a subshell or `&` job: exec it)
  local words
  words=$(_hosts_command hosts_exec "${1:-}") || return 1
  shift
  local -a prefix
  mapfile -t prefix <<<"$words"
  if [ "$BASHPID" != "$$" ]; then
    exec "${prefix[@]}" "$@"  # `hosts_exec ... &`: $! is the command's own pid
  fi
  "${prefix[@]}" "$@"
}

hosts_cleanup() {  # hosts_cleanup: delete every namespace of HOSTS_PREFIX (and so its links); idempotent
  local ns pids failed=0
  [ -n "${HOSTS_PREFIX:-}" ] || return 0
  for ns in $(_hosts_namespaces "$HOSTS_PREFIX"); do
    # A namespace lives on while a process is in it: the caller stops its processes
    # first; whatever is still there is killed, or its links would outlive the run.
    pids=$(ip netns pids "$ns" 2>/dev/null | tr '\n' ' ')
    if [ -n "$pids" ]; then
      echo "hosts_cleanup: killing processes still on host $ns: $pids" >&2
      # shellcheck disable=SC2086
      kill -KILL $pids 2>/dev/null || true
    fi
    ip netns del "$ns" || failed=1
  done
  [ "$failed" -eq 0 ] || { echo "hosts_cleanup: could not delete every namespace of $HOSTS_PREFIX" >&2; return 1; }
}

_hosts_ready() {  # _hosts_ready FUNCTION: fail unless hosts_init made the bridge of HOSTS_PREFIX
  if [ -z "${HOSTS_PREFIX:-}" ] || ! [ -e "/run/netns/$HOSTS_PREFIX" ]; then
    echo "$1: no bridge: call hosts_init first${HOSTS_PREFIX:+ (no namespace $HOSTS_PREFIX)}" >&2
    return 1
  fi
}

_hosts_namespaces() {  # _hosts_namespaces PREFIX: the namespaces of PREFIX, the bridge's last
  ip netns list | cut -d' ' -f1 | grep -E "^$1-" || true
  ip netns list | cut -d' ' -f1 | grep -x "$1" || true
}

_hosts_names() {  # _hosts_names: the hosts of HOSTS_PREFIX in alphabetical order, space-separated
  _hosts_namespaces "$HOSTS_PREFIX" | sed -n "s/^$HOSTS_PREFIX-//p" | sort | tr '\n' ' ' | sed 's/ $//'
}

_hosts_ip() {  # _hosts_ip FUNCTION NAME: print the host's address; FUNCTION names the caller in errors
  local addr
  _hosts_ready "$1" || return 1
  if [ -z "$2" ] || ! [ -e "/run/netns/$HOSTS_PREFIX-$2" ]; then
    echo "$1: no host '$2' (hosts: $(_hosts_names))" >&2
    return 1
  fi
  addr=$(ip -n "$HOSTS_PREFIX-$2" -4 -o addr show dev eth0)
  [[ "$addr" =~ inet\ ([0-9.]+)/ ]] || { echo "$1: host $2 has no address" >&2; return 1; }
  echo "${BASH_REMATCH[1]}"
}

_hosts_command() {  # _hosts_command FUNCTION NAME: the words of hosts_command
  local ip
  ip=$(_hosts_ip "$1" "$2") || return 1
  # ip netns exec and env exec(3) the command: it keeps their pid. ROS_HOSTNAME would win
  # over ROS_IP in ROS, so it goes; ROS_MASTER_URI is passed through as it is.
  printf '%s\n' ip netns exec "$HOSTS_PREFIX-$2" env -u ROS_HOSTNAME "ROS_IP=$ip"
}
