"""OAK-D colour + aligned depth through depthai v3.

Two halves, kept apart on purpose:

* **device side** — :func:`build_pipeline` is the *only* code that creates depthai nodes (colour
  camera on CAM_A, mono pair on CAM_B/CAM_C, StereoDepth aligned to the colour output, optional
  on-device Sync). Adapting to another OAK model means editing that one function.
  :func:`open_device` finds and opens the device with a bounded search.
* **host side** — plain functions that run (and are tested) without hardware:
  :func:`~tdof20.capture.hardware.oakd_frames.frame_to_rgb`, ``frame_to_depth``,
  ``FrameSynchronizer`` (pairs colour and depth by nearest timestamp; all three in
  :mod:`tdof20.capture.hardware.oakd_frames`, their names importable from here) and
  :meth:`OakDCamera.grab`, which polls the output queues with non-blocking ``tryGet()`` under a
  deadline.

Timestamps: depthai's ``ImgFrame.getTimestamp()`` is the capture time on the host's steady clock
(``dai.Clock.now()``; on Linux the same clock as ``time.monotonic()``), as a ``timedelta``. The
synchroniser pairs on it, and ``grab`` uses it to return only frames whose exposure started after
the call. Depth is uint16 millimetres (``depth_scale`` 1.0), 0 = no depth.

Manual smoke test with a device attached::

    python -m tdof20.capture.hardware.oakd --frames 5 --out /tmp/oakd
"""

from __future__ import annotations

import datetime as _dt
import logging
import time
from typing import Any, Callable, Mapping

import numpy as np

from tdof20.capture.hardware.interfaces import HardwareError, RGBDCamera, RGBDFrame, call_with_timeout
from tdof20.capture.hardware.oakd_frames import (DEPTH_STREAM, DEVICE, RGB_STREAM, FrameFormatError, FramePair,
                                                 FrameSynchronizer, frame_to_depth, frame_to_rgb, to_seconds)

log = logging.getLogger(__name__)

SYNC_STREAM = "rgbd"


# --------------------------------------------------------------------------------------------
# small helpers
# --------------------------------------------------------------------------------------------


def _import_depthai():
    """depthai, imported on first use (importing it probes USB and logs a warning)."""
    try:
        import depthai as dai  # noqa: PLC0415
    except Exception as e:  # noqa: BLE001 - ImportError or a broken native library
        raise HardwareError(DEVICE, f"depthai cannot be imported ({type(e).__name__}: {e}); "
                            "install it with `pip install depthai==3.12.0`", retryable=False) from e
    return dai



def host_clock() -> float:
    """Now, in seconds, on the clock depthai stamps frames with (``dai.Clock.now()``)."""
    try:
        import depthai as dai  # noqa: PLC0415

        return dai.Clock.now().total_seconds()
    except Exception:  # noqa: BLE001 - depthai missing: steady clock of the host
        return time.monotonic()


def _exposure_start_s(msg: Any) -> float:
    """When the exposure of ``msg`` started (seconds), or its plain timestamp where the message
    carries no exposure information (a fake frame, a message group)."""
    try:
        import depthai as dai  # noqa: PLC0415

        return to_seconds(msg.getTimestamp(dai.CameraExposureOffset.START))
    except Exception:  # noqa: BLE001 - no depthai, or getTimestamp() takes no offset
        return to_seconds(msg.getTimestamp())


def _try(fn: Callable[[], Any], default: Any = None) -> Any:
    try:
        return fn()
    except Exception:  # noqa: BLE001 - optional metadata
        return default



# --------------------------------------------------------------------------------------------
# device side: the one place that builds depthai nodes
# --------------------------------------------------------------------------------------------


