"""The tag as printed: the official tag36h11 images (AprilRobotics/apriltag-imgs) against OpenCV's drawing of the
same codes, the simulator's texture and the corner order vision gives for a printed official tag."""
from pathlib import Path

import cv2
import numpy as np
import pytest

from services.model import tag as tags
from services.vision.features import TagDetector

DATA = Path(__file__).parent / "data"


def official_png(tag_id: int) -> np.ndarray:
    return cv2.imread(str(DATA / f"tag36_11_{tag_id:05d}.png"), cv2.IMREAD_GRAYSCALE)


@pytest.mark.parametrize("tag_id", [0, 7])
def test_the_official_layout_is_the_official_image(tag_id):
    """tag_image(layout=official), cell by cell, is the official PNG (10×10 cells: quiet zone, border, data)."""
    cells = tags.tag_image(tag_id, px_per_cell=1, layout="official")
    assert np.array_equal(cells, official_png(tag_id))
    opencv = tags.tag_image(tag_id, px_per_cell=1, layout="opencv")
    assert np.array_equal(np.rot90(opencv, tags.opencv_turns()), cells)


def printed(image_cells: np.ndarray, corners_px: np.ndarray, size=(480, 640), px_per_cell: int = 40) -> np.ndarray:
    """A photograph of a print of ``image_cells`` whose black square's corners (top-left, top-right, bottom-right,
    bottom-left of the image) land at ``corners_px``: the image scaled up, warped, on a grey background."""
    big = cv2.resize(image_cells, None, fx=px_per_cell, fy=px_per_cell, interpolation=cv2.INTER_NEAREST)
    # cell edges, in OpenCV's pixel coordinates (a pixel's centre is its index)
    a, b = px_per_cell * tags.QUIET_CELLS - 0.5, px_per_cell * (tags.QUIET_CELLS + tags.BLACK_CELLS) - 0.5
    source = np.float32([[a, a], [b, a], [b, b], [a, b]])
    H = cv2.getPerspectiveTransform(source, np.float32(corners_px))
    return cv2.warpPerspective(big, H, (size[1], size[0]), flags=cv2.INTER_LINEAR, borderValue=128)


@pytest.mark.parametrize("backend", ["aruco", "apriltag"])
@pytest.mark.parametrize("turn", [0, 1, 2, 3])
def test_a_printed_official_tag_gives_the_official_corners_in_order(turn, backend):
    """Whatever way up the print is held, vision (layout official) names its corners as the official image does:
    corner i of the detection is where the official image's corner i (top-left, top-right, bottom-right,
    bottom-left) was printed, within 0.5 px; told the print is OpenCV's drawing instead, it is off by the turn
    between the two (by two corners in OpenCV 4.x-5.0: the 180° the real-arm issue found)."""
    square = np.array([[250.0, 150.0], [390.0, 160.0], [385.0, 300.0], [245.0, 290.0]])
    corners = np.roll(square, turn, axis=0)  # the print turned by quarter turns in the image
    image = printed(official_png(0), corners)
    found = TagDetector(layout="official", backend=backend).find(image, 0)
    assert found is not None
    assert np.abs(found.corners_px - corners).max() < 0.5
    as_opencv = TagDetector(layout="opencv", backend=backend).find(image, 0).corners_px
    assert np.allclose(np.roll(as_opencv, -tags.opencv_turns(), axis=0), found.corners_px)


def test_the_tags_pose_follows_the_official_image():
    """IPPE on the official order gives the official tag frame: x toward the official image's right."""
    from services.vision.features import camera_matrix, tag_pose

    K = camera_matrix(615.0, 615.0, 319.5, 239.5)
    square = np.array([[250.0, 150.0], [390.0, 150.0], [390.0, 290.0], [250.0, 290.0]])
    found = TagDetector(layout="official").find(printed(official_png(0), square), 0)
    R, _ = tag_pose(found.corners_px, K, None, 0.1)
    assert R[0, 0] > 0.99  # the tag's x along the camera's x: upright, not turned by 180°
