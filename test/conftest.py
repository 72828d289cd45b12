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
def ros_env(worker_id="main"):
    """Environment for a child ROS process: a domain id no other test uses, localhost-only DDS."""
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(_next_domain_id())
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    return env


_domain_counter = [0]


def _next_domain_id():
    # 0..101 are valid everywhere; spread by pid so two pytest runs on one machine do not meet.
    _domain_counter[0] += 1
    return 1 + (os.getpid() * 7 + _domain_counter[0]) % 100


@pytest.fixture(autouse=True, scope="session")
def _isolated_precompute_cache(tmp_path_factory):
    """Tests write precompute caches to their own folder, never to the user's."""
    os.environ["MDSS_CACHE_DIR"] = str(tmp_path_factory.mktemp("mdss_cache"))
    yield
