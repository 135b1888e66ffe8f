#!/usr/bin/env bash
# Sets up matopt in ./.venv on a fresh Debian/Ubuntu machine: the system packages it needs,
# then the package with its extras. Safe to run again.
#
#   deploy/setup.sh [EXTRAS]     default: daemon,qt,plot,test,ray (everything)
#
# python3-venv always; with the daemon extra, libLLVM >= 16 for Dr.Jit's CPU backend (which
# aborts on LLVM 14/15); with qt (or test, which brings PySide6 along), the libraries Qt needs,
# on a desktop (its xcb platform) and off one; with test, Xvfb for the test that starts the
# Qt app on an X server. `deploy/setup.sh ""` sets up the clients alone.
set -euo pipefail
cd "$(dirname "$0")/.."
extras=${1-daemon,qt,plot,test,ray}
wants() { [[ ",$extras," == *",$1,"* ]]; }

sudo=""
[ "$(id -u)" = 0 ] || sudo="sudo"

have_llvm() {  # libLLVM.so.19.1, libLLVM-19.so, ...: any major version >= 16
    local f v
    for f in /usr/lib/*/libLLVM*.so* /usr/lib64/libLLVM*.so*; do
        v=$(basename "$f" | sed -nE 's/^libLLVM[-.]?(so\.)?([0-9]+).*/\2/p')
        [ -n "$v" ] && [ "$v" -ge 16 ] && return 0
    done
    return 1
}

# Qt's shared libraries (docs/qt.md): library:package, offscreen and on an X server (xcb).
QT_LIBRARIES="libEGL.so.1:libegl1 libGL.so.1:libgl1 libxkbcommon.so.0:libxkbcommon0
    libfontconfig.so.1:libfontconfig1 libglib-2.0.so.0:libglib2.0-0 libdbus-1.so.3:libdbus-1-3
    libX11-xcb.so.1:libx11-xcb1 libxcb-cursor.so.0:libxcb-cursor0
    libxcb-icccm.so.4:libxcb-icccm4 libxcb-image.so.0:libxcb-image0
    libxcb-keysyms.so.1:libxcb-keysyms1 libxcb-randr.so.0:libxcb-randr0
    libxcb-render-util.so.0:libxcb-render-util0 libxcb-shape.so.0:libxcb-shape0
    libxcb-xfixes.so.0:libxcb-xfixes0 libxcb-xkb.so.1:libxcb-xkb1
    libxkbcommon-x11.so.0:libxkbcommon-x11-0"

missing=()
python3 -c "import ensurepip, venv" >/dev/null 2>&1 || missing+=(python3-venv python3-pip)
if wants daemon; then have_llvm || missing+=(libllvm19); fi
if wants qt || wants test; then
    for pair in $QT_LIBRARIES; do
        ldconfig -p 2>/dev/null | grep -q "${pair%%:*}" || missing+=("${pair##*:}")
    done
fi
if wants test; then command -v Xvfb >/dev/null || missing+=(xvfb); fi
if [ ${#missing[@]} -gt 0 ]; then
    echo "setup: installing ${missing[*]} with apt-get"
    $sudo apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "${missing[@]}"
fi

[ -x .venv/bin/python ] || python3 -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e ".${extras:+[$extras]}"
if wants daemon; then
    llvm=$(.venv/bin/python -c "from matoptd.workers.devices import find_libllvm; print(find_libllvm() or '')")
    echo "setup: ready in .venv (Dr.Jit's CPU backend will use ${llvm:-no libLLVM >= 16 found})"
else
    echo "setup: ready in .venv (extras: ${extras:-none})"
fi
