"""Shared fixtures. Real data lives in ../shared/data next to the repo; tests that need it skip
with a reason when it is absent (a user's fresh machine)."""

import os
import signal
from pathlib import Path

import numpy as np
import pytest

# Children of the test run must take Ctrl-C as at a terminal, even when the run was started in the
# background (`cmd &` makes a non-interactive shell ignore SIGINT, and an ignored signal survives exec).
# A handler does not survive exec, so installing Python's own handler here gives every child the
# default disposition. This replaces a preexec_fn in the harness: preexec_fn makes subprocess use
# fork() instead of vfork(), and after the Milvus tests this process has gRPC threads running; gRPC's
# fork handlers then print "Other threads are currently calling into gRPC, skipping fork() handlers"
# and some children died before exec ("process died while waiting for matcher up"). vfork() runs no
# fork handlers. Measured with pymilvus busy in a thread: 1 of 150 forked children died, 0 of 150
# vforked ones (test/test_harness.py keeps the fork-handler case from coming back).
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

REPO = Path(__file__).resolve().parents[1]
# $LLN_DATA as the Makefile and scripts/ set it; else ../shared/data beside the checkout
SHARED_DATA = Path(os.environ.get('LLN_DATA') or REPO.parent / 'shared' / 'data')


def shared_data(*parts) -> Path:
    """Path under ../shared/data, or skip the test with a reason when it is not there."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f'real data not available: {path} is absent (only CI and dev machines have ../shared)')
    return path


@pytest.fixture(scope='session')
def extractor():
    from lln_ros.core.extractor import Extractor

    return Extractor({'num_threads': 2})


@pytest.fixture(scope='session')
def photo() -> np.ndarray:
    """A real photograph shipped inside matplotlib (RGB uint8), so self-contained tests use real pixels."""
    import matplotlib.cbook as cbook

    from lln_ros.io.image import load_image

    with cbook.get_sample_data('grace_hopper.jpg') as f:
        path = f.name
    return load_image(path)


@pytest.fixture(scope='session')
def colcon_install(tmp_path_factory, extractor):
    """The package built by colcon into a fresh workspace, as a ROS user builds it. After the
    session extractor, which exports the ONNX graph into the cache: nodes then start without it."""
    from ros_harness import colcon_build

    return colcon_build(tmp_path_factory.mktemp('ws'))


@pytest.fixture(scope='session')
def milvus_server():
    """A real Milvus standalone server on 127.0.0.1, started once per run and stopped at its end.
    Only inside a network namespace that has nothing but lo (the server listens on every interface):
    test_milvus_server.py::test_real_server_suite re-runs the milvus_server tests in one."""
    from milvus_loopback import LoopbackMilvus, milvus_version, only_loopback

    if milvus_version() is None:
        pytest.skip('the PyPI package `milvus` (a Milvus 2.3.5 standalone server) is not installed')
    if not only_loopback():
        pytest.skip(
            'a real Milvus server runs only in a loopback-only network namespace: '
            'test_milvus_server.py::test_real_server_suite runs this test in one'
        )
    server = LoopbackMilvus().start()
    yield server
    server.close()


@pytest.fixture
def milvus_map(milvus_server, request):
    """A fresh map URI on the real server (database lln_test, a map name of this test's own);
    its collections are dropped afterwards (an idle server's CPU climbs with every loaded one)."""
    import re

    name = 't' + re.sub(r'[^0-9a-zA-Z]', '_', request.node.name)[-40:] + f'_{id(request) % 10000}'
    yield f'{milvus_server.uri}/lln_test?map={name}'
    from milvus_loopback import drop_maps

    drop_maps(milvus_server, 'lln_test', name + '_')
