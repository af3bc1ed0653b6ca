"""Vision with a real lens: frames of a camera with barrel distortion, read back from an MJPEG video file, measured
with the calibration's distortion (vision undistorts the corner points, not the image) give the tag's pose within
1 % of its distance; the same frames measured as if the lens were ideal do not."""
import msgspec
import numpy as np
import pytest

from protocol import messages as m
from services.camera import core as camera_core
from services.camera.calibration import read_intrinsics
from services.camera.sources import VideoFileSource
from services.vision.core import VisionCore
from services.vision.service import VisionConfig
from tests.services.camera.footage import write_footage


@pytest.fixture(scope="module")
def measured(tmp_path_factory):
    footage = write_footage(tmp_path_factory.mktemp("footage"), n=8)
    info = camera_core.camera_info(read_intrinsics(footage.calibration), np.eye(4), m.Header())
    ideal_lens = msgspec.structs.replace(info, distortion=[0.0] * 5)
    source = VideoFileSource(footage.video, loop=False)
    errors = {"calibrated": [], "ideal": []}
    for i, truth in enumerate(footage.truths):
        frame = source.read()
        stamp = 1_000_000_000 + i
        image = camera_core.image_message(camera_core.pixels_for(frame.pixels, m.ImageEncoding.MONO8,
                                                                 footage.intrinsics),
                                          m.ImageEncoding.MONO8, m.Header(stamp_ns=stamp, source_stamp_ns=stamp))
        distance = np.linalg.norm(truth[:3, 3])
        for name, camera_info in (("calibrated", info), ("ideal", ideal_lens)):
            outcome = VisionCore(VisionConfig()).process(image, camera_info, stamp)
            assert outcome.status is m.FeatureStatus.OK, (name, i, outcome.detail)
            t = np.array(outcome.seen.view.pose_in_camera.xyz)
            errors[name].append(np.linalg.norm(t - truth[:3, 3]) / distance)
    return {name: np.array(values) for name, values in errors.items()}


def test_the_pose_is_within_one_percent_of_the_distance_with_the_calibration(measured):
    assert measured["calibrated"].max() < 0.01


def test_without_undistortion_the_same_frames_measure_worse(measured):
    assert measured["ideal"].max() > 3 * measured["calibrated"].max()
