"""Nothing outlives its supervisor (issue 43): killed by any signal, SIGKILL included,
``upcast up`` and ``upcast serve`` leave no process and no ring or socket behind.

The mechanism is each process's reaper (server/ops/reaper.py, orphan_guard.py): it
learns from the kernel (EOF on a pipe) that its parent is gone, SIGTERMs what is
registered, removes the files, SIGKILLs what is left after 1 s.

The issue's bound is 2 s; measured on a 2-core machine, 5 runs (3 beside a busy
loop): ``up`` 1.04-1.23 s, ``serve --sessions 2`` 1.20-1.37 s. The end-to-end tests
assert ``CLEANUP_BOUND_S`` (5 s) so that a loaded CI machine's scheduling does not
fail them; the reaper's own tests assert the 2 s.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from server.ops.process import pid_alive
from server.ops.reaper import Watched, Watchlist, reap, start_time

ROOT = Path(__file__).resolve().parents[1]
SMALL = ["--render-size", "160x90", "--display-size", "320x180", "--fps", "15"]
UP_TIMEOUT_S = 120.0  # a cold start imports torch in 3 processes on 2 cores
ISSUE_BOUND_S = 2.0
CLEANUP_BOUND_S = 5.0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _children(pid: int) -> list[int]:
    out = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_bytes()
        except OSError:
            continue
        if int(stat[stat.rfind(b")") + 2 :].split()[1]) == pid:
            out.append(int(entry))
    return out


def _tree(pid: int) -> list[int]:
    """Every descendant of ``pid`` now (children, theirs, ...)."""
    found: list[int] = []
    todo = [pid]
    while todo:
        kids = _children(todo.pop())
        found += kids
        todo += kids
    return found


def _wait_gone(pids: list[int], paths: list[Path], timeout_s: float) -> float:
    """Seconds until no pid is alive and no path exists; fails after ``timeout_s``."""
    t0 = time.monotonic()
    while True:
        alive = [p for p in pids if pid_alive(p)]
        left = [p for p in paths if os.path.lexists(p)]
        elapsed = time.monotonic() - t0
        if not alive and not left:
            return elapsed
        if elapsed > timeout_s:
            names = {p: Path(f"/proc/{p}/cmdline").read_bytes()[:120] for p in alive}
            raise AssertionError(f"after {timeout_s} s: alive {names}, left {left}")
        time.sleep(0.01)


def _session_paths(prefix: str) -> list[Path]:
    tmp = Path("/tmp")
    return [
        *Path("/dev/shm").glob(f"{prefix}*"),
        *tmp.glob(f"{prefix}*.ctl"),
        *tmp.glob(f"{prefix}*.input"),
    ]


# -- the reaper on its own ------------------------------------------------------------------

PARENT = textwrap.dedent(
    """
    import os, subprocess, sys, time
    from pathlib import Path
    from server.ops import orphan_guard

    tmp = Path(sys.argv[1])
    plain = subprocess.Popen(["sleep", "60"])
    # A group of its own with a child in it, and one that ignores SIGTERM.
    group = subprocess.Popen(["sh", "-c", "sleep 60 & wait"], start_new_session=True)
    stubborn = subprocess.Popen(
        [sys.executable, "-c", "import signal, time; "
         "signal.signal(signal.SIGTERM, signal.SIG_IGN); print('ok', flush=True); time.sleep(60)"],
        stdout=subprocess.PIPE,
    )
    assert stubborn.stdout.readline() == b"ok\\n"
    orphan_guard.watch_process(plain.pid)
    orphan_guard.watch_process(group.pid, group=True)
    orphan_guard.watch_process(stubborn.pid)
    (tmp / "ring").write_bytes(b"x")
    (tmp / "folder").mkdir()
    (tmp / "folder" / "native").write_bytes(b"x")
    orphan_guard.watch_path(tmp / "ring")
    orphan_guard.watch_path(tmp / "folder")
    (tmp / "kept").write_bytes(b"x")
    orphan_guard.watch_path(tmp / "kept")
    orphan_guard.forget_path(tmp / "kept")
    if sys.argv[2] == "clean":  # a normal stop: end, wait, forget, exit
        for p in (plain, group, stubborn):
            p.kill()
            p.wait()
            orphan_guard.forget_process(p.pid)
        for name in ("ring", "folder"):
            orphan_guard.forget_path(tmp / name)
        print(orphan_guard.GUARD.reaper_pid, flush=True)
        sys.exit(0)
    print("ready", flush=True)
    time.sleep(60)
    """
)


def _parent(tmp_path: Path, mode: str) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen(
        [sys.executable, "-c", PARENT, str(tmp_path), mode],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        text=True,
    )


def test_a_killed_parents_children_end_and_its_files_go_within_2s(tmp_path: Path) -> None:
    parent = _parent(tmp_path, "kill")
    try:
        assert parent.stdout is not None
        assert parent.stdout.readline() == "ready\n"
        time.sleep(0.2)  # the group's shell has started its sleep
        pids = _tree(parent.pid)
        assert len(pids) >= 5, pids  # sleep, sh, its sleep, stubborn, the reaper
    finally:
        parent.kill()
        parent.wait()
    took = _wait_gone(pids, [tmp_path / "ring", tmp_path / "folder"], ISSUE_BOUND_S)
    assert took < ISSUE_BOUND_S
    assert (tmp_path / "kept").exists()  # forgotten: not the reaper's to remove


def test_a_parent_that_cleaned_up_leaves_no_reaper_and_nothing_removed(tmp_path: Path) -> None:
    parent = _parent(tmp_path, "clean")
    assert parent.stdout is not None
    reaper = int(parent.stdout.readline())
    assert parent.wait(30) == 0
    _wait_gone([reaper], [], ISSUE_BOUND_S)
    for name in ("ring", "folder", "kept"):
        assert (tmp_path / name).exists()


APP_PARENT = textwrap.dedent(
    """
    import os
    from server.game.x11.app import Application

    # What an X11 source starts: a program in a group of its own, with a child.
    app = Application.start(["sh", "-c", "sleep 60 & wait"], {"PATH": os.environ["PATH"]})
    print("ready", flush=True)
    import time; time.sleep(60)
    """
)


def test_a_killed_x11_sources_application_group_ends(tmp_path: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    parent = subprocess.Popen(
        [sys.executable, "-c", APP_PARENT], cwd=ROOT, env=env, stdout=subprocess.PIPE, text=True
    )
    try:
        assert parent.stdout is not None
        assert parent.stdout.readline() == "ready\n"
        time.sleep(0.2)
        pids = _tree(parent.pid)
        assert len(pids) >= 3, pids  # sh, its sleep, the reaper
    finally:
        parent.kill()
        parent.wait()
    assert _wait_gone(pids, [], ISSUE_BOUND_S) < ISSUE_BOUND_S


@pytest.fixture
def sleeper() -> Iterator[subprocess.Popen[bytes]]:
    proc = subprocess.Popen(["sleep", "60"])
    yield proc
    proc.kill()
    proc.wait()


def test_a_pid_given_to_another_process_is_never_signalled(
    sleeper: subprocess.Popen[bytes],
) -> None:
    start = start_time(sleeper.pid)
    assert start is not None
    watch = Watchlist(processes={sleeper.pid: Watched(sleeper.pid, start + 1, False)})
    assert reap(watch, grace_s=0.1) == (0, 0)
    assert sleeper.poll() is None


def test_the_watchlist_follows_the_lines() -> None:
    watch = Watchlist()
    for line in ("pid 10 99 1\n", "pid 11 98 0\n", "-pid 11\n", "path /tmp/a b\n", "path /x\n"):
        watch.feed(line)
    watch.feed("-path /x\n")
    assert watch.processes == {10: Watched(10, 99, True)}
    assert list(watch.paths) == ["/tmp/a b"]
    with pytest.raises(ValueError):
        watch.feed("bogus\n")


# -- the whole stack ------------------------------------------------------------------------


def _start(args: list[str], log: Path) -> subprocess.Popen[bytes]:
    web = log.parent / "web"
    web.mkdir(exist_ok=True)
    (web / "index.html").write_text("<h1>test</h1>")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    with log.open("wb") as out:
        return subprocess.Popen(
            [sys.executable, "-m", "server.cli", *args, "--web-root", str(web)],
            cwd=ROOT,
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
        )


def _wait_for(proc: subprocess.Popen[bytes], log: Path, line: str) -> None:
    deadline = time.monotonic() + UP_TIMEOUT_S
    while line not in log.read_text(errors="replace"):
        assert proc.poll() is None, log.read_text(errors="replace")[-3000:]
        assert time.monotonic() < deadline, f"never said {line!r}"
        time.sleep(0.2)


def _kill_and_check(proc: subprocess.Popen[bytes], log: Path, prefix: str, least: int) -> None:
    pids = _tree(proc.pid)
    paths = _session_paths(prefix)
    assert len(pids) >= least, pids
    assert any(p.parent == Path("/dev/shm") for p in paths), paths
    proc.kill()
    proc.wait()
    try:
        took = _wait_gone(pids, paths, CLEANUP_BOUND_S)
    except AssertionError:
        for pid in pids:  # never leave them to the next test
            if pid_alive(pid):
                os.kill(pid, signal.SIGKILL)
        raise
    print(f"cleaned up in {took:.2f} s")
    assert not _session_paths(prefix), log.read_text(errors="replace")[-2000:]


@pytest.mark.slow
def test_up_killed_leaves_no_process_ring_or_socket(tmp_path: Path) -> None:
    port = _free_port()
    log = tmp_path / "up.log"
    args = ["up", "--host", "127.0.0.1", "--port", str(port), "--metrics-port", "0"]
    up = _start([*args, "--no-audio", *SMALL], log)
    try:
        _wait_for(up, log, "upcast is up")
        # relay, game, worker and the reaper
        _kill_and_check(up, log, f"upcast-{up.pid}-", least=4)
    finally:
        if up.poll() is None:
            up.kill()
            up.wait()
    # The port is free again: the relay is gone.
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", port))


@pytest.mark.slow
def test_serve_killed_leaves_no_process_ring_or_socket(tmp_path: Path) -> None:
    port, http_port = _free_port(), _free_port()
    log = tmp_path / "serve.log"
    args = ["serve", "--sessions", "2", "--host", "127.0.0.1", "--port", str(port)]
    args += ["--admission", "admit"]  # both at once: this test is about the kill
    serve = _start([*args, "--http-port", str(http_port), *SMALL], log)
    try:
        _wait_for(serve, log, "2 sessions up")
        # relay, reaper, and per session: its process, reaper, game, worker
        _kill_and_check(serve, log, f"upcast-serve-{serve.pid}-", least=10)
    finally:
        if serve.poll() is None:
            serve.kill()
            serve.wait()
