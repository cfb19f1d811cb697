"""Where jobs run: in this process, or on Dask distributed [Dask 2024, "Futures"; "LocalCluster"].

A job is a picklable value and a module-level function of it (a reference: scene, resolution,
frame, seed; a sweep point: technique, scene, parameters). :func:`open_executor` picks where:

* neither ``workers`` nor a scheduler: the embedded default, each job in this process, in order;
* ``workers=N``: a :class:`distributed.LocalCluster` of N worker processes with one task thread
  each, whose Dr.Jit thread pools share this machine's cores (``cores // N`` threads each);
* ``scheduler="tcp://HOST:8786"`` (or ``$SHADOWLAB_SCHEDULER``): an existing cluster.

Jobs go to the cluster through ``Client.submit`` and come back in submission order, so a result
does not depend on which worker ran it or when. Each job selects the Mitsuba variant in its
worker (:func:`shadowlab.backend.init`); each worker keeps its own kernel cache (:mod:`.preload`).
A worker that dies mid-job has its job re-run elsewhere by the scheduler; jobs that write the
reference store are written to be re-run (the store's lock and atomic save, and a run id).
"""

from __future__ import annotations

import logging
import os
import socket
import struct
import subprocess
import sys
import threading
import time
import uuid
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Sequence

from distributed import Client, LocalCluster, as_completed
from distributed.comm.addressing import parse_host_port
from tqdm import tqdm

from .. import backend
from ..errors import EnvironmentProblem, InputError, ShadowlabError

__all__ = ["Executor", "Embedded", "DaskExecutor", "open_executor", "SCHEDULER_ENV", "PRELOAD", "SCHEMES",
           "run_id"]

SCHEDULER_ENV = "SHADOWLAB_SCHEDULER"
#: set in the workers of ``--workers N`` (preload.py: they ignore SIGINT)
LOCAL_WORKER_ENV = "SHADOWLAB_LOCAL_WORKER"
#: the -W option given to multiprocessing's resource tracker (see :func:`_local`)
TRACKER_NOISE = "ignore:resource_tracker:UserWarning"
#: the worker preload, by file path (it must run before Dr.Jit is imported, so not as a module)
PRELOAD = str(Path(__file__).with_name("preload.py"))
#: address schemes of Dask's communication layer
SCHEMES = ("tcp", "tls", "inproc", "ucx", "ws", "wss")
#: seconds to reach a scheduler and hear its handshake: ``--scheduler`` exits 3 within them
CONNECT_TIMEOUT_S = 10
#: seconds a scheduler has, once connected, to send its handshake (a real one sends it at once)
HANDSHAKE_TIMEOUT_S = 5
#: seconds to wait for the first worker of a scheduler that has none yet
WORKERS_TIMEOUT_S = 30


def run_id() -> str:
    """A fresh id for one command's jobs (recorded with what they store, so that a job re-run after
    its worker died recognises its own earlier result)."""
    return uuid.uuid4().hex[:16]


class Failed:
    """A job's :class:`~shadowlab.errors.ShadowlabError` (bad input, the environment), carried back
    as its result: the command ends with that one line and exit code, as in one process, and the
    worker does not log the task as a failed computation with a traceback (Dask's "Compute Failed",
    printed on the user's terminal). Any other exception is a bug and stays a failed task."""

    def __init__(self, error: ShadowlabError):
        self.error = error


def _call(fn: Callable, item, variant: str, threads: int | None):
    """A job on a worker: select the variant (once per process) and the thread count, then run."""
    try:
        backend.init(variant, threads=threads)
        return fn(item)
    except ShadowlabError as e:
        return Failed(e)


class Executor:
    """Runs ``fn`` over jobs; :meth:`map` returns the results in the order of ``items``."""

    kind = "embedded"
    workers = 1

    def map(self, fn: Callable, items: Sequence, *, desc: str = "jobs", progress: bool = False) -> list:
        raise NotImplementedError

    def describe(self) -> dict:
        """What ran the jobs (recorded in outputs)."""
        return {"kind": self.kind, "workers": self.workers}

    def close(self) -> None:
        pass


class Embedded(Executor):
    """Each job in this process, in order (the default)."""

    def map(self, fn, items, *, desc="jobs", progress=False):
        out = []
        with tqdm(total=len(items), desc=desc, unit="job", disable=not progress, leave=False) as bar:
            for x in items:
                out.append(fn(x))
                bar.update(1)
        return out


