"""Shared by tests/test_server*.py (no tests here): a tiny tdof20 dataset with both protocols and a server around it.

Scene 8 (single, object 7, images 0-3): simple train 0-1, simple test 2-3, hard train 0-3.
Scene 28 (multi, objects 1, 7, 17, images 0-2): hard test. Test images carry restored depth."""

from __future__ import annotations

import io
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from scipy.spatial.transform import Rotation

from tdof20.dataset.results import format_results_csv
from tdof20.formats import BopSceneWriter, write_json
from tdof20.objects import export_models
from tdof20.server import auth
from tdof20.server.app import create_app
from tdof20.server.config import ServerConfig
from tdof20.server.db import init_db, make_engine

K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
LAYOUT = {8: [[7]] * 4, 28: [[1, 7, 17]] * 3}
HIDDEN = {8: {2, 3}, 28: {0, 1, 2}}


def build_dataset(root: Path) -> list[tuple]:
    """Write the dataset; returns its ground truth rows (scene, im, obj, R, t)."""
    export_models(root / "models", (1, 7, 17))
    rng = np.random.default_rng(3)
    gt, targets = [], {"simple": [], "hard": []}
    for sid, images in LAYOUT.items():
        with BopSceneWriter(root / "scenes" / f"{sid:06d}") as w:
            for im, objs in enumerate(images):
                poses = []
                for o in objs:
                    R = Rotation.random(random_state=int(rng.integers(2**31))).as_matrix()
                    t = np.array([rng.uniform(-60, 60), rng.uniform(-40, 40), rng.uniform(600, 800)])
                    poses.append((o, R, t))
                mask = np.zeros((4, 6), bool)  # a mask of its own per image (publish's test compares bytes)
                mask[(0 if sid == 8 else 2):(2 if sid == 8 else 4), im:im + 3] = True
                extra = {"depth_restored": np.full((4, 6), 700, np.uint16)} if im in HIDDEN[sid] else None
                w.add_frame(im, K, 1.0, poses, [mask] * len(poses), [mask] * len(poses),
                            rgb=np.full((4, 6, 3), 40 + im, np.uint8), depth=np.full((4, 6), 650 + im, np.uint16),
                            extra=extra)
                gt += [(sid, im, o, R, t) for o, R, t in poses]
                split = "hard" if sid == 28 else "simple"
                if im in HIDDEN[sid]:
                    targets[split] += [{"scene_id": sid, "im_id": im, "obj_id": o, "inst_count": 1} for o in objs]
    write_json(root / "dataset_info.json", {"name": "tdof20", "scenes": {"8": "single/handle_cup_440",
                                                                        "28": "multi/07"}})
    write_json(root / "camera.json", {"cx": 320.0, "cy": 240.0, "fx": 600.0, "fy": 600.0, "width": 640,
                                      "height": 480, "depth_scale": 1.0})
    write_json(root / "splits" / "simple_train.json", {"8": [0, 1]})
    write_json(root / "splits" / "simple_test.json", {"8": [2, 3]})
    write_json(root / "splits" / "hard_train.json", {"8": [0, 1, 2, 3]})
    write_json(root / "splits" / "hard_test.json", {"28": [0, 1, 2]})
    for split, tg in targets.items():
        write_json(root / f"test_targets_{split}.json", tg)
    (root / ".cache").mkdir()
    (root / ".cache" / "val_targets_simple.json").write_text("[]")
    return gt


RICH_TEST = (28, 29)  # the rich dataset's hard test scenes (objects 1, 7, 17 in every image)


