#!/bin/sh
# Install Debian's libllvm19 so drjit's LLVM backend (mitsuba variant llvm_ad_rgb) works.
#
# drjit 1.5 crashes with the system default LLVM 15; LLVM 19 works. Idempotent: does
# nothing when libLLVM.so.19* is already present. Installs with apt-get only when run
# as root with apt-get available; otherwise prints what to do. Never fails the caller
# (always exits 0): kdtrace falls back to the scalar_rgb variant with a warning.
#
# Usage: sh scripts/setup-llvm.sh
# Afterwards kdtrace finds the library by itself (references/llvm.py); for other tools:
#   export DRJIT_LIBLLVM_PATH=<the path printed below>

find_llvm19() {
    for dir in /usr/lib/llvm-19/lib /usr/lib/x86_64-linux-gnu; do
        for lib in "$dir"/libLLVM.so.19* "$dir"/libLLVM-19.so*; do
            if [ -f "$lib" ]; then
                echo "$lib"
                return 0
            fi
        done
    done
    return 1
}

if lib=$(find_llvm19); then
    echo "setup-llvm: LLVM 19 already installed: $lib"
    echo "setup-llvm: export DRJIT_LIBLLVM_PATH=$lib"
    exit 0
fi

if [ "$(id -u)" != "0" ] || ! command -v apt-get >/dev/null 2>&1; then
    echo "setup-llvm: libLLVM 19 not found and cannot install it here (need root and apt-get)."
    echo "setup-llvm: run as root: apt-get update && apt-get install -y libllvm19"
    echo "setup-llvm: until then kdtrace renders Mitsuba references with scalar_rgb (slower)."
    exit 0
fi

echo "setup-llvm: installing libllvm19 with apt-get"
if ! { apt-get update && DEBIAN_FRONTEND=noninteractive apt-get install -y libllvm19; }; then
    echo "setup-llvm: apt-get failed; kdtrace will fall back to scalar_rgb (slower)."
    exit 0
fi

if lib=$(find_llvm19); then
    echo "setup-llvm: installed: $lib"
    echo "setup-llvm: export DRJIT_LIBLLVM_PATH=$lib"
else
    echo "setup-llvm: libllvm19 installed but no libLLVM.so.19* found under /usr/lib/llvm-19/lib or /usr/lib/x86_64-linux-gnu"
fi
exit 0