class DaskExecutor(Executor):
    """Jobs on a Dask cluster through a :class:`distributed.Client`."""

    kind = "dask"

    def __init__(self, client, *, cluster=None, threads: int | None = None, address: str | None = None):
        self.client, self.cluster, self.threads, self.address = client, cluster, threads, address
        self.variant = backend.init()
        self.workers = len(client.scheduler_info().get("workers", {})) or 1

    def map(self, fn, items, *, desc="jobs", progress=False):
        futs = [self.client.submit(_call, fn, x, self.variant, self.threads, pure=False,
                                   key=f"shadowlab-{desc.replace(' ', '_')}-{i}-{uuid.uuid4().hex[:8]}")
                for i, x in enumerate(items)]
        try:
            with tqdm(total=len(futs), desc=f"{desc} ({self.workers} workers)", unit="job", disable=not progress,
                      leave=False) as bar:
                for f in as_completed(futs):
                    if f.status == "error":
                        raise f.exception()
                    if isinstance(f.result(), Failed):   # the first job with the user's error ends the command
                        raise f.result().error
                    bar.update(1)
            return [f.result() for f in futs]
        finally:
            for f in futs:
                if not f.done():
                    f.cancel()

    def describe(self):
        return {"kind": self.kind, "workers": self.workers,
                "scheduler": self.address or "LocalCluster (processes)", "threads_per_worker": self.threads}

    def close(self):
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()


def check_address(address: str) -> str:
    """``tcp://HOST:PORT`` and the other schemes of :data:`SCHEMES`; anything else is an InputError."""
    scheme, sep, rest = address.partition("://")
    if not sep or scheme not in SCHEMES or not rest:
        raise InputError(f"--scheduler {address!r}: not a Dask scheduler address; give "
                         f"{' or '.join(s + '://HOST:PORT' for s in SCHEMES[:2])} (e.g. tcp://10.0.0.5:8786)")
    return address


def check_workers(workers: int | None) -> int | None:
    if workers is not None and workers < 1:
        raise InputError(f"--workers {workers}: give 1 or more worker processes (or leave --workers out to run "
                         "in this process)")
    return workers