def build_pipeline(pipeline: Any, width: int, height: int, fps: float, *,
                   extended_disparity: bool = False, subpixel: bool = True, lr_check: bool = True,
                   mono_size: tuple[int, int] = (640, 400), preset: str = "DEFAULT",
                   align: str = "frame", use_sync_node: bool = False, max_sync_skew_s: float = 0.02,
                   queue_size: int = 4) -> dict[str, Any]:
    """Build the OAK-D RGB-D graph on ``pipeline`` (a ``dai.Pipeline`` bound to an open device)
    and return its host output queues. **Needs a device**: depthai 3.x builds device nodes only
    with one attached; everything else in this module runs without.

    Nodes:

    * ``Camera`` on ``CAM_A`` -> one output of ``(width, height)`` BGR888i (``ImgResizeMode.CROP``,
      undistorted) at ``fps``: the colour image;
    * ``Camera`` on ``CAM_B`` / ``CAM_C`` -> ``mono_size`` outputs at ``fps`` -> ``StereoDepth``
      (``preset`` from ``dai.node.StereoDepth.PresetMode``, then ``extended_disparity``,
      ``subpixel``, ``lr_check``) -> depth, uint16 mm;
    * depth alignment to the colour image, ``align``:
      ``"frame"`` (default) links the colour output to ``StereoDepth.inputAlignTo`` so the depth
      takes exactly the colour output's size, crop and intrinsics (on an RVC4 device an
      ``ImageAlign`` node does the same); ``"socket"`` uses
      ``setDepthAlign(CameraBoardSocket.CAM_A)`` + ``setOutputSize(width, height)`` (the sensor's
      full field of view scaled: matches the colour only when the colour output is not cropped);
    * ``use_sync_node``: a ``Sync`` node (threshold ``max_sync_skew_s``) pairs colour and depth
      on the device and one queue carries ``MessageGroup`` s with members ``"rgb"`` and
      ``"depth"``; otherwise (default) the two streams come separately and the host pairs them
      (:class:`FrameSynchronizer`).

    Returns ``{"rgb": queue, "depth": queue}`` or ``{"rgbd": queue}``; each a non-blocking
    ``MessageQueue`` of ``queue_size`` (old frames are overwritten while nobody reads).
    The caller starts the pipeline (``pipeline.start()``).
    """
    dai = _import_depthai()
    size = (int(width), int(height))

    cam = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_A)
    rgb_out = cam.requestOutput(size, type=dai.ImgFrame.Type.BGR888i, resizeMode=dai.ImgResizeMode.CROP,
                                fps=float(fps), enableUndistortion=True)
    left = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_B)
    right = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_C)

    stereo = pipeline.create(dai.node.StereoDepth)
    stereo.setDefaultProfilePreset(getattr(dai.node.StereoDepth.PresetMode, preset))
    stereo.setExtendedDisparity(bool(extended_disparity))
    stereo.setSubpixel(bool(subpixel))
    stereo.setLeftRightCheck(bool(lr_check))
    left.requestOutput(tuple(mono_size), fps=float(fps)).link(stereo.left)
    right.requestOutput(tuple(mono_size), fps=float(fps)).link(stereo.right)

    depth_out = stereo.depth
    if align == "frame":
        platform = _try(lambda: pipeline.getDefaultDevice().getPlatform())
        if platform == dai.Platform.RVC4:      # StereoDepth cannot align there: ImageAlign does
            aligner = pipeline.create(dai.node.ImageAlign)
            stereo.depth.link(aligner.input)
            rgb_out.link(aligner.inputAlignTo)
            depth_out = aligner.outputAligned
        else:
            rgb_out.link(stereo.inputAlignTo)
    elif align == "socket":
        stereo.setDepthAlign(dai.CameraBoardSocket.CAM_A)
        stereo.setOutputSize(*size)
    else:
        raise ValueError(f"align must be 'frame' or 'socket', not {align!r}")

    if use_sync_node:
        sync = pipeline.create(dai.node.Sync)
        sync.setSyncThreshold(_dt.timedelta(seconds=float(max_sync_skew_s)))
        rgb_out.link(sync.inputs[RGB_STREAM])
        depth_out.link(sync.inputs[DEPTH_STREAM])
        return {SYNC_STREAM: sync.out.createOutputQueue(maxSize=queue_size, blocking=False)}
    return {
        RGB_STREAM: rgb_out.createOutputQueue(maxSize=queue_size, blocking=False),
        DEPTH_STREAM: depth_out.createOutputQueue(maxSize=queue_size, blocking=False),
    }


def list_devices() -> list[Any]:
    """The OAK devices free to open (``dai.Device.getAllAvailableDevices()``, ~0.5 s)."""
    return list(_import_depthai().Device.getAllAvailableDevices())


def _device_ids(info: Any) -> set[str]:
    return {str(x) for x in (_try(lambda: info.getDeviceId()), _try(lambda: info.name)) if x}


