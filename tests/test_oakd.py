"""OAK-D driver, host side only: frame conversion, synchronisation, grab() on fake queues,
connect() without a device. Nothing here needs a camera (build_pipeline is never called)."""

from __future__ import annotations

import inspect
import threading
import time
import types
from datetime import timedelta

import cv2
import numpy as np
import pytest

from tdof20.capture.hardware import oakd
from tdof20.capture.hardware.interfaces import HardwareError, RGBDCamera
from tdof20.capture.hardware.oakd import (FrameFormatError, FrameSynchronizer, OakDCamera, build_pipeline,
                                          frame_to_depth, frame_to_rgb)

H, W = 48, 64
T0 = 1000.0          # the fake host clock at the start of each grab


# ------------------------------------------------------------------------------- fakes


class FakeFrame:
    """What grab() needs of a depthai ImgFrame: getCvFrame / getFrame / getTimestamp (timedelta)."""

    def __init__(self, arr: np.ndarray, t: float, seq: int = 0):
        self.arr, self.t, self.seq = arr, t, seq

    def getCvFrame(self):
        return self.arr

    def getFrame(self):
        return self.arr

    def getTimestamp(self):
        return timedelta(seconds=self.t)

    def getSequenceNum(self):
        return self.seq


class FakeGroup:
    """A dai.MessageGroup stand-in (what a Sync node emits)."""

    def __init__(self, **msgs):
        self.msgs = msgs

    def getMessageNames(self):
        return list(self.msgs)

    def __getitem__(self, name):
        return self.msgs[name]


class FakeQueue:
    """Non-blocking queue: each message becomes available ``delay`` seconds after the first tryGet."""

    def __init__(self, items=()):
        self.items = list(items)          # (delay_s, msg)
        self.t_first = None
        self.calls = 0

    def tryGet(self):
        self.calls += 1
        now = time.monotonic()
        if self.t_first is None:
            self.t_first = now
        if self.items and now - self.t_first >= self.items[0][0]:
            return self.items.pop(0)[1]
        return None


def bgr(value: int) -> np.ndarray:
    img = np.zeros((H, W, 3), np.uint8)
    img[..., 0] = value            # blue channel carries an id
    img[..., 2] = 255 - value
    return img


def depth(value: int, shape=(H, W), dtype=np.uint16) -> np.ndarray:
    return np.full(shape, value, dtype)


def camera_on(queues, clock_t=T0, **kw) -> OakDCamera:
    cam = OakDCamera(width=W, height=H, **kw)
    cam.attach(queues, {"K": [1, 0, 0, 0, 1, 0, 0, 0, 1], "width": W, "height": H, "depth_scale": 1.0},
               clock=lambda: clock_t)
    return cam


# ------------------------------------------------------------------------------- conversion


def test_bgr_array_becomes_rgb():
    img = bgr(10)
    rgb = frame_to_rgb(img)
    assert rgb.dtype == np.uint8 and rgb.shape == (H, W, 3) and rgb.flags.c_contiguous
    assert tuple(rgb[0, 0]) == (245, 0, 10)
    assert tuple(frame_to_rgb(FakeFrame(img, 0.0))[3, 4]) == (245, 0, 10)   # getCvFrame() is BGR
    assert tuple(frame_to_rgb(img[..., ::-1], fmt="rgb")[0, 0]) == (245, 0, 10)
    assert frame_to_rgb(np.full((H, W), 7, np.uint8), fmt="gray").shape == (H, W, 3)
    bgra = np.dstack([img, np.full((H, W), 255, np.uint8)])
    assert tuple(frame_to_rgb(bgra, fmt="bgra")[0, 0]) == (245, 0, 10)


