"""Shared test setup: slow studies are opt-in (--slow); ROS tests get their own DDS domain."""
import os

import pytest


def pytest_addoption(parser):
    parser.addoption("--slow", action="store_true", default=False,
                     help="also run the slow-marked studies (fine meshes, sweeps)")


def pytest_collection_modifyitems(config, items):
    if config.getoption("--slow"):
        return
    skip = pytest.mark.skip(reason="slow study: run with --slow or through the report commands")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)


@pytest.fixture
def ros_env():
    """Environment for a child ROS process: a ROS_DOMAIN_ID leased through a lock file (no
    other test or concurrent run can hold it) and localhost-only DDS."""
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "launch_scripts"))
    from launch_testing import DomainLease
    from launch_testing import ros_env as make_env
    lease = DomainLease()
    try:
        yield make_env(lease.domain_id)
    finally:
        lease.release()


@pytest.fixture(autouse=True, scope="session")
def _isolated_precompute_cache(tmp_path_factory):
    """Tests write precompute caches to their own folder, never to the user's."""
    os.environ["MDSS_CACHE_DIR"] = str(tmp_path_factory.mktemp("mdss_cache"))
    yield
