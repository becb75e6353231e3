#!/usr/bin/env bash
# Set up everything drivesim needs on a fresh Debian machine: system libraries, a venv, the package and its tests.
# Idempotent; `make demo` and `make test` run it on first use.
set -euo pipefail
VENV=${VENV:-.venv}
PYTHON=${PYTHON:-python3}

# libusb: `import open3d` needs it; EGL + Mesa: moderngl renders headless in the renderer tests;
# chromium: the eval report test opens the HTML report in a real headless browser.
debs=(libusb-1.0-0 libegl1 libegl-mesa0 libgl1-mesa-dri libgl1 chromium)
missing=()
for d in "${debs[@]}"; do dpkg -s "$d" >/dev/null 2>&1 || missing+=("$d"); done
if ((${#missing[@]})); then
  if [ "$(id -u)" = 0 ]; then
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null
  else
    echo "setup: please install the Debian packages: ${missing[*]} (sudo apt-get install ${missing[*]})" >&2
    exit 2
  fi
fi

[ -x "$VENV/bin/python" ] || "$PYTHON" -m venv "$VENV"
"$VENV/bin/python" -m pip install -q --upgrade pip >/dev/null
# torch first and pinned: the local CPU build of 2.13.0; pyproject caps torch below 2.14 so nothing pulls CUDA.
"$VENV/bin/python" -m pip install -q "torch==2.13.0"
# test: pytest, moderngl, ruff; ray: the Ray backend, so its tests run rather than skip.
"$VENV/bin/python" -m pip install -q -e ".[test,ray]"
