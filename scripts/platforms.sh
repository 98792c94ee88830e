#!/usr/bin/env bash
# dcuscope on the machines DCUs are: the same checks run inside Debian root filesystems that
# debootstrap builds (and keeps, outside the checkout), one line per platform.
#
#   scripts/platforms.sh all                  # bullseye trixie arm64
#   scripts/platforms.sh bullseye arm64       # some of them
#   scripts/platforms.sh --list               # what each one checks
#
#   bullseye  amd64, GStreamer 1.18: the native library built there against 1.18's headers; an
#             unchanged gst-launch-1.0 app traced with GST_TRACERS=dcuscope beside 1.18's own
#             latency tracer; the trace read by this checkout's `dcuscope stats`, each element's
#             median within 0.1 ms + 3 % of the latency tracer's (the table is printed).
#   trixie    amd64, GStreamer 1.26, Python 3.13: the wheel built here, pip-installed there with its
#             [pipeline] extra; `dcuscope run vtest --probes --relay` to a relay here (loopback):
#             stored == sent; `dcuscope trace` of a gst-launch app.
#   arm64     Debian 12 arm64 under qemu-user (binfmt_misc): the package pip-installed from source
#             (the native library compiled there); a gst-launch app traced, its trace shipped to a
#             relay here with `dcuscope ship`: stored == sent; `dcuscope run vtest -n 5` detecting
#             persons with onnxruntime's aarch64 wheel.
#
# Needs root (debootstrap, chroot, mounts), debootstrap, and for arm64 qemu-user-static and
# binfmt_misc (mounted and registered here when missing); `make setup` done in this checkout.
# Downloads: ~250 MB for bullseye, ~600 MB each for trixie and arm64 (Debian packages, then PyPI
# wheels). Timings on a 2-core x86-64 box with a cache: docs/on-a-dcu.md. Not part of `make test`.
#
# Root filesystems are kept in $DCUSCOPE_PLATFORMS_CACHE (default ~/.cache/dcuscope/platforms) and
# built again only when their package list changes; each platform's log is there too. The Debian
# mirror is the host's own (its apt sources), or $DCUSCOPE_DEBIAN_MIRROR.
# Exit status 0 only when every platform asked for passed.
set -uo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
CHECKOUT=$PWD
PY=$CHECKOUT/.venv/bin/python
CACHE=${DCUSCOPE_PLATFORMS_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/dcuscope/platforms}
ALL=(bullseye trixie arm64)

GST_APT="gstreamer1.0-tools,gstreamer1.0-plugins-base,gstreamer1.0-plugins-good,libgstreamer1.0-dev,gcc,libc6-dev,pkg-config"
PY_APT="python3,python3-venv,python3-gi,python3-gst-1.0,gir1.2-gstreamer-1.0,gir1.2-gst-plugins-base-1.0,gstreamer1.0-libav,gstreamer1.0-python3-plugin-loader,ca-certificates"

usage() { sed -n '2,/^set -uo/p' "$0" | sed '$d' | sed 's/^# \{0,1\}//'; }

