"""Reconstruction with the exact poses of a simulated session: the fused surface lies on the true
objects, the table plane is the turntable top, one cluster per object."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from tdof20.annotate.reconstruct import reconstruct
from tdof20.capture import run_capture, sim_config
from tdof20.formats import RawSession, read_scene
from tdof20.geometry import invert, transform_points
from tdof20.objects import get_object


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    out = tmp_path_factory.mktemp("rec") / "s"
    run_capture(sim_config("multi/05", steps=8, step_deg=45.0, n_arms=2, width=240, height=180), out, yes=True,
                show_progress=False)
    return out


def test_fused_scene_and_clusters_match_the_truth(session):
    s = RawSession.open(session)
    truth = read_scene(session / "truth")

    def T_cam_table(im):
        c = truth.camera[im]
        T = np.eye(4)
        T[:3, :3] = np.asarray(c["cam_R_w2c"]).reshape(3, 3)
        T[:3, 3] = c["cam_t_w2c"]
        return T

    ref = T_cam_table(0)
    frames = []
    for arm in range(s.info.n_arms):
        for step in range(s.info.steps):
            im = arm * s.info.steps + step
            frames.append((s.load_depth_mm("opaque", arm, step), ref @ invert(T_cam_table(im))))
    rec = reconstruct(frames, s.info.camera, axis_point=ref[:3, 3], axis_dir=ref[:3, 2])
    # the table plane passes through the turntable top: the table origin lies on it
    origin_ref = ref[:3, 3]
    assert abs(origin_ref @ rec.plane[:3] + rec.plane[3]) < 3.0
    # one cluster per object, each close to its true surface
    n_obj = len(truth.gt[0])
    assert len(rec.clusters) == n_obj
    model_pts = []
    for g, e in enumerate(truth.gt[0]):
        R, t = truth.pose(0, g)
        model_pts.append(get_object(e["obj_id"]).sample_surface(20000, seed=1) @ R.T + t)
    tree = cKDTree(np.concatenate(model_pts))
    for c in rec.clusters:
        d, _ = tree.query(c)
        assert np.median(d) < 2.0 and np.percentile(d, 95) < 6.0
