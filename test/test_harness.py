"""The test harness itself: children of the test process must start cleanly even while gRPC, loaded
by the Milvus tests in this same process, has threads running (the cause of the CI flake of issue 12)."""

from __future__ import annotations

import importlib.util
import sys
import threading

import pytest

from ros_harness import RosProcess

HAVE_MILVUS = importlib.util.find_spec('pymilvus') is not None and importlib.util.find_spec('milvus_lite') is not None


@pytest.mark.skipif(not HAVE_MILVUS, reason='pymilvus / milvus-lite not installed (requirements.txt)')
def test_children_start_without_fork_handlers_while_grpc_is_busy(tmp_path, capfd):
    from pymilvus import MilvusClient

    client = MilvusClient(str(tmp_path / 'busy.db'))
    client.create_collection('busy', dimension=8)
    client.insert('busy', [{'id': i, 'vector': [0.1 * i] * 8} for i in range(50)])
    stop = threading.Event()

    def hammer():
        while not stop.is_set():
            client.search('busy', [[0.1] * 8], limit=3)

    worker = threading.Thread(target=hammer, daemon=True)
    worker.start()
    exe = tmp_path / 'child'
    exe.write_text(f'#!{sys.executable}\nimport sys\nprint("up", sys.argv[1:])\n')
    exe.chmod(0o755)
    try:
        procs = [RosProcess(exe, ['-p', f'i:={i}'], {}, tmp_path / f'child{i}.log') for i in range(30)]
        codes = [p.proc.wait(30) for p in procs]
    finally:
        stop.set()
        worker.join(10)
        client.close()
    err = capfd.readouterr().err
    # fork() with gRPC threads live makes gRPC print this for every child, and some children die
    # before exec; vfork() (no preexec_fn) runs no fork handlers at all
    assert 'fork_posix' not in err and 'skipping fork() handlers' not in err, err[-2000:]
    assert codes == [0] * 30, [p.log() for p in procs if p.proc.returncode]
    assert all("up ['--ros-args', '-p'" in p.log() for p in procs)


def test_concurrent_test_runs_get_disjoint_dds_domains(tmp_path):
    """Two pytest processes on one host (two suites, or a helper's tests beside CI) hold different
    domain slots, so their nodes never discover each other."""
    import ast
    import subprocess

    import ros_harness

    here = {int(ros_harness.ros_env(tmp_path)['ROS_DOMAIN_ID']) for _ in range(30)}
    code = (
        'import sys; sys.path.insert(0, sys.argv[1]); import ros_harness, pathlib; '
        'print(sorted({int(ros_harness.ros_env(pathlib.Path(sys.argv[2]))["ROS_DOMAIN_ID"]) for _ in range(30)}))'
    )
    out = subprocess.run(
        [sys.executable, '-c', code, str(ros_harness.REPO / 'test'), str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    there = set(ast.literal_eval(out.stdout.strip().splitlines()[-1]))
    assert len(here) == ros_harness.DOMAINS_PER_SLOT and len(there) == ros_harness.DOMAINS_PER_SLOT
    assert not here & there, (sorted(here), sorted(there))
