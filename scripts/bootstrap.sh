#!/usr/bin/env bash
# Set up everything walkstream needs on a fresh Debian machine: Mesa's EGL (headless
# OpenGL on llvmpipe when there is no GPU), a virtual environment, and the package.
# Idempotent: a second run only checks. Used by `make demo` and `make test`.
set -euo pipefail
cd "$(dirname "$0")/.."

need_apt=()
ldconfig -p | grep -q 'libEGL_mesa\.so' || need_apt+=(libegl-mesa0)
ldconfig -p | grep -q 'libEGL\.so\.1' || need_apt+=(libegl1)
ldconfig -p | grep -q 'libGL\.so\.1' || need_apt+=(libgl1)
ls /usr/lib/*/dri/swrast_dri.so >/dev/null 2>&1 || need_apt+=(libgl1-mesa-dri)
# A virtual X display for `walkstream client --window` without a screen (xvfb-run), and the window tests.
command -v Xvfb >/dev/null 2>&1 || need_apt+=(xvfb)
command -v xauth >/dev/null 2>&1 || need_apt+=(xauth)
ldconfig -p | grep -q 'libXtst\.so\.6' || need_apt+=(libxtst6)  # real X input events in the window tests
# The scale-out topology the fault tests start as native processes: Redis for session state, nginx in front.
command -v redis-server >/dev/null 2>&1 || need_apt+=(redis-server)
[ -x /usr/sbin/nginx ] || command -v nginx >/dev/null 2>&1 || need_apt+=(nginx-light)
command -v ip >/dev/null 2>&1 || need_apt+=(iproute2)
# The fleet page's browser test: Debian's chromium, headless, driven through chromedriver (selenium).
[ -x /usr/bin/chromium ] || need_apt+=(chromium)
[ -x /usr/bin/chromedriver ] || need_apt+=(chromium-driver)
# The kiosk's captions: DejaVu Sans, rasterised by FreeType (Pillow).
[ -f /usr/share/fonts/truetype/dejavu/DejaVuSans.ttf ] || need_apt+=(fonts-dejavu-core)
# systemd-analyze checks the kiosk's unit (deploy/walkstream-kiosk.service) in its test.
command -v systemd-analyze >/dev/null 2>&1 || need_apt+=(systemd)
if [ ${#need_apt[@]} -gt 0 ]; then
  echo "bootstrap: installing ${need_apt[*]} (Mesa EGL, Xvfb, Redis, nginx, chromium, systemd)" >&2
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need_apt[@]}" >/dev/null
fi

PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  echo "bootstrap: creating .venv" >&2
  "$PY" -m venv .venv
fi
stamp=.venv/.walkstream-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  echo "bootstrap: installing walkstream and its dependencies into .venv" >&2
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e '.[dev]'
  touch "$stamp"
fi
# Compile the selection kernels (numba) once into their cache, so no server or test process
# spends its first seconds compiling them.
.venv/bin/python -c "from server.select import kernels; kernels.warm_up() or print('bootstrap: numba kernels unavailable, the solvers use numpy', flush=True)"
