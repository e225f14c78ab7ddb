# shellcheck shell=bash
# Environment for running inclinometer_calib (core + ROS 2 Jazzy from PyPI wheels).
#
#   source scripts/env.sh        # from any directory; bash or zsh
#
# Prerequisite: scripts/setup.sh has been run (creates .venv and builds the messages into
# .ros_ws/install). Safe to source repeatedly. Sets:
#   - the venv activated (.venv)
#   - ROS_DISTRO=jazzy, RMW_IMPLEMENTATION=rmw_fastrtps_cpp
#   - ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST (always: no discovery traffic leaves this machine)
#   - AMENT_PREFIX_PATH / CMAKE_PREFIX_PATH: our colcon install prefix, then the venv
#   - LD_LIBRARY_PATH: our install's lib, the venv's lib and site-packages/ros_*.libs
#   - _ROS_WHEELS_BOOTSTRAP_COMPLETE=1 (the wheels' .pth hook then skips its re-exec of Python)
#   - PYTHONPATH=<repo root>:<install site-packages>, repo root FIRST, nothing else: core modules
#     come from the source tree, inclinometer_calib.msg/.srv from the install tree (merged by
#     pkgutil.extend_path in inclinometer_calib/__init__.py; see docs/packaging.md).
# A ROS_DOMAIN_ID already set is kept.

if [ -n "${BASH_SOURCE:-}" ]; then
    _ic_this="${BASH_SOURCE[0]}"
elif [ -n "${ZSH_VERSION:-}" ]; then
    # shellcheck disable=SC2296
    _ic_this="${(%):-%x}"
else
    _ic_this="$0"
fi
_ic_repo="$(cd "$(dirname "$_ic_this")/.." && pwd)"
_ic_venv="$_ic_repo/.venv"
_ic_install="$_ic_repo/.ros_ws/install/inclinometer_calib"

if [ ! -x "$_ic_venv/bin/python3" ]; then
    echo "scripts/env.sh: $_ic_venv does not exist; run: bash $_ic_repo/scripts/setup.sh" >&2
    unset _ic_this _ic_repo _ic_venv _ic_install
    return 1 2>/dev/null || exit 1
fi

# lib/python3.X of the venv, found without starting Python
_ic_pylib=""
for _ic_d in "$_ic_venv"/lib/python3.*; do
    if [ -d "$_ic_d/site-packages" ]; then _ic_pylib="$(basename "$_ic_d")"; fi
done
_ic_site="$_ic_venv/lib/$_ic_pylib/site-packages"

# prepend $2 to the colon list named $1 unless already present
_ic_prepend() {
    eval "_ic_cur=\${$1:-}"
    case ":$_ic_cur:" in
        *":$2:"*) ;;
        *) if [ -n "$_ic_cur" ]; then eval "export $1=\"\$2:\$_ic_cur\""; else eval "export $1=\"\$2\""; fi ;;
    esac
}

# venv (activate is idempotent; keep the prompt untouched in non-interactive shells)
# shellcheck disable=SC1091
. "$_ic_venv/bin/activate"

export ROS_VERSION=2
export ROS_PYTHON_VERSION=3
export ROS_DISTRO=jazzy
export RMW_IMPLEMENTATION=rmw_fastrtps_cpp
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export _ROS_WHEELS_BOOTSTRAP_COMPLETE=1

# library search path (the wheels' RPATHs are wrong after pip installs them)
for _ic_d in "$_ic_site"/ros_*.libs; do
    if [ -d "$_ic_d" ]; then _ic_prepend LD_LIBRARY_PATH "$_ic_d"; fi
done
_ic_prepend LD_LIBRARY_PATH "$_ic_venv/lib"
_ic_prepend AMENT_PREFIX_PATH "$_ic_venv"
_ic_prepend CMAKE_PREFIX_PATH "$_ic_venv"

_ic_install_site="$_ic_install/lib/$_ic_pylib/site-packages"
if [ -d "$_ic_install" ]; then
    _ic_prepend LD_LIBRARY_PATH "$_ic_install/lib"
    _ic_prepend AMENT_PREFIX_PATH "$_ic_install"
    _ic_prepend CMAKE_PREFIX_PATH "$_ic_install"
    export PYTHONPATH="$_ic_repo:$_ic_install_site"
else
    if [ -z "${_IC_SETUP_RUNNING:-}" ]; then
        echo "scripts/env.sh: warning: messages not built ($_ic_install missing); run scripts/setup.sh" >&2
    fi
    export PYTHONPATH="$_ic_repo"
fi

unset -f _ic_prepend
unset _ic_this _ic_repo _ic_venv _ic_install _ic_install_site _ic_pylib _ic_site _ic_d _ic_cur