def threads_per_worker(workers: int, cores: int | None = None) -> int:
    """Dr.Jit threads of each of ``workers`` local processes so that together they use the cores
    once: ``max(1, cores // workers)``.

    >>> threads_per_worker(2, cores=2), threads_per_worker(3, cores=16), threads_per_worker(4, cores=2)
    (1, 5, 1)
    """
    return max(1, (cores or os.cpu_count() or 1) // workers)


@contextmanager
def open_executor(workers: int | None = None, scheduler: str | None = None):
    """The executor for ``--workers`` / ``--scheduler`` (``$SHADOWLAB_SCHEDULER``), closed on exit.

    Bad options are an InputError (exit 2); a scheduler that cannot be reached is an
    EnvironmentProblem (exit 3) naming the address.

    >>> with open_executor() as ex:
    ...     ex.map(abs, [-2, 3])
    [2, 3]
    """
    check_workers(workers)
    if workers is not None and scheduler:
        raise InputError("--workers and --scheduler: give one (--workers N starts a local cluster, --scheduler "
                         "uses an existing one)")
    address = scheduler or (None if workers is not None else os.environ.get(SCHEDULER_ENV) or None)
    if address is None and workers is None:
        ex = Embedded()
    elif address is not None:
        ex = _connect(check_address(address))
    else:
        ex = _local(workers)
    try:
        yield ex
    finally:
        ex.close()


def _unreachable(address: str, why: str) -> EnvironmentProblem:
    return EnvironmentProblem(f"cannot reach the Dask scheduler at {address} ({why}); start one there (`dask "
                              f"scheduler`) or fix --scheduler / ${SCHEDULER_ENV}")


def _recv_some(sock: socket.socket, n: int, deadline: float) -> bytes:
    """Up to ``n`` bytes, as many as arrive before ``deadline`` (or the peer closes)."""
    data = b""
    while len(data) < n:
        left = deadline - time.monotonic()
        if left <= 0:
            break
        sock.settimeout(left)
        try:
            chunk = sock.recv(n - len(data))
        except (socket.timeout, TimeoutError):
            break
        if not chunk:
            break
        data += chunk
    return data


def is_dask_greeting(head: bytes) -> bool:
    """Whether the first 16 bytes a server sent open a Dask TCP message: its total size (uint64,
    little-endian) then its frame count, both small for the handshake a scheduler sends on accept.

    >>> is_dask_greeting(struct.pack("<QQ", 120, 1)), is_dask_greeting(b"HTTP/1.1 400 Bad")
    (True, False)
    """
    if len(head) < 16:
        return False
    total, frames = struct.unpack("<QQ", head[:16])
    return 0 < frames <= 64 and 8 * (frames + 1) <= total <= 1 << 20


def probe_tcp(address: str, timeout: float = CONNECT_TIMEOUT_S) -> None:
    """Check within ``timeout`` seconds that a Dask scheduler listens at the ``tcp://`` ``address``:
    it must accept the connection and send the handshake Dask's comm layer sends on accept. A
    closed port, a server that accepts and stays silent, and another service (HTTP, SSH) each
    raise :class:`EnvironmentProblem` (exit 3) saying which. Dask's own client waits forever on a
    silent server and reads another service's bytes as a frame size (an "out of memory" of
    exabytes), so this runs first."""
    t0 = time.monotonic()
    try:
        host, port = parse_host_port(address.partition("://")[2], 8786)
        sock = socket.create_connection((host, port), timeout=timeout)
    except (OSError, ValueError) as e:
        raise _unreachable(address, f"{type(e).__name__}: {e}") from None
    wait = min(HANDSHAKE_TIMEOUT_S, max(timeout - (time.monotonic() - t0), 0.5))
    with sock:
        head = _recv_some(sock, 16, time.monotonic() + wait)
    if not head:
        raise _unreachable(address, f"a program accepts connections on that port but sent no Dask handshake within "
                                    f"{wait:g} s: a stalled scheduler, or another service")
    if not is_dask_greeting(head):
        raise EnvironmentProblem(f"the program listening at {address} is not a Dask scheduler (it answered "
                                 f"{head[:16]!r}); give the address of a running `dask scheduler` with --scheduler "
                                 f"/ ${SCHEDULER_ENV}, or stop the other program using that port")


def _within(fn: Callable, seconds: float, on_timeout: Callable[[], BaseException]):
    """``fn()`` in a daemon thread, given at most ``seconds``: its result, its exception, or
    ``on_timeout()`` raised when it has not returned by then (the thread is left behind)."""
    box: dict = {}

    def run():
        try:
            box["value"] = fn()
        except BaseException as e:  # noqa: BLE001 - handed to the caller's thread
            box["error"] = e

    t = threading.Thread(target=run, name="shadowlab-connect", daemon=True)
    t.start()
    t.join(max(seconds, 0.1))
    if t.is_alive():
        raise on_timeout()
    if "error" in box:
        raise box["error"]
    return box["value"]


def _connect(address: str) -> DaskExecutor:
    """A client of the scheduler at ``address``: exit 3 within :data:`CONNECT_TIMEOUT_S` if it
    cannot be reached or does not speak Dask, or if it has no worker after :data:`WORKERS_TIMEOUT_S`."""
    t0 = time.monotonic()
    if address.startswith("tcp://"):
        probe_tcp(address, CONNECT_TIMEOUT_S)
    left = CONNECT_TIMEOUT_S - (time.monotonic() - t0)
    try:
        client = _within(lambda: Client(address, timeout=max(left, 1.0)), left + 1.0,
                         lambda: _unreachable(address, f"no Dask handshake within {CONNECT_TIMEOUT_S:g} s"))
    except EnvironmentProblem:
        raise
    except (OSError, TimeoutError) as e:
        raise _unreachable(address, f"{type(e).__name__}: {e}") from None
    except TypeError as e:  # tls:// without Dask's TLS settings: "TLS expects a `ssl_context` ..."
        raise EnvironmentProblem(f"cannot connect to the Dask scheduler at {address}: {e}; give Dask's TLS settings "
                                 "(distributed.comm.tls.ca-file, .client.cert, .client.key in Dask's configuration) "
                                 "or use the scheduler's tcp:// address") from None
    except Exception as e:  # noqa: BLE001 - e.g. MemoryError: another protocol's bytes read as a frame size
        raise _unreachable(address, f"it does not answer as a Dask scheduler ({type(e).__name__})") from None
    try:
        _within(lambda: client.wait_for_workers(1, timeout=WORKERS_TIMEOUT_S), WORKERS_TIMEOUT_S + 5.0,
                lambda: TimeoutError())
    except (OSError, TimeoutError):
        client.close(timeout=2)
        raise EnvironmentProblem(f"the Dask scheduler at {address} has no workers (none joined within "
                                 f"{WORKERS_TIMEOUT_S:g} s), so no job could run; start some (`dask worker "
                                 f"{address}`)") from None
    return DaskExecutor(client, address=address, threads=None)


def visible_gpus() -> list[str]:
    """The GPU ids this process may use: ``$CUDA_VISIBLE_DEVICES`` if set, else those ``nvidia-smi -L``
    lists ([] on a machine without)."""
    env = os.environ.get("CUDA_VISIBLE_DEVICES")
    if env is not None:
        return [g.strip() for g in env.split(",") if g.strip()]
    try:
        out = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return []
    return (
        [str(i) for i, l in enumerate(out.stdout.splitlines()) if l.startswith("GPU ")] if out.returncode == 0 else []
    )


def _local(workers: int) -> DaskExecutor:
    env = {}
    if backend.init().startswith("cuda"):   # one worker per GPU, round robin (the preload sets CUDA_VISIBLE_DEVICES)
        env["SHADOWLAB_WORKER_GPUS"] = ",".join(visible_gpus())
    env[LOCAL_WORKER_ENV] = "1"   # the preload makes these workers ignore SIGINT: Ctrl-C is this process's
    # multiprocessing's resource tracker (a child started with our -W options) reports the semaphores of a
    # worker the cluster's close had to stop mid-job, and unlinks them: after a Ctrl-C that line is only noise
    if TRACKER_NOISE not in sys.warnoptions:
        sys.warnoptions.append(TRACKER_NOISE)
    # CRITICAL: after a Ctrl-C a worker whose scheduler closed first logs its failed heartbeat at ERROR,
    # with a traceback, on the terminal (seen once under load); a job's own errors reach this process as
    # the future's exception, which the command reports in one line
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0",
                           preload=[PRELOAD], silence_logs=logging.CRITICAL, env=env)
    return DaskExecutor(Client(cluster), cluster=cluster, threads=threads_per_worker(workers))
