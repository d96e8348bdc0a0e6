import os
import subprocess
import sys
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


def pytest_sessionstart(session):
    """Compile the kernels once, one share per core, before xdist starts its
    workers (its own hook runs last).

    On a fresh install every process that needs a kernel compiles it, and
    the suite's first minute had each worker, and each sweep they started,
    compiling the same kernels at once (the suite took 636 s with an empty
    numba cache against 533 s with a full one, on 2 cores). Side by side in
    one process per core they take 27 s there (52 s in one process); with
    the cache full, loading them costs a second or two."""
    config = session.config
    if hasattr(config, "workerinput") or config.option.collectonly:
        return  # a worker (the controller did it), or nothing will run
    parts = max(1, min(os.cpu_count() or 1, 4))
    code = ("import sys; import mpe3d.solvers, mpe3d.solvers.sfm.bundle; from mpe3d.solvers import warmup; "
            "warmup.warm(part=int(sys.argv[1]), parts={})")
    compiling = [subprocess.Popen([sys.executable, "-c", code.format(parts), str(part)])
                 for part in range(parts)]
    if any([process.wait() for process in compiling]):  # each waited for, failed or not
        pytest.exit("compiling the kernels failed (see above)", returncode=3)


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
