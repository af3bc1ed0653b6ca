"""Where the camera service's frames come from: a camera through OpenCV (a V4L2/UVC device), a video file, or a
folder of images. Each source hands out frames with the time they were captured; no zenoh, no threads.

Capture stamps, as close to exposure as the source allows:

* a device: V4L2 stamps each buffer when the driver has it (``CAP_PROP_POS_MSEC``, the monotonic clock), which is
  after exposure by the sensor's readout; that stamp, mapped to wall time, minus ``capture_latency_s`` (what the lab
  measured for its camera, 0 by default). Where the backend gives no usable buffer stamp, the time ``grab()``
  returned is taken instead (later by the driver's and OpenCV's handling), and :attr:`DeviceSource.stamp_source`
  says which;
* a file or a folder: the time the frame is handed out, paced by the service at the playback rate.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional, Protocol

import cv2
import numpy as np

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")
#: a V4L2 buffer stamp further than this from the monotonic clock now is not a capture stamp (a file position, 0)
_PLAUSIBLE_BUFFER_AGE_S = 1.0


class SourceError(OSError):
    """A source that cannot be opened or has failed (an I/O error: the service's start reports it as such)."""


@dataclass
class Frame:
    """One frame: its pixels (H×W grey or H×W×3 BGR, as OpenCV reads them) and when it was captured (wall ns)."""

    pixels: np.ndarray
    capture_ns: int
    #: where it came from (a file's name, a device frame's index): for logs
    label: str = ""


class FrameSource(Protocol):
    #: whether the service paces this source (files) or the source paces itself (a camera)
    paced: bool
    #: the source's own frame rate when it has one (a video file's), else None
    native_rate_hz: Optional[float]

    def read(self) -> Optional[Frame]:
        """The next frame, or None at the end of a file or folder that does not loop. Raises SourceError."""

    def close(self) -> None: ...


def _mono_to_wall_ns() -> int:
    """Wall time minus monotonic time now (ns): adds to a monotonic stamp to give wall time."""
    return time.time_ns() - time.monotonic_ns()


class DeviceSource:
    """A camera through OpenCV's V4L2 backend (``device``: an index, or a path such as /dev/video0)."""

    paced = False
    native_rate_hz = None

    def __init__(self, device: int | str, width: int, height: int, rate_hz: Optional[float],
                 exposure: Optional[float] = None, capture_latency_s: float = 0.0,
                 open_capture: Callable[..., cv2.VideoCapture] = cv2.VideoCapture) -> None:
        backend = cv2.CAP_V4L2 if hasattr(cv2, "CAP_V4L2") else cv2.CAP_ANY
        self._capture = open_capture(device, backend)
        if not self._capture.isOpened():
            raise SourceError(f"cannot open camera {device!r} (is it plugged in, and is this user in group video?)")
        cap = self._capture
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # the newest frame, not one queued for several periods
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, width)
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
        if rate_hz:
            cap.set(cv2.CAP_PROP_FPS, rate_hz)
        if exposure is not None:
            cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1)  # V4L2: 1 is manual, 3 aperture-priority auto
            if not cap.set(cv2.CAP_PROP_EXPOSURE, exposure):
                raise SourceError(f"camera {device!r} does not take a manual exposure of {exposure}")
        actual = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        if actual != (width, height):
            cap.release()
            raise SourceError(f"camera {device!r} gives {actual[0]}x{actual[1]}, not the {width}x{height} asked for "
                              "(and calibrated for)")
        self.device = device
        self.capture_latency_ns = int(capture_latency_s * 1e9)
        #: "buffer" (the driver's stamp of each frame) or "grab" (when OpenCV returned it)
        self.stamp_source = "buffer"
        self._index = 0

    def read(self) -> Optional[Frame]:
        if not self._capture.grab():
            raise SourceError(f"camera {self.device!r} gave no frame")
        grabbed_ns = time.time_ns()
        buffer_ms = self._capture.get(cv2.CAP_PROP_POS_MSEC)
        offset = _mono_to_wall_ns()
        stamp = grabbed_ns
        if math.isfinite(buffer_ms) and buffer_ms > 0:
            candidate = int(buffer_ms * 1e6) + offset
            if abs(grabbed_ns - candidate) < _PLAUSIBLE_BUFFER_AGE_S * 1e9:
                stamp = min(candidate, grabbed_ns)
                self.stamp_source = "buffer"
            else:
                self.stamp_source = "grab"
        else:
            self.stamp_source = "grab"
        ok, pixels = self._capture.retrieve()
        if not ok or pixels is None:
            raise SourceError(f"camera {self.device!r}: a frame was grabbed but could not be decoded")
        self._index += 1
        return Frame(pixels, stamp - self.capture_latency_ns, f"frame {self._index}")

    def close(self) -> None:
        self._capture.release()


class VideoFileSource:
    """A video file, frame by frame, from the start again at its end when ``loop``."""

    paced = True

    def __init__(self, path: str | Path, loop: bool = True) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise SourceError(f"no video file {self.path}")
        self._capture = cv2.VideoCapture(str(self.path))
        if not self._capture.isOpened():
            raise SourceError(f"OpenCV cannot open {self.path} as a video")
        fps = self._capture.get(cv2.CAP_PROP_FPS)
        self.native_rate_hz = fps if math.isfinite(fps) and 0 < fps <= 1000 else None
        self.loop = loop
        self._index = 0

    def read(self) -> Optional[Frame]:
        ok, pixels = self._capture.read()
        if not ok and self.loop and self._index > 0:
            self._capture.set(cv2.CAP_PROP_POS_FRAMES, 0)
            self._index = 0
            ok, pixels = self._capture.read()
        if not ok:
            if self._index == 0:
                raise SourceError(f"{self.path} holds no frame OpenCV can decode")
            return None
        self._index += 1
        return Frame(pixels, time.time_ns(), f"{self.path.name} frame {self._index}")

    def close(self) -> None:
        self._capture.release()


class ImageFolderSource:
    """The images of a folder (``IMAGE_SUFFIXES``) in name order, again from the first at the end when ``loop``."""

    paced = True
    native_rate_hz = None

    def __init__(self, path: str | Path, loop: bool = True) -> None:
        self.path = Path(path)
        if not self.path.is_dir():
            raise SourceError(f"no image folder {self.path}")
        self.files = sorted(p for p in self.path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not self.files:
            raise SourceError(f"{self.path} holds no image ({', '.join(IMAGE_SUFFIXES)})")
        self.loop = loop
        self._next = 0

    def read(self) -> Optional[Frame]:
        if self._next >= len(self.files):
            if not self.loop:
                return None
            self._next = 0
        file = self.files[self._next]
        self._next += 1
        pixels = cv2.imread(str(file), cv2.IMREAD_UNCHANGED)
        if pixels is None:
            raise SourceError(f"{file} is not an image OpenCV can read")
        if pixels.dtype != np.uint8:
            raise SourceError(f"{file} has {pixels.dtype} pixels; 8-bit images only")
        if pixels.ndim == 3 and pixels.shape[2] == 4:
            pixels = cv2.cvtColor(pixels, cv2.COLOR_BGRA2BGR)
        return Frame(pixels, time.time_ns(), file.name)

    def close(self) -> None:
        pass
