"""OAK-D frames on the host, without depthai (so they run, and are tested, without hardware):
frame conversion (:func:`frame_to_rgb`, :func:`frame_to_depth`) and the pairing of colour and
depth by nearest timestamp (:class:`FrameSynchronizer`). The device side and the camera:
:mod:`tdof20.capture.hardware.oakd`."""

from __future__ import annotations

import bisect
import datetime as _dt
from dataclasses import dataclass
from typing import Any

import numpy as np

from tdof20.capture.hardware.interfaces import HardwareError

DEVICE = "camera"
RGB_STREAM = "rgb"
DEPTH_STREAM = "depth"


def to_seconds(t: Any) -> float:
    """A timestamp as float seconds: ``datetime.timedelta`` (depthai) or a number."""
    if isinstance(t, _dt.timedelta):
        return t.total_seconds()
    return float(t)


# --------------------------------------------------------------------------------------------
# frame conversion
# --------------------------------------------------------------------------------------------
class FrameFormatError(HardwareError, ValueError):
    """A frame has the wrong type, dtype or size (a configuration problem: not retryable)."""

    def __init__(self, message: str):
        super().__init__(DEVICE, message, retryable=False)


def _check_hw(arr: np.ndarray, expected_hw: tuple[int, int] | None, what: str) -> None:
    if expected_hw is not None and tuple(arr.shape[:2]) != tuple(expected_hw):
        h, w = arr.shape[:2]
        eh, ew = expected_hw
        raise FrameFormatError(f"{what} frame is {w}x{h} (WxH), expected {ew}x{eh}")


