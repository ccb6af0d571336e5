"""Shared fixtures. Real data lives in ../shared/data next to the repo; tests that need it skip
with a reason when it is absent (a user's fresh machine)."""
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / 'shared' / 'data'


def shared_data(*parts) -> Path:
    """Path under ../shared/data, or skip the test with a reason when it is not there."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f'real data not available: {path} is absent (only CI and dev machines have ../shared)')
    return path


@pytest.fixture(scope='session')
def extractor():
    from lln_ros.extractor import Extractor
    return Extractor({'num_threads': 2})


@pytest.fixture(scope='session')
def photo() -> np.ndarray:
    """A real photograph shipped inside matplotlib (RGB uint8), so self-contained tests use real pixels."""
    import matplotlib.cbook as cbook
    from lln_ros.image import load_image
    with cbook.get_sample_data('grace_hopper.jpg') as f:
        path = f.name
    return load_image(path)


@pytest.fixture(scope='session')
def colcon_install(tmp_path_factory):
    """The package built by colcon into a fresh workspace, as a ROS user builds it."""
    from ros_harness import colcon_build
    return colcon_build(tmp_path_factory.mktemp('ws'))