def _rgb_to_nv12(rgb: np.ndarray) -> np.ndarray:
    i420 = cv2.cvtColor(rgb, cv2.COLOR_RGB2YUV_I420)          # Y, then U plane, then V plane
    h, w = rgb.shape[:2]
    y = i420[:h]
    u = i420[h:h + h // 4].reshape(h // 2, w // 2)
    v = i420[h + h // 4:].reshape(h // 2, w // 2)
    uv = np.stack([u, v], axis=-1).reshape(h // 2, w)
    return np.vstack([y, uv])


def test_nv12_array_becomes_rgb():
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[:, : W // 2] = (200, 40, 30)
    rgb[:, W // 2:] = (20, 60, 220)
    nv12 = _rgb_to_nv12(rgb)
    assert nv12.shape == (H * 3 // 2, W)
    out = frame_to_rgb(nv12, fmt="nv12")
    assert out.shape == (H, W, 3)
    assert np.abs(out.astype(int) - rgb).max() <= 6
    with pytest.raises(FrameFormatError, match="NV12"):
        frame_to_rgb(np.zeros((H * 3 // 2, W + 1), np.uint8), fmt="nv12")


def test_real_depthai_imgframes_convert():
    dai = pytest.importorskip("depthai")
    img = bgr(10)
    for typ in ("BGR888i", "RGB888p", "NV12"):
        f = dai.ImgFrame()
        f.setCvFrame(img, getattr(dai.ImgFrame.Type, typ))
        out = frame_to_rgb(f, expected_hw=(H, W))
        assert np.abs(out.astype(int) - img[..., ::-1]).max() <= 6, typ
    d = dai.ImgFrame()
    d.setFrame(depth(1234))
    d.setType(dai.ImgFrame.Type.RAW16)
    d.setWidth(W)
    d.setHeight(H)
    assert (frame_to_depth(d, expected_hw=(H, W)) == 1234).all()


def test_colour_errors_are_clear():
    with pytest.raises(FrameFormatError, match="dtype float32, expected uint8"):
        frame_to_rgb(bgr(1).astype(np.float32))
    with pytest.raises(FrameFormatError, match=r"shape \(48, 64\), expected \(H, W, 3\)"):
        frame_to_rgb(np.zeros((H, W), np.uint8))
    with pytest.raises(FrameFormatError, match="colour frame is 64x48 .*expected 640x480"):
        frame_to_rgb(bgr(1), expected_hw=(480, 640))
    with pytest.raises(FrameFormatError, match="unknown colour format"):
        frame_to_rgb(bgr(1), fmt="yuyv")


def test_depth_checks_dtype_and_size():
    d = depth(1500)
    out = frame_to_depth(FakeFrame(d, 0.0), expected_hw=(H, W))
    assert out.dtype == np.uint16 and out.shape == (H, W) and (out == 1500).all()
    assert not np.shares_memory(out, d)                      # a copy: the device buffer may be reused
    assert frame_to_depth(d[..., None]).shape == (H, W)
    with pytest.raises(FrameFormatError, match="dtype float32, expected uint16"):
        frame_to_depth(depth(1, dtype=np.float32))
    with pytest.raises(FrameFormatError, match=r"depth frame is 640x400 \(WxH\), expected 640x480") as e:
        frame_to_depth(depth(1, shape=(400, 640)), expected_hw=(480, 640))
    assert isinstance(e.value, ValueError) and isinstance(e.value, HardwareError)
    assert not e.value.retryable and str(e.value).startswith("camera: ")
    with pytest.raises(FrameFormatError, match="expected \\(H, W\\)"):
        frame_to_depth(np.zeros((H, W, 3), np.uint16))


# ------------------------------------------------------------------------------- synchroniser


def test_sync_pairs_nearest_timestamp():
    s = FrameSynchronizer(max_skew_s=0.02)
    for t in (0.0, 0.1, 0.2):
        s.push_rgb(f"rgb{t}", t)
    s.push_depth("d", 0.105)
    p = s.pop_pair()
    assert (p.rgb, p.depth, p.t_rgb, p.t_depth) == ("rgb0.1", "d", 0.1, 0.105)
    assert p.skew_s == pytest.approx(-0.005)
    assert s.sizes() == (1, 0)                       # rgb 0.0 was stale and dropped; 0.2 waits
    assert s.pop_pair() is None


def test_sync_respects_max_skew_and_accepts_timedelta():
    s = FrameSynchronizer(max_skew_s=0.02)
    s.push_rgb("r", timedelta(seconds=5.0))
    s.push_depth("d", timedelta(seconds=5.03))
    assert s.pop_pair() is None
    s.push_depth("d2", timedelta(seconds=5.019))
    p = s.pop_pair()
    assert p.depth == "d2" and p.t_rgb == 5.0


def test_sync_prefers_closest_pair():
    s = FrameSynchronizer(max_skew_s=0.02)
    s.push_rgb("r1", 1.0)
    s.push_depth("d1", 1.015)
    s.push_rgb("r2", 1.1)
    s.push_depth("d2", 1.101)
    p = s.pop_pair()
    assert (p.rgb, p.depth) == ("r2", "d2")
    assert len(s) == 0                               # the older, worse pair is stale now


def test_sync_out_of_order_and_missing_depth():
    s = FrameSynchronizer(max_skew_s=0.01)
    s.push_depth("d0.2", 0.2)                        # arrives before older frames
    s.push_rgb("r0.2", 0.2)
    s.push_rgb("r0.0", 0.0)
    s.push_rgb("r0.1", 0.1)                          # its depth frame never comes
    s.push_depth("d0.0", 0.0)
    p = s.pop_pair()
    assert (p.rgb, p.depth) == ("r0.0", "d0.0")
    p = s.pop_pair()
    assert (p.rgb, p.depth) == ("r0.2", "d0.2")
    assert s.pop_pair() is None and len(s) == 0
    assert s.dropped == 1                            # r0.1


def test_sync_bounded_memory_and_age():
    s = FrameSynchronizer(max_skew_s=0.01, max_frames=8, max_age_s=1.0)
    for i in range(1000):                            # colour only: depth stream is dead
        s.push_rgb(i, i * 0.001)
    assert s.sizes() == (8, 0)
    assert s.dropped == 992
    s.push_depth("late", 0.0)                        # matches a frame long gone
    assert s.pop_pair() is None
    s.push_depth("new", 5.0)                         # a much newer frame ages the colour out
    assert s.sizes() == (0, 1)
    assert not s.push_rgb("ancient", 3.0)            # older than max_age before the newest: refused


def test_sync_reset_ignores_older_frames():
    s = FrameSynchronizer(max_skew_s=0.02)
    s.push_rgb("old", 1.0)
    s.reset(min_t=2.0)
    assert len(s) == 0
    assert not s.push_rgb("before", 1.99)
    assert s.push_rgb("after", 2.0) and s.push_depth("d", 2.01)
    assert s.pop_pair().rgb == "after"


# ------------------------------------------------------------------------------- grab on fake queues


def test_grab_returns_the_right_pair():
    rgb_q = FakeQueue([
        (0.0, FakeFrame(bgr(1), T0 - 0.05, seq=1)),     # captured before the call: ignored
        (0.0, FakeFrame(bgr(2), T0 + 0.05, seq=2)),     # its depth never arrives
        (0.05, FakeFrame(bgr(3), T0 + 0.15, seq=3)),
        (0.10, FakeFrame(bgr(4), T0 + 0.25, seq=4)),
    ])
    depth_q = FakeQueue([
        (0.0, FakeFrame(depth(100), T0 - 0.05)),
        (0.08, FakeFrame(depth(300), T0 + 0.16, seq=7)),
    ])
    cam = camera_on({"rgb": rgb_q, "depth": depth_q})
    t = time.monotonic()
    f = cam.grab(timeout_s=2.0)
    assert time.monotonic() - t < 1.0
    assert f.rgb.shape == (H, W, 3) and f.rgb.dtype == np.uint8
    assert tuple(f.rgb[0, 0]) == (252, 0, 3)                 # RGB of frame 3
    assert f.depth.dtype == np.uint16 and (f.depth == 300).all()
    assert (f.t_rgb, f.t_depth) == (pytest.approx(T0 + 0.15), pytest.approx(T0 + 0.16))
    assert f.meta["seq_rgb"] == 3 and f.meta["seq_depth"] == 7
    assert f.meta["skew_s"] == pytest.approx(-0.01)


def test_grab_from_sync_node_groups():
    q = FakeQueue([
        (0.0, FakeGroup(rgb=FakeFrame(bgr(1), T0 - 1.0), depth=FakeFrame(depth(1), T0 - 1.0))),
        (0.02, FakeGroup(rgb=FakeFrame(bgr(9), T0 + 0.1), depth=FakeFrame(depth(9), T0 + 0.1))),
    ])
    f = camera_on({"rgbd": q}).grab(1.0)
    assert tuple(f.rgb[0, 0]) == (246, 0, 9) and (f.depth == 9).all()


def test_grab_with_real_depthai_messages():
    dai = pytest.importorskip("depthai")

    def img(arr, t, typ):
        m = dai.ImgFrame()
        if typ == "RAW16":
            m.setFrame(arr)
            m.setType(dai.ImgFrame.Type.RAW16)
            m.setWidth(W)
            m.setHeight(H)
        else:
            m.setCvFrame(arr, getattr(dai.ImgFrame.Type, typ))
        m.setTimestamp(timedelta(seconds=t))
        return m

    g = dai.MessageGroup()
    g["rgb"] = img(bgr(5), T0 + 0.1, "NV12")
    g["depth"] = img(depth(777), T0 + 0.101, "RAW16")
    f = camera_on({"rgbd": FakeQueue([(0.0, g)])}).grab(1.0)
    assert np.abs(f.rgb[0, 0].astype(int) - (250, 0, 5)).max() <= 6
    assert (f.depth == 777).all() and f.t_rgb == pytest.approx(T0 + 0.1)
    assert "K_frame" not in f.meta                   # host-made frames carry no valid transformation


def test_grab_times_out_with_hardware_error():
    cam = camera_on({"rgb": FakeQueue(), "depth": FakeQueue()})
    t = time.monotonic()
    with pytest.raises(HardwareError, match=r"^camera: no synchronised colour\+depth pair within 0.3 s") as e:
        cam.grab(timeout_s=0.3)
    assert 0.3 <= time.monotonic() - t < 0.8
    assert e.value.retryable


def test_grab_times_out_when_depth_is_missing():
    rgb_q = FakeQueue([(0.01 * i, FakeFrame(bgr(i), T0 + 0.01 * i)) for i in range(1, 20)])
    depth_q = FakeQueue([(0.0, FakeFrame(depth(1), T0 + 0.5))])        # never close enough in time
    cam = camera_on({"rgb": rgb_q, "depth": depth_q})
    t = time.monotonic()
    with pytest.raises(HardwareError, match=r"within 0.4 s \(\d+ colour, 1 depth frames"):
        cam.grab(0.4)
    assert time.monotonic() - t < 0.9
    assert cam._sync.sizes()[0] <= cam._sync.max_frames


def test_grab_rejects_a_wrong_depth_size():
    cam = camera_on({"rgb": FakeQueue([(0, FakeFrame(bgr(1), T0 + 0.1))]),
                     "depth": FakeQueue([(0, FakeFrame(depth(1, shape=(H // 2, W)), T0 + 0.1))])})
    with pytest.raises(FrameFormatError, match=r"depth frame is 64x24 \(WxH\), expected 64x48"):
        cam.grab(1.0)


def test_grab_needs_connect():
    with pytest.raises(HardwareError, match="not connected"):
        OakDCamera().grab(0.1)
    with pytest.raises(HardwareError, match="unknown until connect"):
        OakDCamera().intrinsics()


def test_grab_reports_a_lost_device():
    class DeadQueue:
        def tryGet(self):
            raise RuntimeError("Communication exception - possible device error/misconfiguration")

    cam = camera_on({"rgb": DeadQueue(), "depth": FakeQueue()})
    with pytest.raises(HardwareError, match="reading the rgb queue failed .*device disconnected"):
        cam.grab(1.0)


# ------------------------------------------------------------------------------- connect / close


def test_connect_without_device_is_quick(monkeypatch):
    pytest.importorskip("depthai")
    monkeypatch.setattr(oakd, "list_devices", lambda: [])
    cam = OakDCamera(connect_timeout_s=0.3, device_id="14442C10D13EABCE00")
    t = time.monotonic()
    with pytest.raises(HardwareError, match="^camera: no OAK device found with id '14442C10D13EABCE00'"):
        cam.connect()
    assert time.monotonic() - t < 1.5
    assert cam._queues is None and cam._device is None
    cam.close()                                                        # never raises
    cam.close()


def test_connect_names_other_devices(monkeypatch):
    pytest.importorskip("depthai")
    other = types.SimpleNamespace(getDeviceId=lambda: "AAAA", name="1.3")
    monkeypatch.setattr(oakd, "list_devices", lambda: [other])
    with pytest.raises(HardwareError, match="available: 1.3, AAAA"):
        OakDCamera(connect_timeout_s=0.1, device_id="BBBB").connect()


def test_connect_with_real_depthai_and_no_device():
    """The real search, bounded: skipped where depthai cannot run or a camera is attached."""
    try:
        import depthai  # noqa: F401
    except Exception as e:  # noqa: BLE001
        pytest.skip(f"depthai does not import here: {e}")
    cam = OakDCamera(connect_timeout_s=1.0)
    box: dict = {}

    def run():
        try:
            cam.connect()
            box["ok"] = True
        except BaseException as e:  # noqa: BLE001
            box["err"] = e

    th = threading.Thread(target=run, daemon=True)
    t = time.monotonic()
    th.start()
    th.join(8.0)
    if th.is_alive():
        pytest.skip("depthai's device search did not return within 8 s here")
    if box.get("ok"):
        cam.close()
        pytest.skip("an OAK device is attached")
    err = box["err"]
    assert isinstance(err, HardwareError), repr(err)
    assert "no OAK device found" in str(err)
    assert time.monotonic() - t < 5.0


class _FakeDai:
    """Just enough of depthai for connect(): Pipeline(device) and CameraBoardSocket."""

    CameraBoardSocket = types.SimpleNamespace(CAM_A="CAM_A")

    class Pipeline:
        def __init__(self, device):
            self.device, self.started, self.stopped = device, False, False

        def start(self):
            self.started = True

        def stop(self):
            self.stopped = True
            raise RuntimeError("already stopped")                   # close() must swallow this

        def isRunning(self):
            return self.started and not self.stopped


class _FakeDevice:
    closed = False

    def readCalibration(self):
        return types.SimpleNamespace(
            getCameraIntrinsics=lambda sock, w, h: [[500.0, 0, w / 2], [0, 501.0, h / 2], [0, 0, 1]])

    def getDeviceId(self):
        return "1844301011B546F500"

    def close(self):
        self.closed = True


class _LiveQueue:
    """Produces a frame stamped 'now' on every other tryGet."""

    def __init__(self, make):
        self.make, self.n = make, 0

    def tryGet(self):
        self.n += 1
        return self.make(oakd.host_clock() + 0.001) if self.n % 2 else None


def test_connect_reads_intrinsics_and_close_releases(monkeypatch):
    dev = _FakeDevice()
    built = {}

    def fake_build(pipeline, width, height, fps, **kw):
        built.update(pipeline=pipeline, size=(width, height), fps=fps, **kw)
        t_fixed = {}

        def stamp(t):                                  # colour and depth of one capture share a time
            return t_fixed.setdefault("t", t)

        return {"rgb": _LiveQueue(lambda t: FakeFrame(bgr(1), stamp(t))),
                "depth": _LiveQueue(lambda t: FakeFrame(depth(1), stamp(t)))}

    monkeypatch.setattr(oakd, "_import_depthai", lambda: _FakeDai)
    monkeypatch.setattr(oakd, "open_device", lambda device_id, timeout_s: dev)
    monkeypatch.setattr(oakd, "build_pipeline", fake_build)
    cam = OakDCamera(width=W, height=H, fps=10.0, extended_disparity=True, subpixel=False, lr_check=True,
                     max_sync_skew_s=0.03)
    cam.connect()
    assert built["size"] == (W, H) and built["fps"] == 10.0
    assert built["extended_disparity"] is True and built["subpixel"] is False and built["lr_check"] is True
    assert built["max_sync_skew_s"] == 0.03
    assert built["pipeline"].started
    intr = cam.intrinsics()
    assert intr["K"] == [500.0, 0, W / 2, 0, 501.0, H / 2, 0, 0, 1]
    assert (intr["width"], intr["height"], intr["depth_scale"]) == (W, H, 1.0)
    assert intr["device"] == "1844301011B546F500"
    f = cam.grab(10.0)  # returns at the first pair; the first grab of a process imports depthai (1 s+ when busy)
    assert f.meta["device"] == "1844301011B546F500"
    cam.close()
    assert dev.closed and built["pipeline"].stopped
    with pytest.raises(HardwareError, match="not connected"):
        cam.grab(0.1)


class _FakeTransformation:
    def __init__(self, K, size):
        self.K, self.size = K, size

    def isValid(self):
        return True

    def getSize(self):
        return self.size

    def getIntrinsicMatrix(self):
        return self.K


def test_connect_prefers_the_intrinsics_frames_carry(monkeypatch):
    K = [[510.0, 0, 33.0], [0, 511.0, 23.5], [0, 0, 1]]

    def make_rgb(t):
        f = FakeFrame(bgr(1), t)
        f.getTransformation = lambda: _FakeTransformation(K, (W, H))
        return f

    t_fixed = {}

    def stamp(t):
        return t_fixed.setdefault("t", t)

    monkeypatch.setattr(oakd, "_import_depthai", lambda: _FakeDai)
    monkeypatch.setattr(oakd, "open_device", lambda device_id, timeout_s: _FakeDevice())
    monkeypatch.setattr(oakd, "build_pipeline", lambda *a, **k: {
        "rgb": _LiveQueue(lambda t: make_rgb(stamp(t))), "depth": _LiveQueue(lambda t: FakeFrame(depth(1), stamp(t)))})
    cam = OakDCamera(width=W, height=H)
    cam.connect()
    intr = cam.intrinsics()
    assert intr["K"] == [510.0, 0, 33.0, 0, 511.0, 23.5, 0, 0, 1] and intr["K_source"] == "frame"
    cam.close()
    # a transformation of another size (or an invalid one, as host-made frames carry) is ignored
    assert OakDCamera(width=W, height=H)._frame_intrinsics(types.SimpleNamespace(
        getTransformation=lambda: _FakeTransformation(K, (2 * W, 2 * H)))) is None


def test_connect_failure_in_pipeline_is_one_line_and_closes(monkeypatch):
    dev = _FakeDevice()

    def broken_build(*a, **k):
        raise RuntimeError("Camera on socket CAM_C not found\nmore detail")

    monkeypatch.setattr(oakd, "_import_depthai", lambda: _FakeDai)
    monkeypatch.setattr(oakd, "open_device", lambda device_id, timeout_s: dev)
    monkeypatch.setattr(oakd, "build_pipeline", broken_build)
    cam = OakDCamera(connect_timeout_s=1.0)
    with pytest.raises(HardwareError, match="CAM_C not found more detail") as e:
        cam.connect()
    assert "\n" not in str(e.value)
    assert dev.closed and cam._device is None


# ------------------------------------------------------------------------------- the device side


def test_build_pipeline_is_importable_and_documented():
    assert issubclass(OakDCamera, RGBDCamera)
    params = inspect.signature(build_pipeline).parameters
    assert list(params)[:4] == ["pipeline", "width", "height", "fps"]
    for name in ("extended_disparity", "subpixel", "lr_check", "align", "use_sync_node", "max_sync_skew_s"):
        assert params[name].kind is inspect.Parameter.KEYWORD_ONLY
    doc = inspect.getdoc(build_pipeline)
    for word in ("CAM_A", "CAM_B", "CAM_C", "StereoDepth", "inputAlignTo", "setDepthAlign", "Sync", "Needs a device"):
        assert word in doc
    ctor = inspect.signature(OakDCamera).parameters
    assert {k: ctor[k].default for k in ctor} == {
        "width": 640, "height": 480, "fps": 10.0, "device_id": None, "connect_timeout_s": 10.0,
        "max_sync_skew_s": 0.02, "extended_disparity": False, "subpixel": True, "lr_check": True}


class _SpecPipeline:
    """A dai.Pipeline stand-in whose nodes are mocks spec'd on the installed depthai classes, so
    build_pipeline's node and method names are checked against depthai without a device."""

    def __init__(self, platform=None):
        from unittest import mock

        self.mock, self.nodes, self.platform = mock, [], platform

    def create(self, cls):
        node = self.mock.MagicMock(spec=cls, name=cls.__name__)
        if hasattr(cls, "build"):
            node.build.return_value = node
        self.nodes.append((cls, node))
        return node

    def getDefaultDevice(self):
        return types.SimpleNamespace(getPlatform=lambda: self.platform)

    def of(self, cls):
        return [n for c, n in self.nodes if c is cls]


def test_build_pipeline_names_exist_in_installed_depthai():
    dai = pytest.importorskip("depthai")
    p = _SpecPipeline(platform=dai.Platform.RVC2)
    queues = build_pipeline(p, 640, 480, 10.0, extended_disparity=True, subpixel=True, lr_check=False)
    assert set(queues) == {"rgb", "depth"}
    cams = p.of(dai.node.Camera)
    assert [c.build.call_args.args[0] for c in cams] == [dai.CameraBoardSocket.CAM_A, dai.CameraBoardSocket.CAM_B,
                                                        dai.CameraBoardSocket.CAM_C]
    rgb_call = cams[0].requestOutput.call_args
    assert rgb_call.args[0] == (640, 480) and rgb_call.kwargs["type"] == dai.ImgFrame.Type.BGR888i
    (stereo,) = p.of(dai.node.StereoDepth)
    stereo.setExtendedDisparity.assert_called_once_with(True)
    stereo.setLeftRightCheck.assert_called_once_with(False)
    cams[0].requestOutput.return_value.link.assert_any_call(stereo.inputAlignTo)
    stereo.setDepthAlign.assert_not_called()

    p = _SpecPipeline()
    build_pipeline(p, 640, 480, 10.0, align="socket")
    (stereo,) = p.of(dai.node.StereoDepth)
    stereo.setDepthAlign.assert_called_once_with(dai.CameraBoardSocket.CAM_A)
    stereo.setOutputSize.assert_called_once_with(640, 480)

    p = _SpecPipeline(platform=dai.Platform.RVC4)
    queues = build_pipeline(p, 640, 480, 10.0, use_sync_node=True, max_sync_skew_s=0.025)
    assert set(queues) == {"rgbd"} and len(p.of(dai.node.ImageAlign)) == 1
    (sync,) = p.of(dai.node.Sync)
    sync.setSyncThreshold.assert_called_once_with(timedelta(seconds=0.025))
    with pytest.raises(ValueError, match="align must be"):
        build_pipeline(_SpecPipeline(), 640, 480, 10.0, align="centre")
