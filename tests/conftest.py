from collections import Counter

import numpy as np
import pytest

from mpe3d import plugins


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture(autouse=True)
def _no_plugin_outlives_its_test():
    """A plug-in a test loads in this process is withdrawn after it, so that
    no other test (nor a generated reference page) sees its names."""
    before = set(plugins.loaded())
    yield
    for origin in set(plugins.loaded()) - before:
        plugins.unload(origin)


def pytest_collection_modifyitems(config, items):
    """The files with the most slow tests first (each file keeps its order).

    xdist runs a file on one worker (``--dist loadfile``) and, told
    ``--no-loadscope-reorder``, hands the files out in this order; its own
    order, most tests first, left the suite's long files (real sweeps,
    servers, fresh installs: a few tests each, up to 2 minutes) to the end,
    where one worker ran them while the other idled (546 s against 510 s
    balanced, measured on 2 cores)."""
    slow = Counter(item.nodeid.split("::")[0] for item in items if item.get_closest_marker("slow"))
    items.sort(key=lambda item: -slow[item.nodeid.split("::")[0]])
