#!/usr/bin/env bash
# The system libraries bench/peers.py's peers need, installed with apt-get
# when an import shows them missing (the Python packages come with the
# `bench` extra): Open3D loads libusb-1.0 when imported, and Mitsuba's
# llvm_ad_rgb variant loads libLLVM at run time.  Its path integrator aborts
# with Debian's LLVM 15 on some hosts ("Cannot select ... fminimum"; seen on
# AVX-512 Xeons and on AMD EPYC Zen 3) and runs with LLVM 19, which
# bench/path.py then names in DRJIT_LIBLLVM_PATH.  Safe to run again; a peer
# that still cannot load is reported as missing by bench/peers.py.
# LuxCore's PATHCPU (bench/path.py's third renderer) comes from pip's
# pyluxcore, installed here where pip finds a wheel for this platform; where
# it does not, bench/path.py says LuxCore is skipped.
set -uo pipefail
PY=${PYTHON:-python3}
SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"

if ! "$PY" -c "import numpy, pyluxcore" >/dev/null 2>&1; then
    echo "setup_peers.sh: installing pyluxcore (LuxCore) for bench/path.py" >&2
    "$PY" -m pip install -q pyluxcore \
        || echo "setup_peers.sh: pip could not install pyluxcore here; bench/path.py will skip LuxCore" >&2
fi

needed=()
if "$PY" -c "import importlib.util as u, sys; sys.exit(u.find_spec('open3d') is None)" 2>/dev/null \
        && ! "$PY" -c "import open3d" >/dev/null 2>&1; then
    needed+=(libusb-1.0-0)
fi
if "$PY" -c "import importlib.util as u, sys; sys.exit(u.find_spec('mitsuba') is None)" 2>/dev/null \
        && ! "$PY" -c "import mitsuba; mitsuba.set_variant('llvm_ad_rgb')" >/dev/null 2>&1; then
    needed+=(libllvm15)
fi
if "$PY" -c "import importlib.util as u, sys; sys.exit(u.find_spec('mitsuba') is None)" 2>/dev/null \
        && ! ls /usr/lib/*/libLLVM.so.19* >/dev/null 2>&1 \
        && ! "$PY" -c "
import mitsuba as mi
mi.set_variant('llvm_ad_rgb')
mi.render(mi.load_dict(mi.cornell_box()), spp=1)" >/dev/null 2>&1; then
    needed+=(libllvm19)  # the path integrator, where LLVM 15 cannot compile it
fi
[ ${#needed[@]} -eq 0 ] && exit 0
if ! command -v apt-get >/dev/null; then
    echo "setup_peers.sh: install ${needed[*]} (or your system's equivalent) for the benchmark peers" >&2
    exit 1
fi
echo "setup_peers.sh: installing ${needed[*]} for the benchmark peers" >&2
$SUDO apt-get update -qq
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${needed[@]}" >/dev/null
