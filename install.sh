#!/usr/bin/env bash
# Set up swimm on a fresh Debian/Ubuntu machine with Python 3.11+: the EGL/GL libraries MuJoCo renders with
# (apt-get, when they are missing), then a virtual environment (.venv) holding this checkout with every
# service's dependencies and the dev tools (pip), and a `swimm` launcher on PATH.
#
#   ./install.sh                 (from anywhere; it works from the repository root)
#   PYTHON=python3.11 ./install.sh               the Python the environment is made with
#   SWIMM_VENV=/opt/swimm ./install.sh           the environment somewhere else (default: .venv here)
#   SWIMM_BIN_DIR=~/bin ./install.sh             where the launcher goes (default: /usr/local/bin as root,
#                                                else ~/.local/bin)
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

VENV=${SWIMM_VENV:-.venv}
VENV_PYTHON="$VENV/bin/python"

# True when the environment already holds this checkout (editable), installed with its present commands (an
# install made before the `swimm` entry point moved would run code that is gone), and the extras' heavy packages:
# re-running pip would then change nothing we need.
already_installed() {
    local location
    [ -x "$VENV_PYTHON" ] || return 1
    location=$("$VENV_PYTHON" -m pip show swimm 2>/dev/null | sed -n 's/^Editable project location: //p')
    [ -n "$location" ] && [ "$location" -ef . ] && "$VENV_PYTHON" -c '
import importlib.metadata, importlib.util, sys, tomllib
scripts = importlib.metadata.distribution("swimm").entry_points.select(group="console_scripts")
with open("pyproject.toml", "rb") as f:
    current = {script.name: script.value for script in scripts} == tomllib.load(f)["project"]["scripts"]
extras = ("zenoh", "mujoco", "cv2", "torch", "stable_baselines3", "gymnasium", "pandas", "scipy", "onnx", "onnxruntime",
          "pytest_timeout", "ruff", "importlinter")
sys.exit(not (current and all(importlib.util.find_spec(name) for name in extras)))'
}

install_python_packages() {
    if already_installed; then
        echo "swimm (editable, from this checkout) and its dev extras are already installed in $VENV"
        return 0
    fi
    if [ ! -x "$VENV_PYTHON" ]; then
        "$PYTHON" -m venv "$VENV" || {
            echo "cannot make a virtual environment with $PYTHON: on Debian/Ubuntu, apt-get install python3-venv" >&2
            return 1
        }
    fi
    "$VENV_PYTHON" -m pip install --quiet --disable-pip-version-check --upgrade pip
    "$VENV_PYTHON" -m pip install --quiet --disable-pip-version-check -e '.[dev]'
}

# `swimm` on PATH: a link to the environment's console script, which runs the environment's Python.
install_launcher() {
    local bin_dir=${SWIMM_BIN_DIR:-}
    if [ -z "$bin_dir" ]; then
        if [ "$(id -u)" -eq 0 ]; then bin_dir=/usr/local/bin; else bin_dir=$HOME/.local/bin; fi
    fi
    mkdir -p "$bin_dir"
    ln -sf "$(cd "$VENV" && pwd)/bin/swimm" "$bin_dir/swimm"
    echo "swimm launcher: $bin_dir/swimm -> $VENV/bin/swimm"
    case ":$PATH:" in
        *":$bin_dir:"*) ;;
        *) echo "note: $bin_dir is not on PATH; add it, or run $VENV/bin/swimm" ;;
    esac
}

install_gl_libraries
install_python_packages
install_launcher
echo "swimm is installed in $VENV: try 'swimm --help'; tests: $VENV/bin/python -m pytest"
