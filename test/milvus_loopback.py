"""A real Milvus standalone server (the PyPI package ``milvus``) that only loopback can reach.

    python test/milvus_loopback.py [--server] -- CMD [ARG ...]

runs CMD in a new network namespace whose only interface is ``lo`` (brought up here); with
--server a Milvus server is started there first, CMD gets ``LLN_MILVUS_URI=milvus://127.0.0.1:19530``
and ``LLN_MILVUS_DATA_DIR`` (its data directory) in its environment, and the server is stopped
after CMD. The exit code is CMD's. This is how the benchmark measures a real server:

    .venv/bin/python test/milvus_loopback.py --server -- .venv/bin/python bench/bench_map.py \\
        --backend sqlite,milvus-lite,milvus --sizes 1000,10000

Why a namespace: ``milvus run standalone`` binds its gRPC (19530), metrics (9091) and internal
ports on every interface, and has no setting for all of them. In a namespace with only ``lo`` no
other machine can reach them, and every process in it (the tests, the nodes, their DDS traffic)
talks over 127.0.0.1 only. The test suite runs its server tests the same way: one test re-runs
pytest in here (test/test_milvus_server.py), and the ``milvus_server`` fixture (conftest.py) starts
the server inside, once per run.

Needs root or unprivileged user namespaces (unshare(2) with CLONE_NEWNET); no ``unshare``/``ip``
binaries: the namespace and ``lo`` are set up with libc calls from this process before it starts
any thread. The server's binaries are unpacked once (~250 MB, ~40 s) into a cache directory
(LLN_MILVUS_CACHE, default ~/.cache/lln_ros/milvus-server-VERSION) that every server shares; each
server gets its own data directory (~140 MB fresh), deleted when it stops.
"""

from __future__ import annotations

import ctypes
import fcntl
import os
import shutil
import socket
import struct
import subprocess
import sys
import tempfile
import time
import urllib.request

CLONE_NEWNET, CLONE_NEWUSER = 0x40000000, 0x10000000
SIOCGIFFLAGS, SIOCSIFFLAGS, IFF_UP = 0x8913, 0x8914, 0x1
PORT = 19530  # inside the namespace nothing else listens, so the default ports are free
METRICS_PORT = 9091


def only_loopback() -> bool:
    """True when this process's network namespace has no interface but lo."""
    # if_nameindex asks the kernel about this namespace (/sys/class/net shows the one sysfs was mounted in)
    try:
        return [name for _, name in socket.if_nameindex()] == ['lo']
    except OSError:
        return False


def enter_loopback_namespace() -> None:
    """Move this (single-threaded) process into a new network namespace and bring lo up.
    Raises OSError when the kernel refuses (not root and no unprivileged user namespaces)."""
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.unshare(CLONE_NEWNET) != 0:
        err = ctypes.get_errno()
        uid, gid = os.getuid(), os.getgid()  # unprivileged: a user namespace first, mapping us to root
        if libc.unshare(CLONE_NEWUSER | CLONE_NEWNET) != 0:
            raise OSError(
                err, f'unshare(CLONE_NEWNET) failed: {os.strerror(err)} (needs root or unprivileged user namespaces)'
            )
        for name, text in (('setgroups', 'deny'), ('uid_map', f'0 {uid} 1'), ('gid_map', f'0 {gid} 1')):
            with open(f'/proc/self/{name}', 'w') as f:
                f.write(text)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        flags = struct.unpack('16sH', fcntl.ioctl(s, SIOCGIFFLAGS, struct.pack('16sH', b'lo', 0)))[1]
        fcntl.ioctl(s, SIOCSIFFLAGS, struct.pack('16sH', b'lo', flags | IFF_UP))
    if not only_loopback():
        raise OSError('new network namespace has interfaces besides lo')


def _bind_reusing(port: int):
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind(('127.0.0.1', port))
        sock.listen()
        return sock
    except OSError:
        sock.close()
        return None


def milvus_version() -> str | None:
    try:
        from importlib.metadata import version

        return version('milvus')
    except Exception:
        return None


