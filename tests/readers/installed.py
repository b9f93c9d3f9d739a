"""Locate the optional test-only readers (scripts/install-readers.sh); skip a test when absent."""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
TOOLS = REPO / ".tools"
READERS = Path(__file__).resolve().parent
INSTALL_HINT = "run scripts/install-readers.sh"


def _from_env_or(variable: str, default: Path) -> Path:
    return Path(os.environ[variable]) if os.environ.get(variable) else default


def fbx2gltf() -> Path:
    """The FBX2glTF binary (Autodesk FBX SDK inside) from npm fbx2gltf@0.9.7."""
    path = _from_env_or("MOCAPTK_FBX2GLTF", TOOLS / "fbx2gltf" / "bin" / "Linux" / "FBX2glTF")
    if not os.access(path, os.X_OK):
        pytest.skip(f"FBX2glTF (Autodesk FBX SDK reader) not installed at {path}: {INSTALL_HINT}")
    return path


def gltf_validator() -> Path:
    """The Khronos gltf-validator npm module folder (and node on PATH)."""
    path = _from_env_or("MOCAPTK_GLTF_VALIDATOR", TOOLS / "node_modules" / "gltf-validator")
    if shutil.which("node") is None or not (path / "package.json").is_file():
        pytest.skip(f"gltf-validator (npm) or node not installed at {path}: {INSTALL_HINT}")
    return path


def blender_python() -> Path:
    """A Python with PyPI bpy 5.0.1 (its own venv; see docs/rig-format.md)."""
    path = _from_env_or("MOCAPTK_BLENDER_PYTHON", TOOLS / "bpyvenv" / "bin" / "python")
    if not os.access(path, os.X_OK):
        pytest.skip(f"no Blender (bpy) Python at {path}: set MOCAPTK_BLENDER_PYTHON or see "
                    f"docs/rig-format.md")
    return path


def run_ufbx(fbx: Path) -> dict:
    """Load ``fbx`` with ufbx in a subprocess (the binding can crash) and return its report."""
    if importlib.util.find_spec("ufbx") is None:
        pytest.skip(f"ufbx not installed: {INSTALL_HINT}")
    done = subprocess.run([sys.executable, str(READERS / "read_fbx_ufbx.py"), str(fbx)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, f"ufbx reader failed ({done.returncode}): {done.stderr[-2000:]}"
    return json.loads(done.stdout)


def run_validator(glb: Path) -> dict:
    """The Khronos gltf-validator report for ``glb``."""
    module = gltf_validator()
    done = subprocess.run(["node", str(READERS / "validate_gltf.js"), str(module), str(glb)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, f"gltf-validator failed: {done.stderr[-2000:]}"
    return json.loads(done.stdout)
