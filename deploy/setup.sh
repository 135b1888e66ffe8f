#!/usr/bin/env bash
# Sets up matopt in ./.venv on a fresh Debian/Ubuntu machine: the system packages it needs
# (python3-venv; libLLVM >= 16 for Dr.Jit's CPU backend, which aborts on LLVM 14/15; the
# libraries Qt needs), then the package with all its extras. Safe to run again.
set -euo pipefail
cd "$(dirname "$0")/.."

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

missing=()
python3 -c "import ensurepip, venv" >/dev/null 2>&1 || missing+=(python3-venv python3-pip)
have_llvm || missing+=(libllvm19)
# Qt (the desktop client and its tests, offscreen) needs these shared libraries.
for pair in libEGL.so.1:libegl1 libGL.so.1:libgl1 libxkbcommon.so.0:libxkbcommon0 \
            libfontconfig.so.1:libfontconfig1 libglib-2.0.so.0:libglib2.0-0 \
            libdbus-1.so.3:libdbus-1-3; do
    ldconfig -p 2>/dev/null | grep -q "${pair%%:*}" || missing+=("${pair##*:}")
done
if [ ${#missing[@]} -gt 0 ]; then
    echo "setup: installing ${missing[*]} with apt-get"
    $sudo apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "${missing[@]}"
fi

[ -x .venv/bin/python ] || python3 -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e ".[daemon,qt,plot,test,ray]"
llvm=$(.venv/bin/python -c "from matoptd.workers.devices import find_libllvm; print(find_libllvm() or '')")
echo "setup: ready in .venv (Dr.Jit's CPU backend will use ${llvm:-no libLLVM >= 16 found})"