mirror() {
  if [ -n "${DCUSCOPE_DEBIAN_MIRROR:-}" ]; then echo "$DCUSCOPE_DEBIAN_MIRROR"; return; fi
  # The host's own Debian mirror (deb822 or one-line sources); none found: debootstrap's default.
  cat /etc/apt/sources.list.d/*.sources /etc/apt/sources.list 2>/dev/null \
    | grep -oE '(URIs:|^deb) +[a-z]+://[^ ]+/debian/?( |$)' | grep -v security | head -1 | awk '{print $2}'
}

# rootfs NAME SUITE ARCH PACKAGES: the root filesystem's folder, built unless a build of the same
# suite, architecture and packages is there. Progress goes to the log (fd 3 is the log).
rootfs() {
  local name=$1 suite=$2 arch=$3 pkgs=$4 dir=$CACHE/$1 want
  want="$suite $arch $pkgs"
  if [ -f "$dir/.dcuscope-rootfs" ] && [ "$(cat "$dir/.dcuscope-rootfs")" = "$want" ]; then
    echo "$dir"; return 0
  fi
  rm -rf "$dir" "$dir.partial"
  local started=$SECONDS
  echo "building the $suite $arch root filesystem (debootstrap)" >&3
  if [ "$arch" = "$(dpkg --print-architecture)" ]; then
    debootstrap --variant=minbase --arch="$arch" "$suite" "$dir.partial" $(mirror) >&3 2>&1 || return 1
  else
    debootstrap --variant=minbase --arch="$arch" --foreign "$suite" "$dir.partial" $(mirror) >&3 2>&1 || return 1
    chroot "$dir.partial" /debootstrap/debootstrap --second-stage >&3 2>&1 || return 1
  fi
  # apt, not debootstrap --include, resolves the packages' alternatives (dbus-session-bus, ...).
  in_root "$dir.partial" apt-get update -q >&3 2>&1 || return 1
  in_root "$dir.partial" env DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends \
    ${pkgs//,/ } >&3 2>&1 || return 1
  in_root "$dir.partial" apt-get clean >&3 2>&1
  echo "root filesystem built in $((SECONDS - started)) s" >&3
  echo "$want" >"$dir.partial/.dcuscope-rootfs"
  mv "$dir.partial" "$dir" && echo "$dir"
}

# in_root DIR CMD...: CMD in the root filesystem, with /proc, /dev and (same architecture only) /sys
# mounted in a mount namespace of its own (gone with it), this host's DNS, and HOME=/root. Under
# qemu-user, this host's /sys describes x86 CPUs: ONNX Runtime's CPU detection reads it and crashes.
in_root() {
  local dir=$1 sys=1; shift
  [ -f "$dir/.dcuscope-rootfs" ] && [ "$(cut -d' ' -f2 "$dir/.dcuscope-rootfs")" != "$(dpkg --print-architecture)" ] && sys=0
  cp -L /etc/resolv.conf "$dir/etc/resolv.conf" 2>/dev/null || true
  unshare --mount --propagation private -- bash -c '
    d=$1 sys=$2; shift 2
    mount -t proc proc "$d/proc" && mount --rbind /dev "$d/dev" || exit 97
    [ "$sys" = 0 ] || mount --rbind /sys "$d/sys" || exit 97
    exec chroot "$d" /usr/bin/env -i HOME=/root PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin \
      LANG=C.UTF-8 "$@"' _ "$dir" "$sys" "$@"
}

# The sources as git sees them (tracked and new, not ignored; a file deleted but not yet committed is
# skipped), plus the page's vendored scripts.
copy_sources() {
  local to=$1
  rm -rf "$to" && mkdir -p "$to"
  git ls-files -co --exclude-standard -z | tar --null --ignore-failed-read -T - -cf - 2>/dev/null | tar -xf - -C "$to"
  [ -d dcuscope/ui/static/vendor ] && cp -r dcuscope/ui/static/vendor "$to/dcuscope/ui/static/"
  return 0
}

binfmt_arm64() {
  local dir=/proc/sys/fs/binfmt_misc
  [ -f $dir/register ] || mount -t binfmt_misc binfmt_misc $dir 2>/dev/null || {
    echo "binfmt_misc cannot be mounted here (a container without it?)"; return 1; }
  [ -x /usr/bin/qemu-aarch64-static ] || { echo "qemu-user-static is not installed (apt-get install qemu-user-static)"; return 1; }
  [ -f $dir/qemu-aarch64 ] && grep -q '^enabled' $dir/qemu-aarch64 && return 0
  # Debian's qemu-user-static entry, with F: the interpreter is opened now, so it runs in chroots.
  printf '%s' ':qemu-aarch64:M::\x7fELF\x02\x01\x01\x00\x00\x00\x00\x00\x00\x00\x00\x00\x02\x00\xb7\x00:\xff\xff\xff\xff\xff\xff\xff\x00\xff\xff\xff\xff\xff\xff\xff\xff\xfe\xff\xff\xff:/usr/bin/qemu-aarch64-static:F' \
    >$dir/register 2>/dev/null || { echo "cannot register qemu-aarch64 with binfmt_misc"; return 1; }
}

# relay_start DB: a relay of this checkout on a free loopback port; sets RELAY_PID, RELAY_URL.
relay_start() {
  local log=$1.log
  "$PY" -m dcuscope.cli relay --port 0 --clock-port 0 --db "$1" >"$log" 2>&1 &
  RELAY_PID=$!
  for _ in $(seq 100); do
    RELAY_URL=$(grep -oE 'http://127\.0\.0\.1:[0-9]+' "$log" | head -1)
    [ -n "$RELAY_URL" ] && return 0
    sleep 0.2
  done
  echo "the relay did not start: $(tail -1 "$log")"; return 1
}
relay_stop() { [ -n "${RELAY_PID:-}" ] && kill "$RELAY_PID" 2>/dev/null && wait "$RELAY_PID" 2>/dev/null; RELAY_PID=; }

source scripts/platforms/checks.sh

list() {
  usage | sed -n '/^  bullseye/,/^$/p'
}

main() {
  local asked=()
  for a in "$@"; do
    case $a in
      all) asked+=("${ALL[@]}") ;;
      bullseye|trixie|arm64) asked+=("$a") ;;
      --list) list; return 0 ;;
      -h|--help) usage; return 0 ;;
      *) echo "platforms.sh: unknown platform '$a' (bullseye, trixie, arm64 or all; --help)" >&2; return 2 ;;
    esac
  done
  [ ${#asked[@]} -gt 0 ] || { usage; return 2; }
  local failed=0 problem
  problem=$(preflight) || { for p in "${asked[@]}"; do echo "$p: FAILED $problem"; done; return 1; }
  mkdir -p "$CACHE/logs"
  for p in "${asked[@]}"; do
    local log=$CACHE/logs/$p.log started=$SECONDS line
    : >"$log"
    line=$("check_$p" 3>>"$log" 2>>"$log")
    local rc=$? took=$((SECONDS - started))
    if [ $rc -eq 0 ]; then
      echo "$p: ok ${line:-} (${took} s)"
    else
      failed=1
      echo "$p: FAILED ${line:-see the log} (${took} s; log: $log)"
    fi
    [ -f "$CACHE/logs/$p.table" ] && [ $rc -eq 0 ] && sed 's/^/    /' "$CACHE/logs/$p.table"
  done
  return $failed
}

preflight() {
  [ "$(id -u)" -eq 0 ] || { echo "needs root (debootstrap, chroot, mounts)"; return 1; }
  command -v debootstrap >/dev/null || { echo "debootstrap is not installed (apt-get install debootstrap)"; return 1; }
  [ -x "$PY" ] || { echo "no $PY: run make setup first"; return 1; }
}

if [ "${BASH_SOURCE[0]}" = "$0" ]; then main "$@"; fi
