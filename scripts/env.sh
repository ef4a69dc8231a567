# Source me: `source scripts/env.sh`. Sets up a shell to talk to DRVS.
#
# - ROS_MASTER_URI: http://127.0.0.1:11311 unless already set;
# - ROS_HOSTNAME: 127.0.0.1 unless ROS_HOSTNAME or ROS_IP is set;
# - PATH: the project's venv first (run scripts/setup.sh to create it);
# - PYTHONPATH and ROS_PACKAGE_PATH: so Debian's /usr/bin/rosservice, rossrv and
#   rosmsg find the drvs types (rossrv via package.xml/msg/srv, rosservice via drvs.srv).
_drvs_root=$(cd "$(dirname "${BASH_SOURCE[0]:-$0}")/.." && pwd)
export ROS_MASTER_URI="${ROS_MASTER_URI:-http://127.0.0.1:11311}"
if [ -z "${ROS_HOSTNAME:-}" ] && [ -z "${ROS_IP:-}" ]; then
  export ROS_HOSTNAME=127.0.0.1
fi
case ":${PATH}:" in
  *":${_drvs_root}/.venv/bin:"*) ;;
  *) export PATH="${_drvs_root}/.venv/bin:${_drvs_root}/nodes:${PATH}" ;;
esac
case ":${PYTHONPATH:-}:" in
  *":${_drvs_root}:"*) ;;
  *) export PYTHONPATH="${_drvs_root}${PYTHONPATH:+:${PYTHONPATH}}" ;;
esac
case ":${ROS_PACKAGE_PATH:-}:" in
  *":${_drvs_root}:"*) ;;
  *) export ROS_PACKAGE_PATH="${_drvs_root}${ROS_PACKAGE_PATH:+:${ROS_PACKAGE_PATH}}" ;;
esac
if [ ! -d "${_drvs_root}/drvs/srv" ]; then
  echo "env.sh: drvs types are not generated yet: run scripts/setup.sh (or make test)" >&2
fi
unset _drvs_root
