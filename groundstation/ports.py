"""Which local process holds a port: the one line an error needs when the ground station cannot
have its link (Linux /proc; elsewhere, or without permission, nothing is named).

Two cases the operator meets: a UDP or TCP port this process wants to listen on is bound by
another process (``pmon gcs view`` and a second ``pmon gcs`` on ``udpin:...:14550``); and a TCP
server that takes one client (an ArduPilot serial port over TCP, SITL's ``tcp:5762``) is already
connected to another local process, so the connection opens and nothing ever arrives.
"""
from __future__ import annotations

import os
from pathlib import Path

_STATES = {"0A": "LISTEN", "01": "ESTABLISHED", "07": "UNCONNECTED"}  # UDP bound sockets show 07


def _table(proto: str) -> list[dict]:
    rows = []
    for name in (proto, proto + "6"):
        try:
            lines = Path("/proc/net", name).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            f = line.split()
            if len(f) < 10:
                continue
            rows.append({"local_port": int(f[1].rsplit(":", 1)[1], 16),
                         "remote_port": int(f[2].rsplit(":", 1)[1], 16),
                         "state": f[3], "inode": f[9]})
    return rows


def _owners(inodes: set[str]) -> dict[str, int]:
    """socket inode -> pid, for the processes this user may look into."""
    found: dict[str, int] = {}
    if not inodes:
        return found
    for pid_dir in Path("/proc").iterdir():
        if not pid_dir.name.isdigit():
            continue
        try:
            for fd in (pid_dir / "fd").iterdir():
                try:
                    target = os.readlink(fd)
                except OSError:
                    continue
                if target.startswith("socket:[") and target[8:-1] in inodes:
                    found[target[8:-1]] = int(pid_dir.name)
        except OSError:
            continue
    return found


def describe(pid: int) -> str:
    """``pid 1234 (pmon gcs view --port 8350)``: the process's command line, shortened."""
    try:
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        words = [a.decode(errors="replace") for a in argv if a]
    except OSError:
        words = []
    # python -m onboard.cli gcs ...  /  .../bin/pmon gcs ...: the program as the user typed it
    for i, w in enumerate(words):
        if w in ("onboard.cli", "groundstation.cli") or w.endswith(("/pmon", "/pmon-gcs")):
            words = ["pmon"] + words[i + 1:]
            break
    text = " ".join(words)[:80] or "?"
    return f"pid {pid} ({text})"


def bound_by(proto: str, port: int) -> str | None:
    """Who listens on local ``port`` (``proto`` "udp" or "tcp"), or None."""
    me = os.getpid()
    rows = [r for r in _table(proto) if r["local_port"] == port and (proto == "udp" or r["state"] == "0A")]
    owners = _owners({r["inode"] for r in rows})
    pids = sorted({p for p in owners.values() if p != me})
    return ", ".join(describe(p) for p in pids) or None


def connected_to(port: int) -> str | None:
    """Which other local process has a TCP connection to remote ``port`` open, or None."""
    me = os.getpid()
    rows = [r for r in _table("tcp") if r["remote_port"] == port and r["state"] == "01"]
    owners = _owners({r["inode"] for r in rows})
    pids = sorted({p for p in owners.values() if p != me})
    return ", ".join(describe(p) for p in pids) or None


def url_port(url: str) -> tuple[str, int] | None:
    """("udp"|"tcp", port) of a pymavlink URL, or None (serial, unparsable)."""
    kind, _, rest = url.partition(":")
    port = rest.rpartition(":")[2]
    if not port.isdigit():
        return None
    if kind in ("udpin", "udp", "udpout", "udpbcast"):
        return "udp", int(port)
    if kind in ("tcp", "tcpin"):
        return "tcp", int(port)
    return None


def silent_link_hint(url: str) -> str:
    """Why a link that opened heard nothing, when another local process holds its peer: the
    one-client TCP port case. Empty when nothing is known."""
    kp = url_port(url)
    if kp is None or kp[0] != "tcp" or not url.startswith("tcp:"):
        return ""
    other = connected_to(kp[1])
    if other is None:
        return ""
    return (f"; {other} is connected to port {kp[1]} too, and a serial port over TCP (ArduPilot, "
            f"SITL) serves one client: share that process's link instead (pmon gcs hub, "
            f"docs/OPERATING.md), or stop it")


def in_use_hint(url: str) -> str:
    """Who holds the local port a listening URL (udpin:, tcpin:) wants. Empty when unknown."""
    kp = url_port(url)
    if kp is None or not url.startswith(("udpin:", "tcpin:")):
        return ""
    other = bound_by(*kp)
    return f" (held by {other})" if other else ""
