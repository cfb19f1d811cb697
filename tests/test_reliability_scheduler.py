"""``--scheduler`` at a port where no Dask scheduler answers (issue 27, "Hangs").

The docs promise exit 3 within 10 s for a scheduler that cannot be reached. Dask's own client
waits forever on a server that accepts the connection and never answers, and reads another
service's bytes (an HTTP reply) as a frame size, failing with an "out of memory" of exabytes.
Each case here is a real socket server in a thread of this test and a real ``shadowlab`` process:
``reference``, ``sweep`` and ``fit`` must exit 3 within the limit with one line naming the
address and what is wrong there; a real Dask scheduler still passes the check.
"""

import logging
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from shadowlab.cluster import executor as ex_mod

ROOT = Path(__file__).resolve().parents[1]


class _Server:
    """A TCP server on 127.0.0.1 that accepts every connection and then stays silent
    (``reply=None``) or sends ``reply`` and keeps the connection open."""

    def __init__(self, reply: bytes | None = None):
        self.reply, self.conns = reply, []
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(16)
        self.address = f"tcp://127.0.0.1:{self.sock.getsockname()[1]}"
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self):
        while True:
            try:
                c, _ = self.sock.accept()
            except OSError:
                return
            self.conns.append(c)
            if self.reply is not None:
                c.sendall(self.reply)

    def close(self):
        for c in self.conns:
            c.close()
        self.sock.close()


@pytest.fixture
def silent():
    s = _Server()
    yield s
    s.close()


# shadowlab's main, with the seconds spent reaching the scheduler (executor._connect) printed last on stderr
_TIMED = """import sys, time
import shadowlab.cli as c
from shadowlab.cluster import executor as E
spent, connect = [0.0], E._connect
def timed(address):
    t = time.monotonic()
    try:
        return connect(address)
    finally:
        spent[0] += time.monotonic() - t
E._connect = timed
rc = c.main(sys.argv[1:])
print(f"seconds {spent[0]:.2f}", file=sys.stderr)
sys.exit(rc)
"""


def _shadowlab(args, timeout=60):
    """Run ``shadowlab ARGS`` in a new process: (exit code, stdout, stderr, seconds spent reaching the
    scheduler). A process still running after ``timeout`` seconds fails the test as a hang."""
    code = _TIMED
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p))
    env.pop(ex_mod.SCHEDULER_ENV, None)
    try:
        r = subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True,
                           timeout=timeout, cwd=ROOT, env=env)
    except subprocess.TimeoutExpired:
        pytest.fail(f"shadowlab {' '.join(map(str, args))} still running after {timeout} s (a hang)")
    lines = r.stderr.strip().splitlines()
    seconds = float(lines[-1].split()[1])
    return r.returncode, r.stdout, "\n".join(lines[:-1]), seconds


COMMANDS = {
    "reference": ["reference", "contact", "-r", "8x8", "--max-rounds", "2", "--spp", "0"],
    "sweep": ["sweep", "contact", "-t", "pcf", "-p", "softness=1:2:2", "--out", "{tmp}/sweep"],
    "fit": ["fit", "contact", "-t", "pcf", "-p", "softness", "--out", "{tmp}/fit"],
}


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_a_port_that_accepts_and_never_answers_exits_3_within_10_s(command, silent, tmp_path):
    args = [a.replace("{tmp}", str(tmp_path)) for a in COMMANDS[command]]
    rc, out, err, seconds = _shadowlab([*args, "--scheduler", silent.address])
    assert rc == 3, (out, err)
    assert 0 <= seconds <= ex_mod.CONNECT_TIMEOUT_S, seconds   # the promise: given up within 10 s
    lines = err.splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert f"cannot reach the Dask scheduler at {silent.address}" in err and "no Dask handshake" in err, err
    assert "--scheduler" in err                                    # the fix names the option
    assert not (tmp_path / "sweep").exists() and not (tmp_path / "fit").exists()


def test_another_service_on_the_port_is_named_not_out_of_memory(tmp_path):
    http = _Server(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\nConnection: close\r\n\r\n")
    try:
        rc, out, err, seconds = _shadowlab([*COMMANDS["reference"], "--scheduler", http.address])
    finally:
        http.close()
    assert rc == 3 and 0 <= seconds <= ex_mod.CONNECT_TIMEOUT_S, (out, err, seconds)
    assert "out of memory" not in err and "Traceback" not in err and len(err.splitlines()) == 1, err
    assert f"the program listening at {http.address} is not a Dask scheduler" in err and "HTTP/1.1" in err, err


def test_the_probe_knows_a_real_scheduler_and_garbage_in_process():
    from distributed import LocalCluster
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tcp://", dashboard_address=":0",
                      silence_logs=logging.ERROR) as cluster:
        t = time.monotonic()
        ex_mod.probe_tcp(cluster.scheduler_address, timeout=5)     # no exception: the handshake came
        assert time.monotonic() - t < 5
    garbage = _Server(os.urandom(64) + b"\xff" * 16)
    try:
        with pytest.raises(ex_mod.EnvironmentProblem, match="is not a Dask scheduler"):
            ex_mod.probe_tcp(garbage.address, timeout=5)
    finally:
        garbage.close()


def test_a_scheduler_without_workers_exits_3_instead_of_waiting_forever(monkeypatch):
    """A real scheduler that no worker has joined would queue the jobs forever."""
    from distributed import LocalCluster
    monkeypatch.setattr(ex_mod, "WORKERS_TIMEOUT_S", 1)
    with LocalCluster(n_workers=0, processes=False, protocol="tcp://", dashboard_address=":0",
                      silence_logs=logging.ERROR) as cluster:
        with pytest.raises(ex_mod.EnvironmentProblem, match="has no workers .*`dask worker "):
            with ex_mod.open_executor(scheduler=cluster.scheduler_address):
                pass


def test_tls_without_dask_tls_settings_names_them(silent):
    address = silent.address.replace("tcp://", "tls://")
    with pytest.raises(ex_mod.EnvironmentProblem, match="give Dask's TLS settings"):
        with ex_mod.open_executor(scheduler=address):
            pass