class LoopbackMilvus:
    """``milvus run standalone`` on 127.0.0.1:PORT, in this process's namespace (which must have only
    lo: refused otherwise). start() / stop() / restart(); uri; data_dir (kept across restarts)."""

    def __init__(self, data_dir: str | None = None):
        if not only_loopback():
            raise RuntimeError(
                'refusing to start a Milvus server outside a loopback-only network '
                'namespace: it listens on every interface (run under test/milvus_loopback.py)'
            )
        import milvus

        self._milvus = milvus
        self.version = milvus_version()
        self.own_dir = data_dir is None
        self.data_dir = data_dir or tempfile.mkdtemp(prefix='lln_milvus_server_')
        self.uri = f'milvus://127.0.0.1:{PORT}'
        self.server = None
        self.log = os.path.join(self.data_dir, 'logs', 'milvus-stdout.log')
        self._link_binaries()

    def _link_binaries(self) -> None:
        """Unpack the server's binaries once into the shared cache; the data dir links to them."""
        cache = os.environ.get('LLN_MILVUS_CACHE') or os.path.expanduser(
            f'~/.cache/lln_ros/milvus-server-{self.version}'
        )
        os.makedirs(cache, exist_ok=True)
        lock = os.open(os.path.join(cache, '.lock'), os.O_CREAT | os.O_RDWR)
        try:
            fcntl.flock(lock, fcntl.LOCK_EX)  # two runs unpacking at once would corrupt the files
            self._milvus._initialize_data_files(cache)
        finally:
            os.close(lock)
        link = os.path.join(self.data_dir, 'bin')
        if not os.path.islink(link):
            shutil.rmtree(link, ignore_errors=True)
            os.symlink(os.path.join(cache, 'bin'), link)

    def start(self, timeout: float = 180.0) -> 'LoopbackMilvus':
        t = time.monotonic()
        server = self._milvus.MilvusServer(wait_for_started=False)
        # its port probe binds without SO_REUSEADDR, so after a kill (sockets in TIME_WAIT) it would
        # silently move the server to the next port; the server itself (Go) reuses the address
        server.config.try_bind_port = _bind_reusing
        server.set_base_dir(self.data_dir)
        server.config.configs['proxy_port'] = PORT
        server.start()
        self.server = server
        if server.listen_port != PORT or server.webservice_port != METRICS_PORT:
            self.stop()
            raise RuntimeError(
                f'Milvus server got ports {server.listen_port}/{server.webservice_port}, not {PORT}/{METRICS_PORT}'
            )
        url = f'http://127.0.0.1:{server.webservice_port}/healthz'
        while time.monotonic() - t < timeout:
            if server.server_proc.poll() is not None:
                raise RuntimeError(
                    f'Milvus server exited with {server.server_proc.returncode} while starting; log: {self.log_tail()}'
                )
            try:
                with urllib.request.urlopen(url, timeout=2) as resp:
                    if b'OK' in resp.read():
                        self.started_s = time.monotonic() - t
                        return self
            except OSError:
                pass
            time.sleep(0.2)
        self.stop()
        raise TimeoutError(f'Milvus server not healthy after {timeout:.0f} s; log: {self.log_tail()}')

    def stop(self, timeout: float = 30.0, kill: bool = False) -> None:
        """Stop the server: SIGTERM and wait for it (it flushes), SIGKILL after timeout or if kill.
        (MilvusServer.stop waits 1 s only, then kills.)"""
        server, self.server = self.server, None
        if server is None or server.server_proc is None:
            return
        proc = server.server_proc
        proc.kill() if kill else proc.terminate()
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)
        server.server_proc = None
        server.stop()  # closes its log files

    def restart(self, kill: bool = False) -> None:
        self.stop(kill=kill)
        self.start()

    def rss_mb(self) -> float:
        if self.server is None:
            return 0.0
        with open(f'/proc/{self.server.server_proc.pid}/status') as f:
            for line in f:
                if line.startswith('VmRSS:'):
                    return int(line.split()[1]) / 1024
        return 0.0

    def log_tail(self, chars: int = 2000) -> str:
        try:
            with open(self.log, errors='replace') as f:
                return f.read()[-chars:]
        except OSError as e:
            return f'(no log: {e})'

    def close(self) -> None:
        """Stop (SIGKILL: its data is deleted next, and a graceful stop takes up to 30 s) and clean up."""
        self.stop(kill=self.own_dir)
        if self.own_dir:
            shutil.rmtree(self.data_dir, ignore_errors=True)


def drop_maps(server: LoopbackMilvus, db: str, prefix: str) -> list[str]:
    """Drop the collections of database db whose names start with prefix (a test's maps)."""
    from pymilvus import MilvusClient

    client = MilvusClient(uri=server.uri.replace('milvus://', 'http://'), timeout=60)
    try:
        if db not in client.list_databases():
            return []
        client.close()
        client = MilvusClient(uri=server.uri.replace('milvus://', 'http://'), timeout=60, db_name=db)
        names = [n for n in client.list_collections() if n.startswith(prefix)]
        for name in names:
            client.drop_collection(name)
        # and this machine's landmark index files of those maps, so test runs leave none behind
        from lln_ros.mapstore.milvus import MilvusMapStore
        from lln_ros.mapstore.milvus_mixins import landmark_file

        for m in {n.rsplit('_', 1)[0] for n in names}:
            path = landmark_file(f'{server.uri}/{db}?map={m}', MilvusMapStore.default_conf['landmark_dir'])
            if path and os.path.exists(path):
                os.remove(path)
        return names
    finally:
        client.close()


def main(argv: list[str]) -> int:
    server_wanted = '--server' in argv[: argv.index('--')] if '--' in argv else False
    if '--' not in argv or argv.index('--') == len(argv) - 1:
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 2
    cmd = argv[argv.index('--') + 1 :]
    if not only_loopback():
        try:
            enter_loopback_namespace()
        except OSError as e:
            print(f'milvus_loopback: cannot make a loopback-only network namespace: {e}', file=sys.stderr)
            return 3
    env = dict(os.environ)
    server = None
    if server_wanted:
        if milvus_version() is None:
            print(
                'milvus_loopback: the PyPI package `milvus` is not installed (pip install milvus==2.3.5)',
                file=sys.stderr,
            )
            return 3
        server = LoopbackMilvus().start()
        print(
            f'milvus_loopback: Milvus {server.version} on {server.uri} (started in {server.started_s:.1f} s, '
            f'data {server.data_dir})',
            file=sys.stderr,
        )
        env.update(LLN_MILVUS_URI=server.uri, LLN_MILVUS_DATA_DIR=server.data_dir)
    try:
        return subprocess.call(cmd, env=env)
    finally:
        if server is not None:
            server.close()


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
