"""Programs the tests run as processes: their stdout read on a thread, and a clean stop."""
from __future__ import annotations

import json
import queue
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


class LineReader:
    """Collects a subprocess's stdout lines on a thread; wait_for() matches a regex."""

    def __init__(self, proc: subprocess.Popen):
        self.proc = proc
        self.lines: list[str] = []
        self._q: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        for line in self.proc.stdout:
            self._q.put(line.rstrip("\n"))

    def wait_for(self, pattern: str, timeout: float, since: int = 0, check=None) -> re.Match:
        """First line from index `since` matching pattern (and check(match), if given)."""
        rx = re.compile(pattern)
        deadline = time.monotonic() + timeout
        while True:
            for line in self.lines[since:]:
                if (m := rx.search(line)) and (check is None or check(m)):
                    return m
            since = len(self.lines)
            remaining = deadline - time.monotonic()
            exited = self.proc.poll() is not None and self._q.empty()
            if remaining <= 0 or exited:
                tail = "\n".join(self.lines[-30:])
                raise AssertionError(f"no line matching {pattern!r}; last lines:\n{tail}")
            try:
                self.lines.append(self._q.get(timeout=min(remaining, 0.2)))
            except queue.Empty:
                pass


def stop_process(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=5)


def run_json(module: str, *args: str, timeout: float) -> dict:
    """``python -m MODULE ARGS`` from the repository's root, as a user runs a bench; its last
    stdout line parsed as JSON (the benches' figures)."""
    done = subprocess.run([sys.executable, "-m", module, *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])