def frame_to_rgb(frame: Any, fmt: str = "bgr", expected_hw: tuple[int, int] | None = None) -> np.ndarray:
    """A colour frame as a contiguous (H,W,3) uint8 **RGB** array.

    ``frame`` is a depthai ``ImgFrame`` (anything with ``getCvFrame()``: depthai converts every
    colour type — BGR/RGB planar or interleaved, NV12, YUV420 — to BGR there, GRAY8 to (H,W)),
    or a numpy array laid out as ``fmt``:

    * ``"bgr"`` (H,W,3) — OpenCV order, what ``getCvFrame()`` returns (default);
    * ``"rgb"`` (H,W,3);
    * ``"bgra"`` (H,W,4);
    * ``"nv12"`` (H*3/2, W) — the Y plane then interleaved UV at half resolution;
    * ``"gray"`` (H,W).

    ``expected_hw`` = (height, width) checks the size. Raises :class:`FrameFormatError`.
    """
    import cv2  # noqa: PLC0415

    if hasattr(frame, "getCvFrame"):
        arr = np.asarray(frame.getCvFrame())
        fmt = "gray" if arr.ndim == 2 else ("bgra" if arr.ndim == 3 and arr.shape[2] == 4 else "bgr")
    else:
        arr = np.asarray(frame)
    fmt = fmt.lower()
    if arr.dtype != np.uint8:
        raise FrameFormatError(f"colour frame has dtype {arr.dtype}, expected uint8")
    if fmt == "nv12":
        if arr.ndim != 2 or arr.shape[0] % 3 or arr.shape[1] % 2 or (arr.shape[0] // 3) % 2:
            raise FrameFormatError(f"NV12 frame has shape {arr.shape}, expected (H*3/2, W) with even H and W")
        rgb = cv2.cvtColor(arr, cv2.COLOR_YUV2RGB_NV12)
    elif fmt == "gray":
        if arr.ndim == 3 and arr.shape[2] == 1:
            arr = arr[..., 0]
        if arr.ndim != 2:
            raise FrameFormatError(f"grey frame has shape {arr.shape}, expected (H, W)")
        rgb = cv2.cvtColor(arr, cv2.COLOR_GRAY2RGB)
    elif fmt in ("bgr", "rgb", "bgra"):
        channels = 4 if fmt == "bgra" else 3
        if arr.ndim != 3 or arr.shape[2] != channels:
            raise FrameFormatError(f"{fmt.upper()} frame has shape {arr.shape}, expected (H, W, {channels})")
        if fmt == "bgr":
            rgb = cv2.cvtColor(arr, cv2.COLOR_BGR2RGB)
        elif fmt == "bgra":
            rgb = cv2.cvtColor(arr, cv2.COLOR_BGRA2RGB)
        else:
            rgb = arr.copy()
    else:
        raise FrameFormatError(f"unknown colour format {fmt!r} (use bgr, rgb, bgra, nv12 or gray)")
    rgb = np.ascontiguousarray(rgb)
    _check_hw(rgb, expected_hw, "colour")
    return rgb


def frame_to_depth(frame: Any, expected_hw: tuple[int, int] | None = None) -> np.ndarray:
    """A depth frame as a (H,W) uint16 array in millimetres (0 = no depth), a copy.

    ``frame`` is a depthai ``ImgFrame`` from ``StereoDepth.depth`` (RAW16; read with
    ``getFrame()``) or a numpy array. Nothing is resized or converted: a dtype other than uint16
    or a size other than ``expected_hw`` = (height, width) raises :class:`FrameFormatError`
    naming what was expected and what came.
    """
    arr = np.asarray(frame.getFrame() if hasattr(frame, "getFrame") else frame)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if arr.ndim != 2:
        raise FrameFormatError(f"depth frame has shape {arr.shape}, expected (H, W)")
    if arr.dtype != np.uint16:
        raise FrameFormatError(f"depth frame has dtype {arr.dtype}, expected uint16 millimetres")
    _check_hw(arr, expected_hw, "depth")
    return np.array(arr, dtype=np.uint16, copy=True, order="C")


# --------------------------------------------------------------------------------------------
# synchronisation
# --------------------------------------------------------------------------------------------


@dataclass
class FramePair:
    """A colour and a depth message whose timestamps (seconds) lie within the allowed skew."""

    rgb: Any
    depth: Any
    t_rgb: float
    t_depth: float

    @property
    def skew_s(self) -> float:
        return self.t_rgb - self.t_depth


class FrameSynchronizer:
    """Pairs colour and depth frames by nearest timestamp.

    Frames may arrive late, out of order, or not at all. Each stream keeps at most ``max_frames``
    frames sorted by time (the oldest go first), and frames older than ``max_age_s`` before the
    newest frame seen are forgotten. :meth:`pop_pair` returns the pair with the smallest
    ``|t_rgb - t_depth|`` that is ``<= max_skew_s`` (the earlier pair on a tie) and drops it and
    every frame older than it in either stream (those can never be returned later: pairs come out
    in time order). ``reset(min_t)`` empties the buffers and ignores frames stamped before
    ``min_t`` from then on.
    """

    def __init__(self, max_skew_s: float = 0.02, max_frames: int = 16, max_age_s: float = 2.0):
        if max_skew_s < 0 or max_frames < 1 or max_age_s <= 0:
            raise ValueError("max_skew_s >= 0, max_frames >= 1 and max_age_s > 0 are required")
        self.max_skew_s = float(max_skew_s)
        self.max_frames = int(max_frames)
        self.max_age_s = float(max_age_s)
        self._t: dict[str, list[float]] = {RGB_STREAM: [], DEPTH_STREAM: []}
        self._f: dict[str, list[Any]] = {RGB_STREAM: [], DEPTH_STREAM: []}
        self.min_t: float | None = None
        self._newest = -np.inf
        self.dropped = 0   # frames thrown away (stale, too old, over capacity) since reset

    # -- state -------------------------------------------------------------------------------
    def reset(self, min_t: float | _dt.timedelta | None = None) -> None:
        for s in self._t:
            self._t[s].clear()
            self._f[s].clear()
        self.min_t = None if min_t is None else to_seconds(min_t)
        self._newest = -np.inf
        self.dropped = 0

    def sizes(self) -> tuple[int, int]:
        """(number of colour frames, number of depth frames) held."""
        return len(self._t[RGB_STREAM]), len(self._t[DEPTH_STREAM])

    def __len__(self) -> int:
        return sum(self.sizes())

    # -- input ---------------------------------------------------------------------------------
    def push_rgb(self, frame: Any, t: float | _dt.timedelta) -> bool:
        """Add a colour frame stamped ``t``; False when it was ignored as too old."""
        return self._push(RGB_STREAM, frame, to_seconds(t))

    def push_depth(self, frame: Any, t: float | _dt.timedelta) -> bool:
        """Add a depth frame stamped ``t``; False when it was ignored as too old."""
        return self._push(DEPTH_STREAM, frame, to_seconds(t))

    def _push(self, stream: str, frame: Any, t: float) -> bool:
        if self.min_t is not None and t < self.min_t:
            self.dropped += 1
            return False
        if t < self._newest - self.max_age_s:
            self.dropped += 1
            return False
        ts, fs = self._t[stream], self._f[stream]
        i = bisect.bisect_right(ts, t)
        ts.insert(i, t)
        fs.insert(i, frame)
        while len(ts) > self.max_frames:      # keep the last N (by time)
            ts.pop(0)
            fs.pop(0)
            self.dropped += 1
        if t > self._newest:
            self._newest = t
            self._prune_age()
        return True

    def _prune_age(self) -> None:
        horizon = self._newest - self.max_age_s
        for s in self._t:
            n = bisect.bisect_left(self._t[s], horizon)
            if n:
                del self._t[s][:n]
                del self._f[s][:n]
                self.dropped += n

    # -- output --------------------------------------------------------------------------------
    def pop_pair(self) -> FramePair | None:
        """The best pair within ``max_skew_s``, removed with everything older; None if none."""
        tr, td = self._t[RGB_STREAM], self._t[DEPTH_STREAM]
        if not tr or not td:
            return None
        best: tuple[float, float, int, int] | None = None   # (|dt|, t_rgb, i, j)
        for i, t in enumerate(tr):
            k = bisect.bisect_left(td, t)
            for j in (k - 1, k):
                if 0 <= j < len(td):
                    cand = (abs(t - td[j]), t, i, j)
                    if cand[0] <= self.max_skew_s and (best is None or cand[:2] < best[:2]):
                        best = cand
        if best is None:
            return None
        _, _, i, j = best
        pair = FramePair(self._f[RGB_STREAM][i], self._f[DEPTH_STREAM][j], tr[i], td[j])
        self.dropped += i + j
        del tr[: i + 1], self._f[RGB_STREAM][: i + 1]
        del td[: j + 1], self._f[DEPTH_STREAM][: j + 1]
        return pair



__all__ = ["DEVICE", "RGB_STREAM", "DEPTH_STREAM", "to_seconds", "FrameFormatError", "frame_to_rgb", "frame_to_depth",
           "FramePair", "FrameSynchronizer"]
