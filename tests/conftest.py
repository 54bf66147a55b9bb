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


@pytest.fixture(scope="session")
def small_session(tmp_path_factory, small_cfg):
    out = tmp_path_factory.mktemp("sim") / "session"
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
