"""deploy/smoke.sh's precondition: the ports the stack listens on are free, and if one is
not, which process holds it.

"Address already in use" alone does not say whether another upcast, a previous smoke
run's containers (a killed run leaves its host-network relay listening on 4443) or
something else entirely is in the way; the holder's pid and command line do. The
holder is found as ``ss -p`` finds it: the socket's inode in /proc/net/{tcp,udp}{,6},
then the process with that inode among its file descriptors. A holder in another PID
namespace (or one this user may not read) is reported as unknown.

    python deploy/port_check.py 4443 4444 ...   # exit 0: all free; 1: the takers named
"""

from __future__ import annotations

import os
import socket
import sys
from collections.abc import Iterable
from pathlib import Path

PROC = Path("/proc")
SOCKET_TABLES = ("tcp", "tcp6", "udp", "udp6")
TCP_LISTEN = "0A"  # /proc/net/tcp's state column: what blocks a bind (not TIME_WAIT)


def bind_error(port: int) -> OSError | None:
    """The error binding 127.0.0.1:port gives on TCP or UDP, as the servers bind (with
    SO_REUSEADDR: a previous run's connections in TIME_WAIT do not count)."""
    for kind in (socket.SOCK_STREAM, socket.SOCK_DGRAM):
        with socket.socket(socket.AF_INET, kind) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                probe.bind(("127.0.0.1", port))
            except OSError as exc:
                return exc
    return None


def socket_inodes(port: int, proc: Path = PROC) -> dict[int, str]:
    """Inodes of the sockets bound to ``port`` (TCP: listening ones), with their table."""
    found: dict[int, str] = {}
    for table in SOCKET_TABLES:
        try:
            lines = (proc / "net" / table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            if len(fields) < 10:
                continue
            local_port = int(fields[1].rsplit(":", 1)[1], 16)
            listening = table.startswith("udp") or fields[3] == TCP_LISTEN
            if local_port == port and listening and fields[9] != "0":
                found[int(fields[9])] = table
    return found


def socket_owners(inodes: Iterable[int], proc: Path = PROC) -> dict[int, list[int]]:
    """For each inode, the pids holding it open."""
    wanted = {f"socket:[{inode}]": inode for inode in inodes}
    owners: dict[int, list[int]] = {inode: [] for inode in wanted.values()}
    for entry in proc.iterdir():
        if not entry.name.isdigit():
            continue
        try:
            descriptors = os.listdir(entry / "fd")
        except OSError:
            continue  # gone, or not ours to read
        for fd in descriptors:
            try:
                target = os.readlink(entry / "fd" / fd)
            except OSError:
                continue
            if target in wanted:
                owners[wanted[target]].append(int(entry.name))
    return owners


def command_line(pid: int, proc: Path = PROC) -> str:
    try:
        raw = (proc / str(pid) / "cmdline").read_bytes()
    except OSError:
        return "?"
    return raw.replace(b"\0", b" ").decode(errors="replace").strip()[:200] or "?"


def holders(port: int, proc: Path = PROC) -> list[str]:
    """One line per socket on ``port``: its protocol and the processes that hold it."""
    inodes = socket_inodes(port, proc)
    owners = socket_owners(inodes, proc)
    lines = []
    for inode, table in sorted(inodes.items()):
        pids = sorted(set(owners.get(inode, [])))
        who = "; ".join(f"pid {pid}: {command_line(pid, proc)}" for pid in pids)
        lines.append(f"{table} held by {who or 'a process this user cannot see'}")
    return lines


def report(ports: Iterable[int]) -> list[str]:
    """What stands in the way of each taken port; empty when all are free."""
    problems: list[str] = []
    for port in ports:
        error = bind_error(port)
        if error is None:
            continue
        found = holders(port) or ["held by an unknown process"]
        problems.extend(f"port {port}: {error.strerror}: {line}" for line in found)
    return problems


def main(argv: list[str]) -> int:
    try:
        ports = [int(arg) for arg in argv]
    except ValueError:
        print(f"usage: port_check.py PORT ... (got {argv})", file=sys.stderr)
        return 2
    problems = report(ports)
    for line in problems:
        print(line, file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