def build_rich_dataset(root: Path, n_test: int = 300, n_train: int = 24) -> list[tuple]:
    """A dataset with enough targets that the disclosure rule shows figures: scene 8 (single, object
    7, ``n_train`` images: simple train = the first half, simple validation = the first 4 of them,
    simple test = the second half; hard train = all) and scenes 28 and 29 (multi, objects 1, 7, 17
    in each of ``n_test`` images: hard test), 3 x 2 x 300 = 1,800 hard test targets. The visible
    fraction cycles 1.0, 0.7, 0.3 (one image in three per occlusion bin) and the distance spans the
    train images' range, so every condition bin holds a third of the targets. Returns the ground
    truth rows (scene, im, obj, R, t)."""
    export_models(root / "models", (1, 7, 17))
    rng = np.random.default_rng(5)
    gt, targets = [], {"simple": [], "hard": []}
    full = np.zeros((4, 6), bool)
    full[0:2, 0:5] = True  # 10 pixels
    visible = {}
    for k, frac in ((0, 10), (1, 7), (2, 3)):
        v = np.zeros((4, 6), bool)
        v.flat[[i for i in np.flatnonzero(full)][:frac]] = True
        visible[k] = v
    half = n_train // 2
    layout = {8: ([7], n_train, set(range(half, n_train))), 28: ([1, 7, 17], n_test, set(range(n_test))),
              29: ([1, 7, 17], n_test, set(range(n_test)))}
    for sid, (objs, n, test) in layout.items():
        with BopSceneWriter(root / "scenes" / f"{sid:06d}", png_compression=1) as w:
            for im in range(n):
                poses = []
                for j, o in enumerate(objs):
                    R = Rotation.random(random_state=int(rng.integers(2**31))).as_matrix()
                    z = 600.0 + 300.0 * ((im * 7 + j * 3) % n) / n  # 600-900 mm, in train and test alike
                    poses.append((o, R, np.array([rng.uniform(-60, 60), rng.uniform(-40, 40), z])))
                vis = visible[im % 3] if sid != 8 else full
                extra = {"depth_restored": np.full((4, 6), 700, np.uint16)} if im in test else None
                w.add_frame(im, K, 1.0, poses, [full] * len(poses), [vis] * len(poses),
                            rgb=np.full((4, 6, 3), (40 + im) % 250, np.uint8),
                            depth=np.full((4, 6), 650 + im % 100, np.uint16), extra=extra)
                gt += [(sid, im, o, R, t) for o, R, t in poses]
                if im in test:
                    split = "simple" if sid == 8 else "hard"
                    targets[split] += [{"scene_id": sid, "im_id": im, "obj_id": o, "inst_count": 1} for o in objs]
    write_json(root / "dataset_info.json", {"name": "tdof20", "scenes": {"8": "single/handle_cup_440",
                                                                        "28": "multi/07", "29": "multi/08"}})
    write_json(root / "camera.json", {"cx": 320.0, "cy": 240.0, "fx": 600.0, "fy": 600.0, "width": 640,
                                      "height": 480, "depth_scale": 1.0})
    write_json(root / "splits" / "simple_train.json", {"8": list(range(half))})
    write_json(root / "splits" / "simple_test.json", {"8": list(range(half, n_train))})
    write_json(root / "splits" / "hard_train.json", {"8": list(range(n_train))})
    write_json(root / "splits" / "hard_test.json", {str(s): list(range(n_test)) for s in RICH_TEST})
    for split, tg in targets.items():
        write_json(root / f"test_targets_{split}.json", tg)
    (root / ".cache").mkdir()
    write_json(root / ".cache" / "val_targets_simple.json",
               [{"scene_id": 8, "im_id": im, "obj_id": 7, "inst_count": 1} for im in range(4)])
    return gt


def rich_results_csv(gt, seed: int = 0, bad: float = 0.3, noise_mm: float = 3.0, split: str = "hard",
                     n_train: int = 24) -> bytes:
    """A results file for the rich dataset (built with ``n_train``): ``split`` hard or simple (their
    test parts) or val (simple's validation part); each estimate the truth moved by ``noise_mm``
    (normal, per axis), and a share ``bad`` of them (more among the occluded and the far ones)
    moved by 80 mm: scores that differ by condition."""
    keep = {"hard": lambda s, im: s in RICH_TEST, "simple": lambda s, im: s == 8 and im >= n_train // 2,
            "val": lambda s, im: s == 8 and im < 4}[split]
    rng = np.random.default_rng(seed)
    rows = []
    for s, im, o, R, t in gt:
        if not keep(s, im):
            continue
        p = bad * (0.5 + (im % 3) * 0.5) * (0.7 + 0.6 * (t[2] - 600.0) / 300.0)
        shift = rng.normal(0.0, noise_mm, 3) + (np.array([0.0, 0.0, 80.0]) if rng.random() < p else 0.0)
        rows.append((s, im, o, 1.0, R, t + shift, 0.03))
    return format_results_csv(rows).encode()


