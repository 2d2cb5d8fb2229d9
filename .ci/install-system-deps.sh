#!/usr/bin/env bash
# System packages for offscreen/windowed OpenGL (Mesa llvmpipe through EGL/GLX), a virtual X
# server for the viewer's tests, screenshot/input tools, and g++ for the optional compiled CPU kernels. Installs only what is missing, and
# only when run as root on a Debian/Ubuntu machine; otherwise it says what to install.
set -euo pipefail
PKGS="libgl1 libegl1 libgles2 libegl-mesa0 libglx-mesa0 libgl1-mesa-dri xvfb xauth xdotool imagemagick g++"
missing=""
for p in $PKGS; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing="$missing $p"
done
[ -z "$missing" ] && exit 0
if [ "$(id -u)" != 0 ] || ! command -v apt-get >/dev/null; then
  echo "note: missing system packages:$missing (install them with apt-get as root; the viewer and GL tests need them)" >&2
  exit 0
fi
echo "installing system packages:$missing"
export DEBIAN_FRONTEND=noninteractive
apt-get install -y -q --no-install-recommends $missing >/dev/null 2>&1 || {
  apt-get update -q >/dev/null && apt-get install -y -q --no-install-recommends $missing >/dev/null
}
