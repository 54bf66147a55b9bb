"""Ray's failures as one line each (issue 22), on a local Ray instance: workers killed more often
than Ray retries a task, and a --ray-address that is not an address."""
import os

import pytest

pytest.importorskip("ray")

from tdof20.annotate.executors import ray_init, run_chunks  # noqa: E402
from tdof20.errors import TdofError  # noqa: E402


def test_a_worker_killed_more_often_than_ray_retries_is_one_line(capfd):
    # os._exit(1) on the worker: the process dies mid-task, every retry too
    with pytest.raises(TdofError) as ei:
        list(run_chunks(os._exit, [1, 1], executor="ray", workers=1))
    msg = str(ei.value)
    assert "\n" not in msg and msg.startswith("a Ray worker died running chunk")
    assert "WorkerCrashedError" in msg and "Lease ID" not in msg and "raylet" not in msg


@pytest.mark.parametrize("address", [":", "host:", ":6379", "10.0.0.5"])
def test_a_ray_address_that_is_not_one_is_one_line_without_rays_traceback(address, capfd):
    with pytest.raises(TdofError, match="--ray-address .* is not HOST:PORT"):
        ray_init(address)
    err = capfd.readouterr().err
    assert "Traceback" not in err and "Failed to convert" not in err
