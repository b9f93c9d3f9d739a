#!/usr/bin/env bash
# Install the test-only readers that check our outputs (never shipped, never imported by mocaptk):
#   ufbx (PyPI), the FBX2glTF binary from npm fbx2gltf@0.9.7 (Autodesk FBX SDK inside),
#   the Khronos gltf-validator (npm), and Debian's chromium (apt-get, as root; opens report.html
#   headless in tests/test_report_browser.py), Debian's slurm-wlm + munge (tests/test_batch_slurm.py
#   starts them for batch --cluster slurm). npm tools go to <repo>/.tools/ (git-ignored).
#   With --blender also Blender as a module: PyPI bpy 5.0.1 (GPL, ~1.2 GB, Python 3.11 only,
#   pins numpy<2) in its own venv .tools/bpyvenv, used by scripts/check_fbx_blender.py.
# Usage: scripts/install-readers.sh [--blender]  (idempotent; tests skip a missing reader)
set -euo pipefail
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
tools="$repo/.tools"
mkdir -p "$tools"

python -c "import ufbx" 2>/dev/null || python -m pip install --quiet "ufbx>=0.0.5"

if ! command -v npm >/dev/null; then
    echo "install-readers: npm not found, skipping FBX2glTF and gltf-validator (their tests skip)" >&2
else
    if [ ! -x "$tools/fbx2gltf/bin/Linux/FBX2glTF" ]; then
        work="$(mktemp -d)"
        (cd "$work" && npm pack --silent fbx2gltf@0.9.7 >/dev/null && tar -xzf fbx2gltf-0.9.7.tgz)
        rm -rf "$tools/fbx2gltf"
        mv "$work/package" "$tools/fbx2gltf"
        rm -rf "$work"
        chmod +x "$tools/fbx2gltf/bin/Linux/FBX2glTF"
    fi

    if [ ! -f "$tools/node_modules/gltf-validator/package.json" ]; then
        npm install --silent --no-save --no-audit --no-fund --prefix "$tools" gltf-validator@2.0.0-dev.3.10
    fi
fi

python -c "import websocket" 2>/dev/null || python -m pip install --quiet "websocket-client>=1.7"
# Debian packages: chromium opens report.html; poppler-utils (pdftoppm) renders guide.pdf pages
debs=()
command -v chromium >/dev/null || command -v chromium-browser >/dev/null || debs+=(chromium)
command -v pdftoppm >/dev/null || debs+=(poppler-utils)
# slurm-wlm + munge: tests/test_batch_slurm.py starts a single-node SLURM for batch --cluster slurm
command -v slurmctld >/dev/null || [ -x /usr/sbin/slurmctld ] || debs+=(slurm-wlm munge)
if [ "${#debs[@]}" -eq 0 ]; then
    :
elif command -v apt-get >/dev/null && [ "$(id -u)" = 0 ]; then
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${debs[@]}" >/dev/null \
        || echo "install-readers: apt-get could not install ${debs[*]} (the browser / PDF-page / SLURM tests skip)" >&2
else
    echo "install-readers: no root apt-get, skipping ${debs[*]} (the browser / PDF-page tests skip)" >&2
fi

if [ "${1:-}" = "--blender" ] && [ ! -x "$tools/bpyvenv/bin/python" ]; then
    python3.11 -m venv "$tools/bpyvenv"
    "$tools/bpyvenv/bin/python" -m pip install --quiet "bpy==5.0.1"
fi

echo "readers installed: ufbx $(python -c 'import importlib.metadata as m; print(m.version("ufbx"))')," \
     "FBX2glTF $tools/fbx2gltf/bin/Linux/FBX2glTF, gltf-validator $tools/node_modules/gltf-validator," \
     "chromium $(command -v chromium || command -v chromium-browser || echo 'not installed')"
