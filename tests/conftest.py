import os
import shutil

# Under xdist, the cores shared out among the workers: OMP_NUM_THREADS = cores // workers (one on
# 2 cores with -n 2), so that torch's intra-op pool, OpenMP and OpenBLAS do not spin against the
# other worker (measured, 2 processes side by side on the 2-core machine, 8 ResNet34 steps at 64x96:
# 2 threads each 33 s CPU and 120-180 s wall, 1 thread 4.2 s CPU and 16 s wall). Set before
# anything imports torch; CLI subprocesses and DataLoader or annotate workers inherit it. A user's
# OMP_NUM_THREADS is kept; a single-process run (-n 0) is left alone.
_WORKERS = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0"))
if _WORKERS and "OMP_NUM_THREADS" not in os.environ:
    os.environ["OMP_NUM_THREADS"] = str(max(1, len(os.sched_getaffinity(0)) // _WORKERS))

import pytest

from tdof20.capture import run_capture, sim_config
from tdof20.capture.rig import build_rig
from tdof20.sim.render import SimRenderer

SMALL = dict(width=160, height=120)


@pytest.fixture(scope="session")
def small_cfg():
    return sim_config("multi/08", steps=3, step_deg=30.0, n_arms=2, **SMALL)


@pytest.fixture(scope="session")
def renderer_640() -> SimRenderer:
    return build_rig(sim_config("multi/08")).world.renderer


#: folders of session-scoped fixtures, which outlive the module that made them
_SESSION_DIRS: set = set()
#: modules (their node ids) with a failed test: their folders are kept to look at
_FAILED_MODULES: set = set()


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item, call):
    rep = yield
    if rep.failed:
        _FAILED_MODULES.add(item.module.__name__)
    return rep


@pytest.fixture(scope="module", autouse=True)
def _module_folders(request, tmp_path_factory):
    """Removes the folders a module made under the run's temporary folder when its tests are
    done (a module fixture's dataset, runs and checkpoints: several GB over the suite otherwise,
    more than a CI machine's free disk), unless one of its tests failed. A passing test's own
    tmp_path goes at once (tmp_path_retention_policy = "failed" in pyproject.toml)."""
    base = tmp_path_factory.getbasetemp()
    before = set(base.iterdir())
    yield
    if request.module.__name__ in _FAILED_MODULES:
        return
    for p in set(base.iterdir()) - before - _SESSION_DIRS:
        shutil.rmtree(p, ignore_errors=True)


@pytest.fixture(scope="session")
def small_session(tmp_path_factory, small_cfg):
    base = tmp_path_factory.mktemp("sim")
    _SESSION_DIRS.add(base)
    out = base / "session"
    run_capture(small_cfg, out, yes=True, show_progress=False)
    return out


@pytest.fixture(scope="module")
def one_torch_thread():
    """One torch intra-op thread for a module that trains (two threads on a busy 2-core machine
    spin against each other: one step 0.5 s with one thread, 3-10 s with two); restored after."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
