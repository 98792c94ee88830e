#!/usr/bin/env bash
# One-command, idempotent setup of dcuscope on Debian 12: system packages (GStreamer 1.22,
# Python GI overrides, RTSP server, Chromium for the UI tests, linuxptp and Prometheus for the
# clock and metrics tests, PostgreSQL for the shared store's, Redis for the relays' live
# fan-out, sslscan for the TLS cipher test), a venv that sees Debian's PyGObject, the project in editable mode with the tested
# versions of constraints.txt, the native probe library, the relay's compiled merge, and the UI's pinned front-end packages. Fast (~1 s) when all is in place.
set -euo pipefail
cd "$(dirname "$0")/.."

APT_PACKAGES=(
  python3-gi python3-gst-1.0 gir1.2-gstreamer-1.0 gir1.2-gst-plugins-base-1.0
  gstreamer1.0-plugins-base gstreamer1.0-plugins-good gstreamer1.0-plugins-ugly
  gstreamer1.0-plugins-bad gstreamer1.0-libav gstreamer1.0-tools gstreamer1.0-python3-plugin-loader
  gir1.2-gst-rtsp-server-1.0 libgstreamer1.0-dev libgstreamer-plugins-base1.0-dev
  pkg-config gcc python3-venv python3-dev chromium iproute2 iptables linuxptp prometheus postgresql redis-server
  sslscan
)
# The test suite's cross-compile check (tests/test_portability.py): the native library built for
# aarch64 (Jetson) against Debian's arm64 GStreamer headers, beside the host's (multiarch).
CROSS_PACKAGES=(gcc-aarch64-linux-gnu libc6-dev-arm64-cross libgstreamer1.0-dev:arm64)
VENV=.venv
STAMPS=$VENV/.stamps

say() { printf '\033[1msetup:\033[0m %s\n' "$*"; }

missing=()
for pkg in "${APT_PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if ! command -v npm >/dev/null 2>&1; then missing+=(npm); fi
for pkg in "${CROSS_PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if [ ${#missing[@]} -gt 0 ]; then
  say "installing Debian packages: ${missing[*]}"
  SUDO=""
  if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
  export DEBIAN_FRONTEND=noninteractive
  if ! dpkg --print-foreign-architectures | grep -qx arm64; then
    say "adding Debian's arm64 architecture (multiarch) for the aarch64 cross-compile check"
    $SUDO dpkg --add-architecture arm64
  fi
  $SUDO apt-get update -qq
  $SUDO apt-get install -y -qq "${missing[@]}" >/dev/null
fi

if [ ! -x "$VENV/bin/python" ]; then
  say "creating $VENV (Debian's python3, with system site-packages for gi and Gst overrides)"
  /usr/bin/python3 -m venv --system-site-packages "$VENV"
fi
mkdir -p "$STAMPS"

deps_hash=$(cat pyproject.toml setup.py constraints.txt | sha256sum | cut -c1-16)
if [ ! -f "$STAMPS/pip-$deps_hash" ]; then
  say "installing dcuscope and its Python dependencies into $VENV"
  log=$STAMPS/pip.log
  if ! { "$VENV/bin/python" -m pip install -q --upgrade pip && "$VENV/bin/python" -m pip install -q -c constraints.txt -e '.[pipeline,dev,plot]'; } >"$log" 2>&1; then
    cat "$log" >&2
    say "pip install failed (log above)"
    exit 1
  fi
  "$VENV/bin/python" -c "import gi, numpy, cv2, onnxruntime, socketio, yaml, prometheus_client, opentelemetry.sdk, psycopg, matplotlib; gi.require_version('Gst', '1.0')"
  rm -f "$STAMPS"/pip-*
  touch "$STAMPS/pip-$deps_hash"
fi

"$VENV/bin/python" -m dcuscope.probes.capture.native build >/dev/null || say "warning: native probes not built; Python probes will be used (slower)"
"$VENV/bin/python" -m dcuscope.model.compiled build >/dev/null || say "warning: the compiled core not built; relays and offline tools will run its numpy reference (slower)"

if [ -f dcuscope/ui/package-lock.json ]; then
  ui_hash=$(sha256sum dcuscope/ui/package-lock.json | cut -c1-16)
  if [ ! -f "$STAMPS/ui-$ui_hash" ] || [ ! -d dcuscope/ui/static/vendor ]; then
    say "installing the UI's pinned front-end packages (npm ci)"
    npm ci --prefix dcuscope/ui --silent --no-audit --no-fund
    "$VENV/bin/python" -m dcuscope.ui.vendor
    rm -f "$STAMPS"/ui-*
    touch "$STAMPS/ui-$ui_hash"
  fi
fi
say "ready"
