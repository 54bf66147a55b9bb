import numpy as np
import pytest

from tdof20.sim.render import SimRenderer
from tdof20.sim.session import SimSessionConfig, build_session_info, make_renderer, simulate_session

SMALL = dict(width=160, height=120)


@pytest.fixture(scope="session")
def small_cfg() -> SimSessionConfig:
    return SimSessionConfig(scene_id="multi/08", steps=3, step_deg=30.0, n_arms=2, **SMALL)


@pytest.fixture(scope="session")
def renderer_640() -> SimRenderer:
    cfg = SimSessionConfig(scene_id="multi/08", steps=400, n_arms=4)
    return make_renderer(cfg, build_session_info(cfg))


@pytest.fixture(scope="session")
def small_session(tmp_path_factory, small_cfg):
    out = tmp_path_factory.mktemp("sim") / "session"
    simulate_session(small_cfg, out, show_progress=False)
    return out
