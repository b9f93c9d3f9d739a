"""Output writers run in a second process (`mocaptk.background.beside`): the same files as run in
this one, their failures raised here, and nothing written on after the caller gave up."""

from __future__ import annotations

import os
import signal

import pytest
from clustering_synthetic import planted_session, save_session

from mocaptk import background
from mocaptk.background import beside
from mocaptk.errors import MocaptkError, OptionError

needs_fork = pytest.mark.skipif(not background.can_fork(), reason="fork: Linux with 2+ CPUs only")


@needs_fork
def test_the_task_runs_in_another_process_beside_the_body(tmp_path):
    target = tmp_path / "task.txt"
    with beside(lambda: target.write_text(str(os.getpid())), what="the task"):
        body_pid = os.getpid()
    assert int(target.read_text()) != body_pid  # written by the child, finished on leaving


@pytest.mark.parametrize("fork", [True, False])
def test_the_task_result_comes_back_on_leaving(monkeypatch, fork):
    if fork and not background.can_fork():
        pytest.skip("fork: Linux with 2+ CPUs only")
    monkeypatch.setattr(background, "can_fork", lambda: fork)
    with beside(lambda: {"pid": os.getpid(), "rmse_mm": 0.25}, what="the check") as outcome:
        body_pid = os.getpid()
    assert outcome.value["rmse_mm"] == 0.25
    assert (outcome.value["pid"] != body_pid) == fork


@needs_fork
def test_a_failure_of_the_task_is_raised_after_the_body_with_its_type_and_message(tmp_path):
    def task():
        raise OptionError("bad picture option")

    ran = []
    with pytest.raises(OptionError, match="bad picture option"):
        with beside(task, what="the pictures"):
            ran.append(True)
    assert ran == [True]


@needs_fork
def test_a_task_killed_by_a_signal_is_one_error_naming_it():
    with pytest.raises(MocaptkError, match=r"the rig files stopped .*signal 9"):
        with beside(lambda: os.kill(os.getpid(), signal.SIGKILL), what="the rig files"):
            pass


@needs_fork
def test_an_unpicklable_failure_keeps_its_type_name_and_message():
    class Local(Exception):  # a local class does not pickle
        pass

    def task():
        raise Local("lost in transit")

    with pytest.raises(MocaptkError, match="Local: lost in transit"):
        with beside(task, what="the task"):
            pass


@needs_fork
def test_a_failing_body_stops_the_task_before_it_writes(tmp_path):
    gate_read, gate_write = os.pipe()  # never written: the task waits until it is killed
    target = tmp_path / "late.txt"

    def task():
        os.read(gate_read, 1)
        target.write_text("written after the caller gave up")

    with pytest.raises(RuntimeError, match="body failed"):
        with beside(task, what="the task"):
            raise RuntimeError("body failed")
    os.close(gate_write)
    os.close(gate_read)
    assert not target.exists()


def test_cluster_writes_the_same_files_with_and_without_a_second_process(run_cli, tmp_path,
                                                                          monkeypatch):
    traj, _ = planted_session(seed=5, per_group=3, frames=240)
    session, _ = save_session(traj, tmp_path / "planted.npz")
    forked = run_cli("cluster", session, "--out", tmp_path / "forked", "--quiet")
    monkeypatch.setattr(background, "can_fork", lambda: False)
    inline = run_cli("cluster", session, "--out", tmp_path / "inline", "--quiet")
    assert forked.exit_code == inline.exit_code == 0, forked.stderr + inline.stderr
    names = sorted(p.relative_to(tmp_path / "forked") for p in (tmp_path / "forked").rglob("*"))
    assert names == sorted(p.relative_to(tmp_path / "inline") for p in (tmp_path / "inline").rglob("*"))
    assert {"rig.fbx", "rig.glb", "rig.json", "guide.pdf", "layout.png"} <= {n.name for n in names}
    for name in names:
        if (tmp_path / "forked" / name).is_file():
            assert (tmp_path / "forked" / name).read_bytes() == \
                (tmp_path / "inline" / name).read_bytes(), name


@pytest.mark.parametrize("fork", [True, False])
def test_shared_map_keeps_the_order_and_computes_the_first_item_here(monkeypatch, fork):
    if fork and not background.can_fork():
        pytest.skip("fork: Linux with 2+ CPUs only")
    monkeypatch.setattr(background, "can_fork", lambda: fork)
    done = background.shared_map(lambda x: (x * x, os.getpid()), list(range(7)), what="a square")
    assert [value for value, _ in done] == [x * x for x in range(7)]
    assert done[0][1] == os.getpid()
    assert len({pid for _, pid in done}) == (min(background.machine_workers(), 7) if fork else 1)
    assert background.shared_map(lambda x: x, [], what="nothing") == []


@needs_fork
def test_a_failure_in_a_shared_item_is_raised_here():
    def item(x):
        if x == 3:
            raise OptionError("item 3 is bad")
        return x

    with pytest.raises(OptionError, match="item 3 is bad"):
        background.shared_map(item, list(range(6)), what="an item")
