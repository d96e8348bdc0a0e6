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
