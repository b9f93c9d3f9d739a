"""batch's session side without a cluster: patterns, the command line split, sidecar options."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mocaptk.batch.sessions import find_sessions, session_argv, split_batch_line
from mocaptk.errors import InputFileError, OptionError


def test_split_batch_line_keeps_patterns_and_checks_options(tmp_path):
    patterns, options = split_batch_line(
        "cluster", ["a/*.c3d", "--factor", "1.2", "--no-mirror", "b.c3d", "--regions=r.json"], base=tmp_path)
    assert patterns == ["a/*.c3d", "b.c3d"]
    assert options == ["--factor", "1.2", "--no-mirror", "--regions", str(tmp_path / "r.json")]
    with pytest.raises(OptionError, match="mocaptk evaluate has no option --factor"):
        split_batch_line("evaluate", ["x", "--factor", "1"], base=tmp_path)
    with pytest.raises(OptionError, match="--force is set by batch"):
        split_batch_line("cluster", ["x", "--force"], base=tmp_path)


def test_sidecars_folder_then_session_then_relative_paths(tmp_path):
    session = tmp_path / "anna" / "day2.c3d"
    session.parent.mkdir()
    session.write_bytes(b"")
    (session.parent / "mocaptk.json").write_text(json.dumps({"factor": 1.3, "mirror": False, "layout": "x.json"}))
    (session.parent / "day2.mocaptk.json").write_text(json.dumps(
        {"format": "mocaptk.session-options", "version": 1, "regions": "anna_regions.json",
         "rigid": ["H1", "H2", "H3"], "factor": 0.9}))
    argv = session_argv("cluster", session, tmp_path / "out" / "day2", ["--factor", "1.1", "--step", "2"])
    assert argv == ["cluster", str(session), "--factor", "1.1", "--step", "2",
                    "--factor", "1.3", "--no-mirror",  # folder-wide (layout is evaluate's: left out)
                    "--factor", "0.9", "--regions", str(session.parent / "anna_regions.json"),
                    "--rigid", "H1,H2,H3", "--quiet", "--out", str(tmp_path / "out" / "day2")]
    evaluate = session_argv("evaluate", session, tmp_path / "o", [])
    assert evaluate[evaluate.index("--layout") + 1] == str(session.parent / "x.json")
    assert session_argv("info", session, tmp_path / "o", []) == ["info", str(session), "--json"]


@pytest.mark.parametrize("doc, message", [
    ({"regoins": "r.json"}, "unknown option 'regoins' (no batch command has --regoins)"),
    ({"out": "elsewhere"}, "'out' is set by batch for every session"),
    ({"mirror": "yes"}, "'mirror' must be true or false"),
    ({"format": "other"}, "not a session options file"),
    ([1, 2], "expected a JSON object"),
])
def test_bad_sidecar_is_that_sessions_error(tmp_path, doc, message):
    session = tmp_path / "s.c3d"
    session.write_bytes(b"")
    (tmp_path / "s.mocaptk.json").write_text(json.dumps(doc))
    with pytest.raises(InputFileError, match=message.replace("(", r"\(").replace(")", r"\)")) as info:
        session_argv("cluster", session, tmp_path / "o", [])
    assert str(info.value).startswith(str(tmp_path / "s.mocaptk.json"))


def test_find_sessions_skips_sidecars_and_refuses_shared_stems(tmp_path):
    for name in ("a/x.c3d", "a/x.mocaptk.json", "a/mocaptk.json", "b/y.c3d", "c/x.trc"):
        (tmp_path / name).parent.mkdir(exist_ok=True)
        (tmp_path / name).write_text("")
    assert find_sessions([str(tmp_path / "a" / "*"), str(tmp_path / "b" / "*.c3d")]) == [
        tmp_path / "a" / "x.c3d", tmp_path / "b" / "y.c3d"]
    assert find_sessions([str(tmp_path / "**" / "y.c3d")]) == [tmp_path / "b" / "y.c3d"]
    with pytest.raises(OptionError, match="two sessions share the name 'x'"):
        find_sessions([str(tmp_path / "*" / "x.*")])
    with pytest.raises(OptionError, match="no session file matches"):
        find_sessions([str(tmp_path / "a" / "*.c3d"), str(tmp_path / "nope*")])
    assert Path(find_sessions([str(tmp_path / "a" / "x.c3d")])[0]).is_absolute()


def test_solve_takes_its_layout_from_the_batch_line_or_the_sidecar(tmp_path):
    capture = tmp_path / "shoot" / "take1.c3d"
    capture.parent.mkdir()
    capture.write_bytes(b"")
    patterns, options = split_batch_line("solve", ["shoot/*.c3d", "--layout", "L.json", "--formats", "none"],
                                         base=tmp_path)
    assert patterns == ["shoot/*.c3d"] and options == ["--layout", str(tmp_path / "L.json"), "--formats", "none"]
    argv = session_argv("solve", capture, tmp_path / "o", options)
    assert argv == ["solve", str(tmp_path / "L.json"), str(capture), "--formats", "none", "--quiet",
                    "--out", str(tmp_path / "o")]
    (capture.parent / "take1.mocaptk.json").write_text(json.dumps({"layout": "anna/layout.json"}))
    assert session_argv("solve", capture, tmp_path / "o", options)[1] == str(capture.parent / "anna" / "layout.json")
    with pytest.raises(InputFileError, match="no layout for it: give batch --layout L.json"):
        session_argv("solve", tmp_path / "take2.c3d", tmp_path / "o", [])
    with pytest.raises(OptionError, match="mocaptk cluster has no option --layout"):
        split_batch_line("cluster", ["x", "--layout", "L.json"], base=tmp_path)
