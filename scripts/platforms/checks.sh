# The checks of scripts/platforms.sh, one function a platform, sourced by it. Each prints its
# result's details on stdout (one line) and returns non-zero on failure; progress goes to fd 3 (the
# platform's log), and its table, if any, to $CACHE/logs/NAME.table.
BULLSEYE_APT="$GST_APT,python3"
TRIXIE_APT="$GST_APT,$PY_APT"
ARM64_APT="$GST_APT,$PY_APT"

# An unchanged app: 120 frames through converters, a scaler, a 4 ms identity and an encoder.
APP_CHAIN="videotestsrc num-buffers=120 ! video/x-raw,width=320,height=240,framerate=30/1 ! videoconvert ! \
video/x-raw,format=I420 ! videoscale ! video/x-raw,width=160,height=120 ! identity name=sleepy sleep-time=4000 ! \
jpegenc ! fakesink"

step() { echo "== $*" >&3; }
fail() { echo "$*"; return 1; }

# gst_version ROOT: GStreamer's version in a root filesystem (from its gst-launch-1.0).
gst_version() { in_root "$1" gst-launch-1.0 --gst-version 2>/dev/null | grep -oE '[0-9]+\.[0-9]+\.[0-9]+' | head -1; }

check_bullseye() {
  local root work lib
  step "root filesystem"
  root=$(rootfs bullseye bullseye amd64 "$BULLSEYE_APT") || fail "debootstrap of bullseye failed" || return
  work=$root/opt/dcuscope && rm -rf "$work" && mkdir -p "$work/out"
  cp -r "$CHECKOUT/probes/capture/c" "$work/c" && cp "$CHECKOUT/core/cbuild.py" "$work/"
  step "native library, against $(gst_version "$root")'s headers"
  in_root "$root" python3 /opt/dcuscope/cbuild.py /opt/dcuscope/c /opt/dcuscope/lib/libgstdcuscope.so >&3 2>&1 \
    || fail "the native library did not build against GStreamer $(gst_version "$root")" || return
  step "gst-launch-1.0 under dcuscope and latency tracers"
  in_root "$root" env GST_PLUGIN_PATH=/opt/dcuscope/lib \
    GST_TRACERS="dcuscope(node=BULLSEYE,trace=/opt/dcuscope/out/app.trace.jsonl);latency(flags=element)" \
    GST_DEBUG=GST_TRACER:7 GST_DEBUG_FILE=/opt/dcuscope/out/latency.log GST_DEBUG_NO_COLOR=1 \
    bash -c "gst-launch-1.0 -q $APP_CHAIN" >&3 2>&1 || fail "the traced gst-launch-1.0 app failed" || return
  step "this checkout's dcuscope stats against the latency tracer"
  local said
  said=$("$PY" scripts/platforms/latency_table.py "$work/out/app.trace.jsonl" "$work/out/latency.log" \
         "$CACHE/logs/bullseye.table") || fail "$said" || return
  echo "GStreamer $(gst_version "$root"): native library built there; $said"
}

# install_dcuscope ROOT WHAT: a venv at /opt/venv (seeing the system's PyGObject) with WHAT installed
# by pip, with the tested versions of constraints.txt. pip there trusts what this host trusts (its
# CA bundle: a proxy that re-signs TLS) and goes through this host's proxy, if any.
install_dcuscope() {
  local root=$1 what=$2 bundle=${PIP_CERT:-${SSL_CERT_FILE:-/etc/ssl/certs/ca-certificates.crt}}
  rm -rf "$root/opt/venv"
  cp "$CHECKOUT/constraints.txt" "$root/opt/constraints.txt"
  [ -f "$bundle" ] && cp -L "$bundle" "$root/opt/host-ca.crt"
  in_root "$root" python3 -m venv --system-site-packages /opt/venv >&3 2>&1 || return 1
  in_root "$root" env ${http_proxy:+http_proxy=$http_proxy} ${https_proxy:+https_proxy=$https_proxy} \
    ${no_proxy:+no_proxy=$no_proxy} $([ -f "$root/opt/host-ca.crt" ] && echo PIP_CERT=/opt/host-ca.crt) \
    /opt/venv/bin/pip install -q --disable-pip-version-check -c /opt/constraints.txt "$what" >&3 2>&1
}

# stored_check DB TRACE NODE: NODE's run in this host's relay store against its trace; sets SAID.
stored_check() {
  local db=$1 trace=$2 node=$3
  SAID=$("$PY" scripts/platforms/stored_vs_sent.py "$db" "$trace" "$node")
}

