"""The reconstruct stage is repeatable: the same frames give the same table plane, clusters,
points and mesh in two processes (seeds and open3d's hash-map order are process state), and the
table plane does not depend on the RANSAC samples.

Sizes: single/juice_cup_340 (a straight tumbler) with a cabinet beside the table, 240x180, 2 arms x 6 steps, true
poses, the depth cropped to the turntable volume as the pipeline does; each reconstruction runs
in its own process (~5 s each with the imports on an idle machine)."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest

from tdof20.geometry.fitting import fit_plane
from tdof20.capture import run_capture, sim_config

# One reconstruction of a session, with the true poses and the pipeline's crop, saved to an npz.
_RECONSTRUCT = textwrap.dedent("""
    import sys
    import numpy as np
    from tdof20.annotate.reconstruct import ReconstructionConfig, reconstruct
    from tdof20.formats import RawSession, read_scene
    from tdof20.geometry import invert

    raw, out = sys.argv[1], sys.argv[2]
    s = RawSession.open(raw)
    truth = read_scene(raw + "/truth")

    def T_cam_table(im):
        c = truth.camera[im]
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = np.asarray(c["cam_R_w2c"]).reshape(3, 3), c["cam_t_w2c"]
        return T

    def cropped(z, T_table_cam):
        # the turntable volume, as the pipeline fuses it: 300 mm about the axis, -20..400 mm in height
        X = s.info.camera.backproject(z).astype(np.float64) @ T_table_cam[:3, :3].T + T_table_cam[:3, 3]
        keep = (z > 0) & (np.hypot(X[..., 0], X[..., 1]) < 300.0) & (X[..., 2] > -20.0) & (X[..., 2] < 400.0)
        return np.where(keep, z, 0.0).astype(np.float32)

    ref = T_cam_table(0)
    frames = []
    for a in range(s.info.n_arms):
        for k in range(s.info.steps):
            T = T_cam_table(a * s.info.steps + k)
            frames.append((cropped(s.load_depth_mm("opaque", a, k), invert(T)), ref @ invert(T)))
    rec = reconstruct(frames, s.info.camera, ref[:3, 3], ref[:3, 2], ReconstructionConfig())
    arrays = {"plane": rec.plane, "points": rec.points, "mesh_v": np.asarray(rec.mesh.vertices),
              "mesh_t": np.asarray(rec.mesh.triangles), "n_clusters": np.array(len(rec.clusters))}
    for i, (c, n) in enumerate(zip(rec.clusters, rec.cluster_normals)):
        arrays[f"cluster_{i}"], arrays[f"normals_{i}"] = c, n
    np.savez(out, **arrays)
""")


@pytest.fixture(scope="module")
def cluttered_session(tmp_path_factory):
    out = tmp_path_factory.mktemp("rep") / "s"
    run_capture(sim_config("single/juice_cup_340", steps=6, step_deg=60.0, n_arms=2, width=240, height=180,
                           clutter=("cabinet",)), out, yes=True, show_progress=False)
    return out


def _reconstruct_in_a_process(raw, out) -> dict:
    subprocess.run([sys.executable, "-c", _RECONSTRUCT, str(raw), str(out)], check=True, timeout=300)
    with np.load(out) as z:
        return {k: z[k] for k in z.files}


def test_two_processes_reconstruct_the_same_frames_identically(cluttered_session, tmp_path):
    a = _reconstruct_in_a_process(cluttered_session, tmp_path / "a.npz")
    b = _reconstruct_in_a_process(cluttered_session, tmp_path / "b.npz")
    assert int(a["n_clusters"]) >= 1 and len(a["points"]) > 1000 and len(a["mesh_t"]) > 1000
    assert sorted(a) == sorted(b)
    for k in sorted(a):
        assert a[k].shape == b[k].shape and np.array_equal(a[k], b[k]), k   # bit for bit, order included
    # the canonical order: points sorted lexicographically, clusters largest first
    P = a["points"]
    assert np.all(np.diff(P[:, 0]) >= 0)
    sizes = [len(a[f"cluster_{i}"]) for i in range(int(a["n_clusters"]))]
    assert sizes == sorted(sizes, reverse=True)


def test_the_table_plane_does_not_depend_on_the_ransac_samples():
    """A noisy table with an object and a tilted board on it: every seed's RANSAC lands in the
    table's band, and the least-squares refinement takes each to the same plane, bit for bit."""
    rng = np.random.default_rng(0)
    n_true = np.array([0.02, -0.01, 1.0]) / np.linalg.norm([0.02, -0.01, 1.0])
    d_true = -40.0
    uv = rng.uniform(-150.0, 150.0, (30000, 2))
    table = np.c_[uv, np.zeros(len(uv))]
    table[:, 2] = -(table[:, :2] @ n_true[:2] + d_true) / n_true[2]
    table += rng.normal(0.0, 0.6, table.shape)                       # depth noise across the band
    ang = rng.uniform(0.0, 2.0 * np.pi, 8000)
    h = rng.uniform(0.0, 120.0, 8000)
    cup = np.c_[40.0 * np.cos(ang), 40.0 * np.sin(ang), h + 40.0]    # a cylinder standing on the table
    board = np.c_[rng.uniform(60.0, 140.0, (4000, 2)), np.zeros(4000)]
    board[:, 2] = 40.0 + 0.5 * (board[:, 0] - 60.0)                  # a plank leaning on it
    P = np.concatenate([table, cup, board])
    perm = rng.permutation(len(P))
    P, is_table = P[perm], perm < len(table)
    planes, inliers = [], []
    for seed in range(6):
        pl, inl = fit_plane(P, 3.0, iters=300, seed=seed)
        planes.append(pl * np.sign(pl[2]))
        inliers.append(inl)
    for pl, inl in zip(planes[1:], inliers[1:]):
        assert np.array_equal(pl, planes[0]) and np.array_equal(inl, inliers[0])
    pl = planes[0]
    assert np.degrees(np.arccos(min(1.0, pl[:3] @ n_true))) < 0.05
    assert abs(pl[3] - d_true) < 0.05                                 # the centre of the band
    assert is_table[inliers[0]].sum() > 0.999 * len(table)            # the whole table ...
    assert (~is_table[inliers[0]]).sum() < 0.02 * len(table)          # ... and little else
    # the same call twice: the same result (no hidden state)
    again = fit_plane(P, 3.0, iters=300, seed=0)
    assert np.array_equal(again[0], fit_plane(P, 3.0, iters=300, seed=0)[0])
