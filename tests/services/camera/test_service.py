"""The camera service over a real zenoh router: a real video file and an image folder played on the camera keys,
vision measuring the tag in them with the calibration's intrinsics and distortion; frames the calibration does not
describe refused; a source that ends says so."""
import time

import cv2
import numpy as np
import pytest

from protocol import messages as m
from protocol.keys import Keys
from services.camera.service import CameraConfig, CameraService, SourceConfig
from services.runtime.transport import open_session
from services.vision.service import VisionConfig, VisionService
from tests.services.camera.footage import write_footage
from tests.stack import Recorder, wait_for

KEYS = Keys()


@pytest.fixture(scope="module")
def footage(tmp_path_factory):
    return write_footage(tmp_path_factory.mktemp("footage"), n=12)


def camera(router, footage, **source):
    return CameraService(CameraConfig(zenoh=router.client_config(), calibration=str(footage.calibration),
                                      source=SourceConfig(**source), camera_info_period_s=0.2))


@pytest.mark.parametrize("kind", ["video", "images"])
def test_vision_measures_the_tag_in_what_the_camera_service_plays(router, footage, kind):
    client = open_session(router.client_config())
    images = Recorder(client, KEYS.camera_image, m.Image)
    features = Recorder(client, KEYS.features, m.Features)
    vision = VisionService(VisionConfig(zenoh=router.client_config()))
    service = camera(router, footage, kind=kind, path=str(footage.video if kind == "video" else footage.images),
                     rate_hz=15.0)
    vision.start()
    service.start()
    try:
        ok = lambda: sum(f.status is m.FeatureStatus.OK for f in features.snapshot()) >= 12
        assert wait_for(ok, timeout=30.0), [f.detail for f in features.snapshot()[-3:]]
        info = [m.decode(r.ok.payload.to_bytes(), m.CameraInfo) for r in client.get(KEYS.camera_info, timeout=5.0)
                if r.ok is not None]
    finally:
        service.stop()
        vision.stop()
        client.close()
    assert info and info[0].distortion == pytest.approx(list(footage.intrinsics.distortion))
    stamps = [image.header.source_stamp_ns for image in images.snapshot()]
    assert stamps == sorted(set(stamps)) and all(image.header.trace[0].service == "camera"
                                                 for image in images.snapshot())
    rate = (len(stamps) - 1) / ((stamps[-1] - stamps[0]) * 1e-9)
    assert 5.0 < rate < 20.0  # 15 Hz asked; generous: a shared host
    seen = [f for f in features.snapshot() if f.status is m.FeatureStatus.OK]
    assert {f.header.source_stamp_ns for f in seen} <= set(stamps)
    for f in seen:  # each measured pose is one of the footage's (which frame is which is not known here)
        t = np.array(f.tag.pose_in_camera.xyz)
        assert min(np.linalg.norm(t - truth[:3, 3]) / np.linalg.norm(truth[:3, 3])
                   for truth in footage.truths) < 0.01


def test_frames_the_calibration_does_not_describe_are_refused_and_an_ended_source_says_so(router, footage, tmp_path):
    for i, path in enumerate(sorted(footage.images.iterdir())[:3]):
        grey = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(tmp_path / f"{i}.png"), grey if i != 1 else cv2.resize(grey, (320, 240)))
    client = open_session(router.client_config())
    images = Recorder(client, KEYS.camera_image, m.Image)
    service = camera(router, footage, kind="images", path=str(tmp_path), rate_hz=30.0, loop=False)
    service.start()
    try:
        assert wait_for(lambda: service.check_health()[0] is False, timeout=10.0)
        time.sleep(0.3)
        assert "ended" in service.check_health()[1]
        assert service.counters.get("rejected.frame") == 1
        assert len(images) == 2 and all((i.width, i.height) == (640, 480) for i in images.snapshot())
    finally:
        service.stop()
        client.close()


def test_lockstep_and_a_missing_calibration_are_refused_before_the_network(footage):
    with pytest.raises(ValueError, match="realtime only"):
        CameraConfig(clock="lockstep")
    with pytest.raises(ValueError, match="calibration file"):
        CameraService(CameraConfig(source=SourceConfig(kind="video", path=str(footage.video))))
    with pytest.raises(OSError, match="no video file"):
        CameraService(CameraConfig(calibration=str(footage.calibration),
                                   source=SourceConfig(kind="video", path="/nonexistent.avi")))
