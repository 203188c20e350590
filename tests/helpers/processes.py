"""The processes a test session started: none may outlive it (a leftover child holding the runner's
output open keeps the shell that ran `make test` waiting after pytest has exited)."""

from __future__ import annotations

import os
from pathlib import Path


def children(pid: int | None = None) -> dict[int, str]:
    """The live child processes of `pid` (default: this process), by pid, with their command lines."""
    parent = os.getpid() if pid is None else pid
    found: dict[int, str] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmdline = (entry / "cmdline").read_bytes()
        except OSError:  # ended while we looked
            continue
        # pid (comm) state ppid ...: comm may hold spaces and parentheses, so split after its last ')'
        fields = stat[stat.rindex(")") + 2 :].split()
        if int(fields[1]) == parent and fields[0] != "Z":
            found[int(entry.name)] = cmdline.replace(b"\0", b" ").decode(errors="replace").strip()
    return found
