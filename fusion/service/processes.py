"""Child processes of ``armfusion fleet`` and ``armfusion demo``: each node an
``armfusion`` subcommand in its own process, started, watched and stopped cleanly.

A child is started with ``python -m armfusion.fusion.cli …`` (the interpreter running this one), in
its own process group, and on Linux asks the kernel to send it SIGTERM when its parent
dies (``PR_SET_PDEATHSIG``): even a parent killed with SIGKILL leaves no orphan.
:meth:`Children.stop_all` sends SIGINT (the nodes' clean stop), then SIGKILL to whatever
is still running after a grace period.
"""

from __future__ import annotations

import ctypes
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:  # runs in the child between fork and exec
    os.setpgrp()
    signal.signal(signal.SIGINT, signal.SIG_DFL)  # even when this process ignores it (a background job)
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
        except OSError:
            pass


def armfusion_argv(*args: str) -> list[str]:
    """The command line of an ``armfusion`` subcommand run by this interpreter."""
    return [sys.executable, "-m", "armfusion.fusion.cli", *args]


@dataclass
class Child:
    """One node's process; its stderr lines are kept (and can be waited for)."""

    name: str
    proc: subprocess.Popen
    stdout_path: Path | None
    lines: list[str] = field(default_factory=list)
    new_lines: queue.Queue = field(default_factory=queue.Queue)

    def wait_for_line(self, text: str, timeout_s: float) -> bool:
        """Wait until a stderr line contains ``text``; False on timeout or when the process ended."""
        deadline = time.monotonic() + timeout_s
        if any(text in ln for ln in self.lines):
            return True
        while time.monotonic() < deadline:
            try:
                line = self.new_lines.get(timeout=0.1)
            except queue.Empty:
                if self.proc.poll() is not None and self.new_lines.empty():
                    return False
                continue
            if line is None:
                return False
            if text in line:
                return True
        return False

    def stderr_tail(self, n: int = 5) -> str:
        return "\n".join(self.lines[-n:])

    @property
    def running(self) -> bool:
        return self.proc.poll() is None


class Children:
    """The processes a command started; ``with Children() as ch:`` stops them all at exit."""

    def __init__(self, workdir: Path):
        self.workdir = Path(workdir)
        self.children: list[Child] = []

    def start(self, name: str, args: list[str], *, stdout: bool = True) -> Child:
        """Start ``armfusion ARGS`` as ``name``; its stdout goes to ``<workdir>/<name>.out``."""
        self.workdir.mkdir(parents=True, exist_ok=True)
        out_path = self.workdir / f"{name}.out" if stdout else None
        out = open(out_path, "wb") if out_path else subprocess.DEVNULL  # noqa: SIM115 - closed below
        env = {**os.environ, "PYTHONUNBUFFERED": "1", "COLUMNS": "100", "TERM": "dumb"}
        proc = subprocess.Popen(armfusion_argv(*args), stdout=out, stderr=subprocess.PIPE,
                                stdin=subprocess.DEVNULL, preexec_fn=_die_with_parent, env=env)
        if out_path:
            out.close()
        child = Child(name, proc, out_path)
        threading.Thread(target=self._pump, args=(child,), daemon=True).start()
        self.children.append(child)
        return child

    @staticmethod
    def _pump(child: Child) -> None:
        for raw in child.proc.stderr:
            line = raw.decode(errors="replace").rstrip()
            child.lines.append(line)
            child.new_lines.put(line)
        child.new_lines.put(None)

    def stop(self, child: Child, grace_s: float = 15.0) -> int:
        """SIGINT, then SIGKILL after ``grace_s``; the exit code."""
        if child.proc.poll() is None:
            try:
                child.proc.send_signal(signal.SIGINT)
                return child.proc.wait(grace_s)
            except subprocess.TimeoutExpired:
                child.proc.kill()
        return child.proc.wait()

    def stop_all(self, grace_s: float = 15.0, children: list[Child] | None = None) -> None:
        """SIGINT to every child (or to ``children``) at once, then SIGKILL to what still runs
        after ``grace_s``."""
        group = self.children if children is None else children
        for c in group:
            if c.proc.poll() is None:
                c.proc.send_signal(signal.SIGINT)
        deadline = time.monotonic() + grace_s
        for c in group:
            try:
                c.proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                c.proc.kill()
                c.proc.wait()

    def __enter__(self) -> Children:
        return self

    def __exit__(self, *exc) -> None:
        self.stop_all()


def free_loopback_port() -> int:
    """A TCP port on 127.0.0.1 that is free now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def cpu_seconds(pid: int) -> float | None:
    """CPU seconds (user + system) a process has used so far (Linux /proc), or None."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return round((int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK"), 1)
    except (OSError, ValueError, IndexError):
        return None
