"""drvs-server --workers N: N server processes on one address, so one host's cores all serve.

One Python process runs one event loop on at most one core. With --workers N, drvs-server starts N
copies of itself (the same flags, the same port) and watches them: the kernel spreads incoming
connections over them (SO_REUSEPORT), and they share the registry in etcd (--registry etcd://...),
so a camera registers with any of them and is routed by all, and a robot or camera does not care
which one answers. Each worker takes its fused requests' reports on a port of its own. A worker
that dies is started again; SIGTERM or SIGINT stops them all (each drains as a single server does).

Each worker is told its number in DRVS_SERVER_WORKER (0..N-1), which keeps it from starting workers
of its own; with --metrics-port P (P > 0), worker i serves its metrics on P + i.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time

from drvs.core.net import format_address, host_of, parse_address

log = logging.getLogger("drvs.server")

#: The environment variable that marks a worker, and holds its number.
WORKER_ENV = "DRVS_SERVER_WORKER"
#: A worker that dies is restarted after this long (doubled up to RESTART_MAX_S while it keeps dying
#: within STABLE_S of its start).
RESTART_S = 0.5
RESTART_MAX_S = 10.0
STABLE_S = 10.0
#: How long workers have to stop after SIGTERM before they are killed.
STOP_GRACE_S = 10.0


def worker_index() -> int | None:
    """This process's worker number, or None when it is not a worker."""
    text = os.environ.get(WORKER_ENV, "")
    return int(text) if text.isdigit() else None


def reserve_port(listen: str) -> tuple[str, socket.socket]:
    """`listen` with its port fixed: port 0 becomes a free port, held by a bound (not listening)
    socket with SO_REUSEPORT until the workers have bound it too."""
    host, port = parse_address(listen, "listen", allow_port_zero=True)
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
    sock.bind((host_of(listen) or "0.0.0.0", port))
    return format_address(host, sock.getsockname()[1]), sock


def run(argv: list[str], listen: str, workers: int) -> int:
    """Start `workers` copies of `drvs-server argv` on `listen`, keep them running, stop them on
    SIGTERM/SIGINT. Returns the exit status: 0 when they were stopped and all stopped cleanly."""
    address, holder = reserve_port(listen)
    stopping = threading.Event()
    procs: list[subprocess.Popen[bytes] | None] = [None] * workers

    def start(index: int) -> subprocess.Popen[bytes]:
        env = {**os.environ, WORKER_ENV: str(index)}
        # The last --listen wins: every worker binds the one address, its port fixed now.
        proc = subprocess.Popen([sys.executable, "-m", "drvs.server.cli", *argv, "--listen", address], env=env)
        log.info("worker %d started (pid %d) on %s", index, proc.pid, address)
        return proc

    def stop(signum: int, _frame: object) -> None:
        if not stopping.is_set():
            log.info("stopping %d workers (%s)", workers, signal.Signals(signum).name)
        stopping.set()

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    started = [0.0] * workers
    backoff = [RESTART_S] * workers
    due = [0.0] * workers
    try:
        for i in range(workers):
            procs[i], started[i] = start(i), time.monotonic()
        log.info("drvs-server: %d workers on %s", workers, address)
        while not stopping.wait(0.2):
            now = time.monotonic()
            for i, proc in enumerate(procs):
                if proc is not None and proc.poll() is not None:
                    code = proc.returncode
                    backoff[i] = RESTART_S if now - started[i] > STABLE_S else min(RESTART_MAX_S, backoff[i] * 2)
                    log.warning(
                        "worker %d (pid %d) exited with %s; starting it again in %.1f s", i, proc.pid, code, backoff[i]
                    )
                    procs[i], due[i] = None, now + backoff[i]
                elif proc is None and now >= due[i]:
                    procs[i], started[i] = start(i), now
        return _stop_all(procs)
    finally:
        holder.close()
        for proc in procs:
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait()


def _stop_all(procs: list[subprocess.Popen[bytes] | None]) -> int:
    running = [p for p in procs if p is not None and p.poll() is None]
    for proc in running:
        proc.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + STOP_GRACE_S
    status = 0
    for proc in running:
        try:
            code = proc.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            log.error("worker pid %d did not stop within %.0f s; killed", proc.pid, STOP_GRACE_S)
            proc.kill()
            code = proc.wait()
        status = status or (code if code > 0 else 1 if code < 0 else 0)
    return status
