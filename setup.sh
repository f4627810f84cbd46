#!/usr/bin/env bash
# Set-up on a fresh machine: the package (editable) with its test and bench
# extras, Intel's CPU OpenCL runtime, and an OpenCL CPU driver that can
# compile kernels here.  Safe to run again.
set -euo pipefail
cd "$(dirname "$0")"
PY=${PYTHON:-python3}
"$PY" -m pip install --quiet --disable-pip-version-check -e ".[test,bench,intel]"
# pyenv only puts new console scripts (hlbvh-cl) on PATH after a rehash
if command -v pyenv >/dev/null; then pyenv rehash || true; fi

# PyPI's PoCL 3.0 is built on LLVM 14, which cannot compile for CPUs newer
# than it knows ("unknown target CPU 'generic'"), and crashes on the
# traversal's vector code on some AVX-512 CPUs; Debian's PoCL 3.1 can.  The
# device listing runs the real kernels in a child process (hlbvh_cl/probe.py).
if ! "$PY" -m hlbvh_cl devices --require pocl --no-fallback; then
    if command -v apt-get >/dev/null; then
        SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
        echo "setup.sh: installing Debian's PoCL (pocl-opencl-icd)" >&2
        $SUDO apt-get update -qq
        DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq pocl-opencl-icd >/dev/null
    fi
    "$PY" -m hlbvh_cl devices --require pocl || {
        echo "setup.sh: no PoCL device here can compile kernels; see README.md" >&2; exit 1; }
fi

# Optional: system libraries of bench/trace.py's peers (Open3D, Mitsuba); the tests do not need them.
PYTHON="$PY" bash bench/setup_peers.sh || echo "setup.sh: benchmark peers not set up; bench/trace.py reports them missing" >&2