def results_csv(gt, split: str, shift_mm: float = 0.0) -> bytes:
    """The ground truth of a protocol's test images as a results file (t moved by ``shift_mm``)."""
    rows = [(s, im, o, 1.0, R, t + [0.0, 0.0, shift_mm], 0.02) for s, im, o, R, t in gt
            if im in HIDDEN[s] and (s == 28) == (split == "hard")]
    return format_results_csv(rows).encode()


class Server:
    """An in-process server (TestClient) with users alice and bob."""

    def __init__(self, dataset: Path, data: Path, **limits):
        self.cfg = ServerConfig(dataset=dataset, data=data, **limits)
        self.client = TestClient(create_app(self.cfg))
        self.engine = self.client.app.app.state.engine
        self.tokens = {n: auth.add_user(self.engine, n) for n in ("alice", "bob")}

    def headers(self, name: str) -> dict:
        return {"Authorization": f"Bearer {self.tokens[name]}"}

    def submit(self, name: str, data: bytes, split: str = "hard", filename: str = "r.csv", **fields):
        form = {"method": "m", "split": split, **{k: str(v).lower() if isinstance(v, bool) else v
                                                  for k, v in fields.items()}}
        return self.client.post("/api/submissions", headers=self.headers(name), data=form,
                                files={"file": (filename, io.BytesIO(data), "text/csv")})

    def sign_in(self, name: str) -> TestClient:
        """A separate client signed in as ``name`` through the sign-in form."""
        c = TestClient(self.client.app)
        page = c.get("/signin")
        csrf = page.text.split('name="csrf" value="')[1].split('"')[0]
        r = c.post("/signin", data={"name": name, "token": self.tokens[name], "csrf": csrf}, follow_redirects=False)
        assert r.status_code == 303, r.text
        return c


def page_csrf(html: str) -> str:
    return html.split('name="csrf" value="')[1].split('"')[0]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """(root, ground truth rows) of the tiny dataset."""
    root = tmp_path_factory.mktemp("ds")
    return root, build_dataset(root)


@pytest.fixture
def server(dataset, tmp_path):
    return Server(dataset[0], tmp_path / "data")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


CLI = [sys.executable, "-c", "from tdof20.server.cli import app; app()"]


class LiveServer:
    """``tdof20 serve`` in a subprocess on loopback (stopped on exit), users alice and bob."""

    def __init__(self, dataset: Path, data: Path, *args: str, preexec=None, tokens: dict | None = None):
        self.data = data
        self.preexec = preexec
        data.mkdir(parents=True, exist_ok=True)
        engine = make_engine(ServerConfig(dataset=dataset, data=data).db_url)
        init_db(engine)
        self.tokens = tokens or {n: auth.add_user(engine, n) for n in ("alice", "bob")}
        engine.dispose()
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.cmd = CLI + ["serve", "--dataset", str(dataset), "--data", str(data), "--port", str(self.port), *args]
        self.proc: subprocess.Popen | None = None

    def __enter__(self) -> "LiveServer":
        self.proc = subprocess.Popen(self.cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                     preexec_fn=self.preexec)
        for _ in range(300):  # up to 30 s
            try:
                with urllib.request.urlopen(self.url + "/openapi.json", timeout=2):
                    return self
            except OSError:
                if self.proc.poll() is not None:
                    raise RuntimeError(self.proc.stderr.read().decode()[-2000:])
                time.sleep(0.1)
        raise RuntimeError("the server did not start in 30 s")

    def rss_mb(self) -> float:
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
        return 0.0

    def __exit__(self, *exc) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(10)