def open_device(device_id: str | None, timeout_s: float) -> Any:
    """Find the device (any, or the one whose id / name is ``device_id``) within ``timeout_s``
    and open it (``dai.Device(DeviceInfo)`` guarded by :func:`call_with_timeout`).

    Raises HardwareError "no OAK device found ..." when none appears in time.
    """
    dai = _import_depthai()
    deadline = time.monotonic() + float(timeout_s)
    seen: list[str] = []
    while True:
        infos = list_devices()
        seen = sorted({i for info in infos for i in _device_ids(info)})
        match = [info for info in infos if device_id is None or device_id in _device_ids(info)]
        if match:
            break
        if time.monotonic() >= deadline:
            which = f"with id {device_id!r} " if device_id else ""
            others = f"; available: {', '.join(seen)}" if seen else ""
            raise HardwareError(DEVICE, f"no OAK device found {which}within {timeout_s:g} s{others} "
                                "(check the USB3 cable and power, the udev rule for 03e7, and that no "
                                "other program holds the camera)")
        time.sleep(0.2)
    remaining = max(1.0, deadline - time.monotonic())
    return call_with_timeout(lambda: dai.Device(match[0]), remaining, DEVICE, "opening the OAK device")


# --------------------------------------------------------------------------------------------
# the camera
# --------------------------------------------------------------------------------------------