check_trixie() {
  local root work wheel started
  step "root filesystem"
  root=$(rootfs trixie trixie amd64 "$TRIXIE_APT") || fail "debootstrap of trixie failed" || return
  work=$root/opt/work && rm -rf "$work" && mkdir -p "$work"
  step "the wheel, built on this host"
  rm -rf "$CACHE/wheels" && mkdir -p "$CACHE/wheels"
  "$PY" -m pip wheel -q --no-deps -w "$CACHE/wheels" . >&3 2>&1 || fail "pip wheel failed on this host" || return
  wheel=$(basename "$CACHE"/wheels/dcuscope-*.whl) && cp "$CACHE/wheels/$wheel" "$root/opt/"
  step "pip install $wheel[pipeline] there"
  started=$SECONDS
  install_dcuscope "$root" "/opt/$wheel[pipeline]" || fail "pip install of the wheel failed there" || return
  local took=$((SECONDS - started)) python
  python=$(in_root "$root" /opt/venv/bin/python -c 'import platform; print(platform.python_version())')
  rm -f "$CACHE/work-trixie.db"*
  relay_start "$CACHE/work-trixie.db" || fail "no relay on this host" || return
  step "dcuscope run vtest --probes --relay $RELAY_URL"
  in_root "$root" bash -c "cd /opt/work && /opt/venv/bin/dcuscope run vtest -n 20 --node TRIXIE --probes \
    --trace vtest.trace.jsonl --relay $RELAY_URL --close-timeout 30" >&3 2>&1 \
    || { relay_stop; fail "dcuscope run vtest --relay failed there"; return; }
  relay_stop
  stored_check "$CACHE/work-trixie.db" "$work/vtest.trace.jsonl" TRIXIE || fail "vtest: $SAID" || return
  local vtest=$SAID
  step "dcuscope trace of gst-launch-1.0"
  in_root "$root" bash -c "cd /opt/work && /opt/venv/bin/dcuscope trace --node TRIXIE-APP -o app.trace.jsonl --quiet -- \
    gst-launch-1.0 -q $APP_CHAIN" >&3 2>&1 || fail "dcuscope trace failed there" || return
  local frames
  frames=$("$PY" -m dcuscope.cli stats "$work/app.trace.jsonl" --json | "$PY" -c \
    'import json,sys; print(json.load(sys.stdin)["nodes"]["TRIXIE-APP"]["frames"]["complete"])')
  [ "$frames" = 120 ] || fail "dcuscope trace: $frames of 120 frames complete" || return
  echo "Python $python, GStreamer $(gst_version "$root"): wheel installed in $took s; run vtest --relay: $vtest; trace: 120 of 120 frames complete"
}

check_arm64() {
  local root work started problem
  step "binfmt_misc"
  problem=$(binfmt_arm64) || fail "$problem" || return
  step "root filesystem (debootstrap, second stage under qemu-user)"
  root=$(rootfs arm64 bookworm arm64 "$ARM64_APT") || fail "debootstrap of bookworm arm64 failed" || return
  step "pip install the checkout there (the native library compiled there)"
  copy_sources "$root/opt/dcuscope-src"
  started=$SECONDS
  install_dcuscope "$root" "/opt/dcuscope-src[pipeline]" || fail "pip install from source failed there" || return
  local took=$((SECONDS - started)) machine
  machine=$(in_root "$root" /opt/venv/bin/python -c 'import platform; print(platform.machine(), platform.python_version())')
  work=$root/opt/work && rm -rf "$work" && mkdir -p "$work"
  rm -f "$CACHE/work-arm64.db"*
  relay_start "$CACHE/work-arm64.db" || fail "no relay on this host" || return
  step "gst-launch-1.0 traced, its trace shipped with dcuscope ship to $RELAY_URL"
  in_root "$root" bash -c "cd /opt/work && export GST_PLUGIN_PATH=\$(/opt/venv/bin/dcuscope plugin-path) && \
    { /opt/venv/bin/dcuscope ship --relay $RELAY_URL --close-timeout 60 app.trace.jsonl & } && \
    GST_TRACERS='dcuscope(node=ARM64,trace=app.trace.jsonl)' gst-launch-1.0 -q $APP_CHAIN && wait" >&3 2>&1 \
    || { relay_stop; fail "the traced app or dcuscope ship failed there"; return; }
  relay_stop
  stored_check "$CACHE/work-arm64.db" "$work/app.trace.jsonl" ARM64 || fail "ship: $SAID" || return
  local shipped=$SAID line
  step "dcuscope run vtest -n 5 (onnxruntime's aarch64 wheel)"
  line=$(in_root "$root" bash -c "cd /opt/work && /opt/venv/bin/dcuscope run vtest -n 5" 2>&1 | tee -a /dev/fd/3 | grep '^infer: ')
  [[ "$line" == *person* ]] || fail "dcuscope run vtest detected no person: ${line:-no infer line}" || return
  echo "$machine, GStreamer $(gst_version "$root"): installed from source in $took s (emulated); ship: $shipped; run vtest: $line"
}
