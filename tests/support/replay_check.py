"""``pmon replay`` of a flight's run log, as the firmware and mock flight tests check it."""
from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

from onboard.cli import main


def replay(*argv: str) -> tuple[int, str, str]:
    """``pmon replay ARGV`` in this process: (exit code, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(["replay", *map(str, argv)])
    return rc, out.getvalue(), err.getvalue()


def assert_replays_bit_for_bit(path: Path, min_ticks: int) -> list[dict]:
    """The run log at ``path`` holds at least ``min_ticks`` ticks and replays bit for bit."""
    ticks = [json.loads(line) for line in open(path) if line.strip()]
    assert len(ticks) >= min_ticks
    rc, out, err = replay(path)
    assert (rc, err) == (0, ""), out + err
    assert f"{len(ticks)} ticks replayed bit for bit" in out
    print(out.strip(), f"({sum(t['planned'] for t in ticks)} monitoring, "
          f"{sum('setup' in t['replay'] for t in ticks)} with a setup)")
    return ticks