class OakDCamera(RGBDCamera):
    """A Luxonis OAK-D: colour from CAM_A, stereo depth from CAM_B/CAM_C aligned to the colour.

    ``connect()`` opens the device (``device_id`` = its id/MxId or name, or any), builds the
    pipeline (:func:`build_pipeline`), starts it and waits for a first pair (which also fixes the
    intrinsics to those of the frames actually delivered). ``grab(timeout_s)`` returns the next
    pair whose colour and depth timestamps differ by at most ``max_sync_skew_s`` and whose
    exposures began after the call.
    """

    name = "camera"

    def __init__(self, width: int = 640, height: int = 480, fps: float = 10.0, device_id: str | None = None,
                 connect_timeout_s: float = 10.0, max_sync_skew_s: float = 0.02,
                 extended_disparity: bool = False, subpixel: bool = True, lr_check: bool = True):
        if width <= 0 or height <= 0 or fps <= 0:
            raise ValueError(f"camera: width, height and fps must be positive (got {width}, {height}, {fps})")
        self.width, self.height, self.fps = int(width), int(height), float(fps)
        self.device_id = device_id or None
        self.connect_timeout_s = float(connect_timeout_s)
        self.max_sync_skew_s = float(max_sync_skew_s)
        self.extended_disparity = bool(extended_disparity)
        self.subpixel = bool(subpixel)
        self.lr_check = bool(lr_check)
        self.pipeline_options: dict[str, Any] = {}   # extra build_pipeline keywords (align, preset, ...)
        self._device: Any = None
        self._pipeline: Any = None
        self._queues: dict[str, Any] | None = None
        self._intrinsics: dict | None = None
        self._clock: Callable[[], float] = host_clock
        self._sync = FrameSynchronizer(self.max_sync_skew_s)

    # -- lifecycle -----------------------------------------------------------------------------
    def connect(self) -> None:
        if self._queues is not None:
            return
        dai = _import_depthai()
        self._device = open_device(self.device_id, self.connect_timeout_s)
        try:
            device = self._device

            def start() -> tuple[Any, dict[str, Any]]:
                pipeline = dai.Pipeline(device)
                queues = build_pipeline(
                    pipeline, self.width, self.height, self.fps, extended_disparity=self.extended_disparity,
                    subpixel=self.subpixel, lr_check=self.lr_check, max_sync_skew_s=self.max_sync_skew_s,
                    **self.pipeline_options)
                pipeline.start()
                return pipeline, queues

            self._pipeline, queues = call_with_timeout(start, self.connect_timeout_s, DEVICE,
                                                       "building and starting the OAK pipeline")
            calib = call_with_timeout(device.readCalibration, self.connect_timeout_s, DEVICE,
                                      "reading the OAK calibration")
            K = np.asarray(calib.getCameraIntrinsics(dai.CameraBoardSocket.CAM_A, self.width, self.height),
                           dtype=float)
            serial = _try(lambda: device.getDeviceId()) or _try(lambda: device.getMxId()) or self.device_id
            intr = {"K": [float(v) for v in K.reshape(9)], "width": self.width, "height": self.height,
                    "depth_scale": 1.0, "device": serial, "K_source": "calibration"}
            self.attach(queues, intr)
            # A first pair proves the pipeline runs; its colour frame carries the intrinsics of the
            # output actually delivered (crop, undistortion), which wins over the calibration's.
            first = self.grab(max(self.connect_timeout_s, 3.0 / self.fps))
            K_frame = first.meta.get("K_frame")
            if K_frame is not None:
                if np.max(np.abs(np.asarray(K_frame) - K.reshape(9))) > 0.5:
                    log.info("camera: frame intrinsics %s differ from calibration %s; using the frame's",
                             K_frame, K.reshape(9).tolist())
                intr["K"], intr["K_source"] = list(K_frame), "frame"
                self._intrinsics = intr
            log.info("camera: OAK %s streaming %dx%d at %g fps", serial, self.width, self.height, self.fps)
        except HardwareError:
            self.close()
            raise
        except Exception as e:  # noqa: BLE001 - any depthai failure becomes one line
            self.close()
            raise HardwareError(DEVICE, f"starting the OAK pipeline failed: {type(e).__name__}: {e}") from e

    def attach(self, queues: Mapping[str, Any], intrinsics: dict | None = None,
               clock: Callable[[], float] | None = None) -> None:
        """Use already-built output queues (tests, replay, a custom pipeline): ``{"rgb", "depth"}``
        or ``{"rgbd"}`` (message groups), each with a non-blocking ``tryGet()``. ``clock`` gives
        "now" on the frames' time base (default: ``dai.Clock.now()``)."""
        if not (set(queues) >= {RGB_STREAM, DEPTH_STREAM} or SYNC_STREAM in queues):
            raise ValueError(f"camera: queues must be 'rgb' + 'depth' or 'rgbd', got {sorted(queues)}")
        self._queues = dict(queues)
        if intrinsics is not None:
            self._intrinsics = dict(intrinsics)
        if clock is not None:
            self._clock = clock

    def close(self) -> None:
        """Stop the pipeline and release the device; best effort, never raises."""
        pipeline, device = self._pipeline, self._device
        self._pipeline = self._device = self._queues = None
        for step in (lambda: pipeline is not None and pipeline.stop(),
                     lambda: device is not None and device.close()):
            try:
                step()
            except Exception as e:  # noqa: BLE001 - closing must not fail
                log.debug("camera: ignored while closing: %s", e)

    def __enter__(self) -> "OakDCamera":
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- data ----------------------------------------------------------------------------------
    def intrinsics(self) -> dict:
        if self._intrinsics is None:
            raise HardwareError(DEVICE, "intrinsics are unknown until connect() succeeded", retryable=False)
        return dict(self._intrinsics, K=list(self._intrinsics["K"]))

    def _receive(self, stream: str, msg: Any, t_start: float) -> tuple[int, int]:
        """Hand one queue message to the synchroniser; returns (colour, depth) frames accepted."""
        if stream == SYNC_STREAM or hasattr(msg, "getMessageNames"):
            names = set(msg.getMessageNames())
            if not {RGB_STREAM, DEPTH_STREAM} <= names:
                return 0, 0
            a = self._receive(RGB_STREAM, msg[RGB_STREAM], t_start)
            b = self._receive(DEPTH_STREAM, msg[DEPTH_STREAM], t_start)
            return a[0] + b[0], a[1] + b[1]
        if _exposure_start_s(msg) < t_start:      # exposed (partly) before the call: stale
            self._sync.dropped += 1
            return 0, 0
        t = to_seconds(msg.getTimestamp())
        if stream == RGB_STREAM:
            return int(self._sync.push_rgb(msg, t)), 0
        return 0, int(self._sync.push_depth(msg, t))

    def grab(self, timeout_s: float) -> RGBDFrame:
        """The next colour + depth pair captured after this call started (see class docs).

        Raises HardwareError "no synchronised colour+depth pair within X s" after ``timeout_s``,
        FrameFormatError when a frame has the wrong size or dtype, HardwareError when the
        device was lost."""
        if self._queues is None:
            raise HardwareError(DEVICE, "not connected: call connect() first", retryable=False)
        timeout_s = float(timeout_s)
        deadline = time.monotonic() + timeout_s
        t_start = float(self._clock())
        self._sync.max_skew_s = self.max_sync_skew_s
        self._sync.reset(min_t=None)
        n_rgb = n_depth = 0
        while True:
            got = False
            for stream, q in self._queues.items():
                for _ in range(64):               # bounded: a fast producer cannot starve us
                    try:
                        msg = q.tryGet()
                    except Exception as e:  # noqa: BLE001 - closed queue / lost device
                        raise HardwareError(DEVICE, f"reading the {stream} queue failed "
                                            f"(device disconnected?): {type(e).__name__}: {e}") from e
                    if msg is None:
                        break
                    got = True
                    a, b = self._receive(stream, msg, t_start)
                    n_rgb, n_depth = n_rgb + a, n_depth + b
            pair = self._sync.pop_pair()
            if pair is not None:
                return self._to_frame(pair)
            if time.monotonic() >= deadline:
                raise HardwareError(
                    DEVICE, f"no synchronised colour+depth pair within {timeout_s:g} s ({n_rgb} colour, "
                    f"{n_depth} depth frames since the call; max skew {self.max_sync_skew_s * 1000:g} ms)")
            if self._pipeline is not None and not _try(lambda: self._pipeline.isRunning(), True):
                raise HardwareError(DEVICE, "the OAK pipeline stopped (device disconnected?)")
            if not got:
                time.sleep(0.001)

    def _frame_intrinsics(self, msg: Any) -> list[float] | None:
        """The 3x3 K (row-major) a depthai frame carries in its ImgTransformation (v3), when it is
        valid and for this output size; None otherwise (fakes, host-made frames)."""
        tr = _try(lambda: msg.getTransformation())
        if tr is None or not _try(lambda: bool(tr.isValid()), False):
            return None
        if tuple(_try(lambda: tuple(tr.getSize()), ())) != (self.width, self.height):
            return None
        K = _try(lambda: np.asarray(tr.getIntrinsicMatrix(), dtype=float))
        if K is None or K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 1.0 or K[1, 1] <= 1.0:
            return None
        return [float(v) for v in K.reshape(9)]

    def _to_frame(self, pair: FramePair) -> RGBDFrame:
        hw = (self.height, self.width)
        rgb = frame_to_rgb(pair.rgb, expected_hw=hw)
        depth = frame_to_depth(pair.depth, expected_hw=hw)
        meta: dict[str, Any] = {"skew_s": pair.skew_s}
        for key, msg in (("rgb", pair.rgb), ("depth", pair.depth)):
            seq = _try(lambda: msg.getSequenceNum())
            if seq is not None:
                meta[f"seq_{key}"] = int(seq)
            t_dev = _try(lambda: msg.getTimestampDevice())
            if t_dev is not None:
                meta[f"t_{key}_device"] = to_seconds(t_dev)
        K_frame = self._frame_intrinsics(pair.rgb)
        if K_frame is not None:
            meta["K_frame"] = K_frame
        if self._intrinsics is not None and self._intrinsics.get("device"):
            meta["device"] = self._intrinsics["device"]
        return RGBDFrame(rgb=rgb, depth=depth, t_rgb=pair.t_rgb, t_depth=pair.t_depth, meta=meta)


