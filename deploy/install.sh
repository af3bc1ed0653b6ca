#!/usr/bin/env bash
# Installs mfvs on a fresh Debian 12 (bookworm) machine or container:
#   - system packages: Python 3.11 with venv, EGL/Mesa for headless MuJoCo rendering (MUJOCO_GL=egl), libusb-1.0 for
#     Kinova's SDK, Chromium and its chromedriver for the console's browser tests;
#   - a virtual environment in .venv with mfvs (editable) and its test dependencies;
#   - the `mfvs` command on PATH (a link in /usr/local/bin as root, else ~/.local/bin), to this checkout's.
# Re-running it is safe. Environment: PYTHON (default python3), MFVS_SKIP_APT=1 to skip the system packages,
# MFVS_BIN_DIR to choose where the `mfvs` link goes (`none`: no link; CI passes a throwaway directory, so that a
# clone it deletes afterwards does not leave the machine's `mfvs` pointing at nothing). A link to another
# checkout is replaced with a line saying which; a file that is not a link is left alone.
set -euo pipefail
cd "$(dirname "$0")/.."
root=$(pwd)

apt_packages=(
    python3 python3-venv python3-pip
    # headless OpenGL through EGL on Mesa (llvmpipe on machines without a GPU)
    libegl1 libegl-mesa0 libgl1-mesa-dri libgles2 libopengl0 libglx-mesa0
    # Kinova's SDK (robot_gateway's kinova_sdk backend): its USB comm layer needs libusb-1.0
    libusb-1.0-0
    # the tests build a stand-in for Kinova's SDK library (tests/services/robot_gateway/fake_kinova_sdk) to test the
    # ctypes backend, and compile Kinova's C++ headers to check the backend's structs and functions against them
    gcc g++ libc6-dev
    # the console's browser tests and benchmark: Debian's Chromium, headless, driven through its chromedriver
    # (Selenium); a font for the page's text
    chromium chromium-driver fonts-dejavu-core
)
if [[ "${MFVS_SKIP_APT:-0}" != 1 ]]; then
    sudo_cmd=()
    if [[ $(id -u) -ne 0 ]]; then sudo_cmd=(sudo); fi
    export DEBIAN_FRONTEND=noninteractive
    "${sudo_cmd[@]}" apt-get update -qq
    "${sudo_cmd[@]}" apt-get install -y -qq --no-install-recommends "${apt_packages[@]}" >/dev/null
fi

python=${PYTHON:-python3}
if [[ ! -x .venv/bin/python ]]; then
    "$python" -m venv .venv
fi
.venv/bin/python -m pip install --quiet --upgrade pip
.venv/bin/python -m pip install --quiet -e ".[test]"

bin_dir=${MFVS_BIN_DIR:-}
if [[ -z "$bin_dir" ]]; then
    if [[ $(id -u) -eq 0 ]]; then bin_dir=/usr/local/bin; else bin_dir="$HOME/.local/bin"; fi
fi
if [[ "$bin_dir" == none ]]; then
    echo "no mfvs link (MFVS_BIN_DIR=none): run $root/.venv/bin/mfvs"
else
    bash deploy/link_mfvs.sh "$bin_dir" "$root/.venv/bin/mfvs"
fi

MUJOCO_GL=egl .venv/bin/python - <<'PY'
import mujoco
model = mujoco.MjModel.from_xml_string("<mujoco><worldbody><light pos='0 0 1'/><geom size='.1'/></worldbody></mujoco>")
renderer = mujoco.Renderer(model, 8, 8)
renderer.update_scene(mujoco.MjData(model))
renderer.render()
renderer.close()
print("mfvs installed; headless MuJoCo rendering (EGL) works")
PY
echo "run the tests with: .venv/bin/python -m pytest"
