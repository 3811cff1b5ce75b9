#!/usr/bin/env bash
# Installs labrig on a rig: setup (idempotent), then the release builds of every program into
# one folder (the `labrig` CLI finds its programs beside itself).
#
#   bash scripts/install.sh                    # into ~/.local/bin (LABRIG_PREFIX=/opt/labrig: /opt/labrig/bin)
#   LABRIG_INSTALL_EXTRAS=0 bash scripts/install.sh   # without the policy (libtorch), calibration (OpenCV) and dataset programs
#
# Release = Cargo's release profile (opt-level 3, line tables for backtraces). docs/install.md
# has the debug vs release figures; `labrig doctor` warns when it runs from a debug build.
set -euo pipefail
REPO_DIR="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$REPO_DIR"
bash scripts/setup.sh >/dev/null
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-${LABRIG_CACHE:-$HOME/.cache/labrig}/target}"
PREFIX="${LABRIG_PREFIX:-$HOME/.local}"
programs=(
    "labrig labrig" "labrig-sim-bridge labrig-sim" "labrig-franka labrig-franka" "labrig-gripper labrig-gripper"
    "labrig-cameras labrig-cameras" "labrig-quest-teleop labrig-teleop" "labrig-control labrig-control"
    "labrig-recorder labrig-recorder" "labrig-station labrig-station" "labrig-droid labrig-droid"
    "labrig-doctor labrig-doctor"
)
if [ "${LABRIG_INSTALL_EXTRAS:-1}" != 0 ]; then
    programs+=("labrig-policies labrig-policies" "labrig-policy-server labrig-policy"
        "labrig-calibration labrig-calibrate" "labrig-dataset labrig-dataset")
fi
args=()
for p in "${programs[@]}"; do
    read -r package bin <<<"$p"
    args+=(-p "$package" --bin "$bin")
done
echo "[install] cargo build --release (${#programs[@]} programs; cold: tens of minutes on 2 cores)" >&2
cargo build --release --locked "${args[@]}"
mkdir -p "$PREFIX/bin"
for p in "${programs[@]}"; do
    read -r _ bin <<<"$p"
    install -m 755 "$CARGO_TARGET_DIR/release/$bin" "$PREFIX/bin/$bin"
done
echo "[install] ${#programs[@]} programs in $PREFIX/bin; check the rig with: $PREFIX/bin/labrig doctor --rig launch_configs/real_droid.toml" >&2