# --------------------------------------------------------------------------------------------
# manual hardware smoke test
# --------------------------------------------------------------------------------------------


def _main(argv: list[str] | None = None) -> int:
    import argparse  # noqa: PLC0415
    import json  # noqa: PLC0415
    from pathlib import Path  # noqa: PLC0415

    import cv2  # noqa: PLC0415

    ap = argparse.ArgumentParser(description="OAK-D smoke test: grab a few colour+depth pairs, write PNGs.")
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument("--out", type=Path, default=Path("oakd_smoke"))
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--fps", type=float, default=10.0)
    ap.add_argument("--device-id", default=None)
    ap.add_argument("--align", choices=("frame", "socket"), default="frame")
    ap.add_argument("--sync-node", action="store_true", help="pair on the device (Sync node)")
    ap.add_argument("--timeout", type=float, default=2.0)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")

    cam = OakDCamera(args.width, args.height, args.fps, device_id=args.device_id)
    cam.pipeline_options = {"align": args.align, "use_sync_node": args.sync_node}
    try:
        t0 = time.monotonic()
        cam.connect()
        print(f"connected in {time.monotonic() - t0:.2f} s")
        print("intrinsics:", json.dumps(cam.intrinsics()))
        args.out.mkdir(parents=True, exist_ok=True)
        t0, t_prev = time.monotonic(), None
        for i in range(args.frames):
            f = cam.grab(args.timeout)
            cv2.imwrite(str(args.out / f"{i:06d}_rgb.png"), cv2.cvtColor(f.rgb, cv2.COLOR_RGB2BGR))
            cv2.imwrite(str(args.out / f"{i:06d}_depth.png"), f.depth)
            valid = f.depth[f.depth > 0]
            dt = "" if t_prev is None else f", dt {1000 * (f.t_rgb - t_prev):.0f} ms"
            t_prev = f.t_rgb
            print(f"pair {i}: skew {1000 * f.meta['skew_s']:+.1f} ms{dt}, depth valid "
                  f"{valid.size / f.depth.size:.0%}, median {np.median(valid) if valid.size else 0:.0f} mm")
        dt = time.monotonic() - t0
        print(f"{args.frames} pairs in {dt:.2f} s = {args.frames / dt:.1f} pairs/s; PNGs in {args.out}")
    except HardwareError as e:
        print(f"error: {e}")
        return 1
    finally:
        cam.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(_main())
