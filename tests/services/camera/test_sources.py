"""The camera service's sources: an image folder and a real video file (MJPEG, written by OpenCV), in order, looping
or ending; a V4L2 device's capture stamps (no camera here: OpenCV's capture object is replaced by one that answers
as the V4L2 backend does)."""
import time

import cv2
import numpy as np
import pytest

from services.camera.sources import DeviceSource, ImageFolderSource, SourceError, VideoFileSource


def numbered(i: int) -> np.ndarray:
    frame = np.zeros((48, 64), np.uint8)
    frame[:, : 8 * (i + 1)] = 200  # a bar as long as the frame's number: survives JPEG compression
    return frame


def number_of(frame: np.ndarray) -> int:
    grey = frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    return int(round((grey[24] > 100).sum() / 8)) - 1


@pytest.fixture
def folder(tmp_path):
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"img_{i:02d}.png"), numbered(i))
    (tmp_path / "notes.txt").write_text("not an image")
    return tmp_path


def test_a_folder_is_read_in_name_order_and_loops(folder):
    source = ImageFolderSource(folder, loop=True)
    assert [number_of(source.read().pixels) for _ in range(5)] == [0, 1, 2, 0, 1]


def test_a_folder_that_does_not_loop_ends(folder):
    source = ImageFolderSource(folder, loop=False)
    assert [number_of(source.read().pixels) for _ in range(3)] == [0, 1, 2]
    assert source.read() is None


def test_a_file_that_is_no_image_is_an_error_for_its_frame_only(folder):
    (folder / "img_01.png").write_bytes(b"not a png")
    source = ImageFolderSource(folder, loop=False)
    assert number_of(source.read().pixels) == 0
    with pytest.raises(SourceError, match="img_01.png"):
        source.read()
    assert number_of(source.read().pixels) == 2


def test_an_empty_or_missing_folder_is_refused(tmp_path):
    with pytest.raises(SourceError, match="no image"):
        ImageFolderSource(tmp_path)
    with pytest.raises(SourceError, match="no image folder"):
        ImageFolderSource(tmp_path / "missing")


@pytest.fixture
def video(tmp_path):
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (64, 48), isColor=True)
    assert writer.isOpened()
    for i in range(4):
        writer.write(cv2.cvtColor(numbered(i), cv2.COLOR_GRAY2BGR))
    writer.release()
    return path


def test_a_video_file_plays_in_order_at_its_own_rate_and_loops(video):
    source = VideoFileSource(video, loop=True)
    assert source.native_rate_hz == pytest.approx(25.0)
    before = time.time_ns()
    read = [source.read() for _ in range(6)]
    assert [number_of(f.pixels) for f in read] == [0, 1, 2, 3, 0, 1]
    assert all(f.capture_ns >= before for f in read)
    source.close()


def test_a_video_that_does_not_loop_ends_and_garbage_is_refused(video, tmp_path):
    source = VideoFileSource(video, loop=False)
    assert [number_of(source.read().pixels) for _ in range(4)] == [0, 1, 2, 3]
    assert source.read() is None
    garbage = tmp_path / "garbage.avi"
    garbage.write_bytes(b"\x00" * 1000)
    with pytest.raises(SourceError):
        VideoFileSource(garbage).read()
    with pytest.raises(SourceError, match="no video file"):
        VideoFileSource(tmp_path / "missing.avi")


class V4L2Capture:
    """Answers as OpenCV's V4L2 backend does: the size it was set to (or its own), and each buffer's stamp in
    milliseconds of the monotonic clock (``buffer_age_s`` before the grab)."""

    def __init__(self, device, backend, native=(640, 480), buffer_age_s=0.012, opened=True):
        self.props = {cv2.CAP_PROP_FRAME_WIDTH: native[0], cv2.CAP_PROP_FRAME_HEIGHT: native[1]}
        self.native, self.buffer_age_s, self.opened = native, buffer_age_s, opened
        self.buffer_ms = 0.0

    def isOpened(self):
        return self.opened

    def set(self, prop, value):
        if prop in (cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT):
            return True  # a camera that does not have the size keeps its own
        self.props[prop] = value
        return True

    def get(self, prop):
        if prop == cv2.CAP_PROP_POS_MSEC:
            return self.buffer_ms
        return self.props.get(prop, 0.0)

    def grab(self):
        self.buffer_ms = (time.monotonic_ns() * 1e-6 - self.buffer_age_s * 1e3) if self.buffer_age_s is not None \
            else 0.0
        return True

    def retrieve(self):
        return True, np.zeros((self.native[1], self.native[0], 3), np.uint8)

    def release(self):
        pass


def test_a_device_frame_is_stamped_when_the_driver_had_it_less_the_measured_latency():
    source = DeviceSource(0, 640, 480, 30.0, capture_latency_s=0.005,
                          open_capture=lambda d, b: V4L2Capture(d, b, buffer_age_s=0.012))
    before = time.time_ns()
    frame = source.read()
    assert source.stamp_source == "buffer"
    assert before - 30e6 < frame.capture_ns < before - 12e6  # 12 ms in the driver and 5 ms of readout before it


def test_a_device_without_buffer_stamps_is_stamped_at_the_grab():
    source = DeviceSource(0, 640, 480, 30.0, open_capture=lambda d, b: V4L2Capture(d, b, buffer_age_s=None))
    before = time.time_ns()
    frame = source.read()
    assert source.stamp_source == "grab" and before <= frame.capture_ns <= time.time_ns()


def test_a_device_that_cannot_give_the_calibrated_size_or_open_is_refused():
    with pytest.raises(SourceError, match="1280x720"):
        DeviceSource(0, 640, 480, 30.0, open_capture=lambda d, b: V4L2Capture(d, b, native=(1280, 720)))
    with pytest.raises(SourceError, match="cannot open camera"):
        DeviceSource("/dev/video99", 640, 480, 30.0)
