"""The same rig gives byte-identical JSON, FBX and glTF files across runs and hash seeds."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from readers.sample_rig import sample_rig

from mocaptk.retarget import write_rig_fbx, write_rig_glb, write_rig_json

WRITERS = {"rig.json": write_rig_json, "rig.fbx": write_rig_fbx, "rig.glb": write_rig_glb}
_CHILD = """
import sys
sys.path.insert(0, {tests!r})
from readers.sample_rig import sample_rig
from mocaptk.retarget import write_rig_fbx, write_rig_glb, write_rig_json
rig = sample_rig()
for name, write in (("rig.json", write_rig_json), ("rig.fbx", write_rig_fbx),
                    ("rig.glb", write_rig_glb)):
    write(rig, {folder!r} + "/" + name)
"""


def test_exports_are_byte_identical(tmp_path):
    here = tmp_path / "here"
    for name, write in WRITERS.items():
        write(sample_rig(), here / name)
        write(sample_rig(), here / f"again_{name}")
        assert (here / name).read_bytes() == (here / f"again_{name}").read_bytes(), name
    there = tmp_path / "there"
    there.mkdir()
    code = _CHILD.format(tests=str(Path(__file__).parent), folder=str(there))
    env = {**os.environ, "PYTHONHASHSEED": "12345"}
    subprocess.run([sys.executable, "-c", code], check=True, env=env, timeout=120)
    for name in WRITERS:
        assert (here / name).read_bytes() == (there / name).read_bytes(), name
