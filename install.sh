#!/usr/bin/env bash
# Set up swimm on a fresh Debian/Ubuntu machine with Python 3.11+: the EGL/GL libraries MuJoCo renders with
# (apt-get, when they are missing) and this checkout with every service's dependencies and the dev tools (pip).
#
#   ./install.sh                 (from anywhere; it works from the repository root)
#   PYTHON=python3.11 ./install.sh
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")"

PYTHON=${PYTHON:-$(command -v python || command -v python3)}

# What MuJoCo's EGL backend loads: the GL vendor-neutral dispatch libraries and Mesa's EGL/GL drivers.
GL_PACKAGES=(libegl1 libegl-mesa0 libgl1 libgl1-mesa-dri libgles2)

missing_gl_packages() {
    command -v dpkg-query >/dev/null || return 0  # not Debian: nothing we know how to check
    local package
    for package in "${GL_PACKAGES[@]}"; do
        dpkg-query -W -f='${Status}' "$package" 2>/dev/null | grep -q "install ok installed" || echo "$package"
    done
}

install_gl_libraries() {
    local missing sudo=""
    mapfile -t missing < <(missing_gl_packages)
    if [ "${#missing[@]}" -eq 0 ]; then
        echo "EGL/GL libraries already installed"
        return 0
    fi
    if ! command -v apt-get >/dev/null; then
        echo "apt-get unavailable; rendering tests may fail without: ${missing[*]}" >&2
        return 0
    fi
    if [ "$(id -u)" -ne 0 ]; then
        if ! command -v sudo >/dev/null; then
            echo "not root and no sudo; rendering tests may fail without: ${missing[*]}" >&2
            return 0
        fi
        sudo=sudo
    fi
    echo "installing: ${missing[*]}"
    $sudo apt-get update -qq
    $sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}"
}

# True when this checkout is already pip-installed (editable) and the extras' heavy packages are importable.
# Re-running pip then changes nothing we need, and on a machine whose torch was installed without triton it
# would add triton, which crashes next to Mesa's EGL (see tests/conftest.py).
already_installed() {
    local location
    location=$("$PYTHON" -m pip show swimm 2>/dev/null | sed -n 's/^Editable project location: //p')
    [ -n "$location" ] && [ "$location" -ef . ] && "$PYTHON" -c '
import importlib.util, sys
extras = ("zenoh", "mujoco", "cv2", "torch", "stable_baselines3", "gymnasium", "pandas", "scipy", "onnx", "onnxruntime",
          "pytest_timeout", "ruff", "importlinter")
sys.exit(not all(importlib.util.find_spec(name) for name in extras))'
}

install_python_packages() {
    if already_installed; then
        echo "swimm (editable, from this checkout) and its dev extras are already installed"
        return 0
    fi
    # Debian's own python3 refuses pip installs outside a venv (PEP 668); a CI machine is throwaway.
    if [ -e "$("$PYTHON" -c 'import sysconfig; print(sysconfig.get_path("stdlib"))')/EXTERNALLY-MANAGED" ]; then
        export PIP_BREAK_SYSTEM_PACKAGES=1
    fi
    "$PYTHON" -m pip install --quiet --disable-pip-version-check -e '.[dev]'
}

install_gl_libraries
install_python_packages
echo "swimm is installed: try 'swimm --help'"
