"""The images printed on the simulator's markerless objects: a photograph given by file (``texture: FILE``), or a
procedural print made from a seed (what the project ships: no third party's image, nothing to license).

The procedural print is the kind of surface a person's cup or a cereal box has for a keypoint detector: broad
shading (multi-scale smooth noise), coloured blobs and strokes, and lettering; the same seed gives the same image to
the byte, another seed another print (the experiments' "similar texture" clutter is another seed).
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

#: the smallest texture side accepted (px): a smaller image has too little detail to be told from another
MIN_TEXTURE_SIDE = 64
#: textures are scaled so that their longer side is at most this (px): MuJoCo keeps every texture in the GPU's
#: memory (and llvmpipe's), and a 4000-px photograph on a 16-cm face is far finer than the camera resolves
MAX_TEXTURE_SIDE = 1024

_GLYPHS = list("ABCDEFGHJKMNPQRSTUVWXYZ23456789")


def procedural_texture(seed: int, width: int = 512, height: int = 512) -> np.ndarray:
    """A print (height × width × 3, RGB uint8) made from ``seed``."""
    if not (MIN_TEXTURE_SIDE <= width <= MAX_TEXTURE_SIDE and MIN_TEXTURE_SIDE <= height <= MAX_TEXTURE_SIDE):
        raise ValueError(f"a procedural texture is {MIN_TEXTURE_SIDE}-{MAX_TEXTURE_SIDE} px a side")
    rng = np.random.default_rng(seed)
    shading = np.zeros((height, width), np.float32)
    for scale in (4, 8, 16, 32, 64):
        noise = rng.standard_normal((height // scale + 2, width // scale + 2)).astype(np.float32)
        shading += cv2.resize(noise, (width, height), interpolation=cv2.INTER_CUBIC) * np.sqrt(scale)
    shading = cv2.normalize(shading, None, 50, 205, cv2.NORM_MINMAX)
    tint = rng.uniform(0.6, 1.0, 3)
    image = np.clip(shading[:, :, None] * tint, 0, 255).astype(np.uint8)
    side = min(width, height)
    #: as many marks per area whatever the print's shape (a cup's wall is 2.6 times as wide as it is tall)
    area = width * height / 512.0 ** 2
    for _ in range(int(rng.integers(30, 50) * area)):
        colour = tuple(int(v) for v in rng.integers(0, 256, 3))
        centre = (int(rng.integers(0, width)), int(rng.integers(0, height)))
        axes = (int(rng.integers(side // 100 + 3, side // 12)), int(rng.integers(side // 100 + 3, side // 12)))
        cv2.ellipse(image, centre, axes, float(rng.uniform(0, 180)), 0, 360, colour, -1, cv2.LINE_AA)
    for _ in range(int(rng.integers(8, 16) * area)):
        colour = tuple(int(v) for v in rng.integers(0, 256, 3))
        a = (int(rng.integers(0, width)), int(rng.integers(0, height)))
        b = (int(rng.integers(0, width)), int(rng.integers(0, height)))
        cv2.line(image, a, b, colour, int(rng.integers(2, 6)), cv2.LINE_AA)
    for _ in range(int(rng.integers(6, 12) * area)):
        text = "".join(rng.choice(_GLYPHS, int(rng.integers(2, 5))))
        scale = float(rng.uniform(0.6, 2.0)) * side / 512
        at = (int(rng.integers(0, max(1, width - 60))), int(rng.integers(30, height)))
        cv2.putText(image, text, at, cv2.FONT_HERSHEY_SIMPLEX, scale, tuple(int(v) for v in rng.integers(0, 256, 3)),
                    max(1, int(round(2 * side / 512))), cv2.LINE_AA)
    return image


def load_texture(path: str | Path) -> np.ndarray:
    """A photograph as an RGB uint8 image, its longer side at most :data:`MAX_TEXTURE_SIDE`; ValueError naming the
    file for one that is not an image OpenCV reads, or too small."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"texture {path}: no such file")
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValueError(f"texture {path}: not an image OpenCV can read (PNG, JPEG, ...)")
    height, width = bgr.shape[:2]
    if min(height, width) < MIN_TEXTURE_SIDE:
        raise ValueError(f"texture {path}: {width}×{height} px, at least {MIN_TEXTURE_SIDE} a side")
    scale = MAX_TEXTURE_SIDE / max(height, width)
    if scale < 1.0:
        bgr = cv2.resize(bgr, (int(round(width * scale)), int(round(height * scale))), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(bgr[:, :, ::-1])


def texture_image(path: str | None, seed: int, aspect: float = 1.0) -> np.ndarray:
    """The texture a scene object asks for: ``path``'s image, or the procedural print of ``seed`` whose width over
    height is ``aspect`` (a cup's wall: its circumference over its height)."""
    if path is not None:
        return load_texture(path)
    width, height = 512.0 * aspect, 512.0
    scale = min(1.0, MAX_TEXTURE_SIDE / max(width, height))  # its longer side within the bound, its shape kept
    width, height = (int(min(MAX_TEXTURE_SIDE, max(MIN_TEXTURE_SIDE, round(side * scale)))) for side in (width, height))
    return procedural_texture(seed, width, height)
