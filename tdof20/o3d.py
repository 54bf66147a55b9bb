"""Import open3d with its libusb need met without root.

open3d 0.20 links ``libusb-1.0.so.0``. Where the system lacks it, the ``libusb-package`` wheel
ships the library; loading it with RTLD_GLOBAL before open3d is imported satisfies the link.
Every module of tdof20 imports open3d through here: ``from tdof20.o3d import o3d``.
"""

from __future__ import annotations

import ctypes
import ctypes.util


def _preload_libusb() -> None:
    if ctypes.util.find_library("usb-1.0"):
        return
    try:
        import libusb_package
    except ImportError:  # pragma: no cover - declared dependency
        return
    path = libusb_package.get_library_path()
    if path is not None:
        ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL)


_preload_libusb()

import open3d as o3d  # noqa: E402

o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)

__all__ = ["o3d"]
