"""The phantom's silhouette in a picture taken against a plain backdrop of one colour, and its signed distance.

The key is a colour key that the phantom's shading does not move: the backdrop's colour B is the median of the
picture's border (the phantom must not touch the picture's edge), the phantom's colour direction O the median
direction of the pixels far from B, and the key is the linear function of the (linear-light) colour that is 1 on B
and 0 on every shade of O: ``k(I) = w . I`` with ``w`` along the part of B orthogonal to O, scaled so that
``w . B = 1``. A pixel that is part phantom, part backdrop mixes the two linearly, so ``alpha = 1 - k`` is the
phantom's share of the pixel: the silhouette's edge is where it crosses 1/2, to a fraction of a pixel. This
needs a backdrop whose colour differs from the phantom's in hue (a green or blue cloth behind a pink phantom),
not only in brightness.

The signed distance (pixels, positive outside) is the distance transform of the thresholded silhouette, with the
pixels along its edge set from their alpha (``1/2 - alpha``: a pixel centre half a pixel outside an edge has
alpha 0), so that interpolating it puts the edge where the picture has it. It is kept within a crop around the
silhouette and clipped at ``truncation_px``: what is further out is outside.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from phantom import PhantomError, require_extra

#: Width (px) of the picture's border the backdrop's colour is read from.
BORDER_PX = 8
#: A pixel whose colour is this far from the backdrop's (relative to the backdrop's brightness) is surely the
#: phantom, for learning the phantom's colour.
SURE_DISTANCE = 0.5


#: A pixel whose hue is within this (cosine) of the phantom's is the phantom's, for learning its colour.
PHANTOM_HUE_COS = float(np.cos(np.radians(12.0)))
#: The backdrop's brightness is the key smoothed over this (px, a Gaussian's sigma) of surely backdrop pixels.
BACKDROP_SMOOTHING_PX = 6.0
#: The backdrop's brightness is not taken below this fraction of its border's.
MIN_BACKDROP_LEVEL = 0.2
#: A pixel further than this (relative to the backdrop's brightness) from every mix of the backdrop's colour and
#: the phantom's is something else (a tube, the holder): opaque.
OTHER_DISTANCE = 0.15


def srgb_to_linear(image: np.ndarray) -> np.ndarray:
    """8-bit sRGB to linear light, float32 (a table of the 256 values). Here, not beside the renderer that encodes
    pictures the other way: importing the renderer compiles or loads its numba kernels, which the daemon's own
    process (it keys no picture; its scan worker does) would pay for at every start."""
    codes = np.arange(256) / 255.0
    table = np.where(codes <= 0.04045, codes / 12.92, ((codes + 0.055) / 1.055) ** 2.4).astype(np.float32)
    linear: np.ndarray = table[image]
    return linear


#: The 256 sRGB codes in linear light.
SRGB_TABLE = srgb_to_linear(np.arange(256, dtype=np.uint8))


class SilhouetteError(PhantomError):
    """A picture in which no silhouette can be found against the backdrop."""


@dataclass
class Silhouette:
    """One picture's silhouette: its alpha (the phantom's share of each pixel, 0..1, float32), the signed distance
    (px, + outside, clipped at ``truncation_px``) within the crop ``(x0, y0, width, height)`` (outside the crop:
    + truncation_px), the silhouette's area (px) and whether it touches the picture's edge."""

    signed_distance_px: np.ndarray
    crop: tuple[int, int, int, int]
    truncation_px: float
    area_px: float
    touches_edge: bool
    touches_top: bool = False


def alpha_matte(image: np.ndarray) -> np.ndarray:
    """The phantom's share of each pixel (0..1, float32) of an 8-bit sRGB picture (height, width, 3; RGB) taken
    against a backdrop of one hue (see the module docstring): the key scaled by the backdrop's brightness where
    it is (a cloth lit unevenly, in folds, darker in the picture's corners), and whatever is neither backdrop nor
    phantom (tubes, a holder, a white highlight) opaque. SilhouetteError if the backdrop's border is not one
    colour or nothing in the picture differs from it."""
    with require_extra("scan"):
        import cv2

    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise SilhouetteError(f"a picture must be 8-bit colour (height, width, 3), got {image.dtype} {image.shape}")
    border = np.concatenate([image[:BORDER_PX].reshape(-1, 3), image[-BORDER_PX:].reshape(-1, 3),
                             image[:, :BORDER_PX].reshape(-1, 3), image[:, -BORDER_PX:].reshape(-1, 3)])
    backdrop = np.median(SRGB_TABLE[border], axis=0)
    brightness = float(np.linalg.norm(backdrop))
    if brightness < 0.01:
        raise SilhouetteError("the picture's border is black: light the backdrop (a green or blue cloth)")
    # the phantom's colour from every other pixel of every other row: plenty, and four times fewer
    linear = SRGB_TABLE[image[::2, ::2]]
    distance = np.linalg.norm(linear - backdrop, axis=2) / brightness
    sure = distance > SURE_DISTANCE
    if np.count_nonzero(sure) < 12:
        raise SilhouetteError("nothing in the picture differs from the backdrop: is the phantom in view?")
    colours = linear[sure]
    hues = colours / np.maximum(np.linalg.norm(colours, axis=1, keepdims=True), 1e-6)
    direction = np.median(hues, axis=0)
    direction /= np.linalg.norm(direction)
    # tubes, a holder and highlights differ from the backdrop too: the phantom's hue is the one most of those
    # pixels share, the others dropped
    for _ in range(3):
        alike = hues @ direction > PHANTOM_HUE_COS
        if np.count_nonzero(alike) < 12:
            break
        direction = np.median(hues[alike], axis=0)
        direction /= np.linalg.norm(direction)
    across = backdrop - (backdrop @ direction) * direction
    if np.linalg.norm(across) < 0.05 * brightness:
        raise SilhouetteError("the phantom and the backdrop have the same hue: use a backdrop of another colour "
                              "(green or blue behind the pink silicone)")
    key = (across / float(across @ backdrop)).astype(np.float32)
    full = SRGB_TABLE[image]
    keyed = full @ key  # 1 on the backdrop's colour, 0 on every shade of the phantom's
    # the backdrop's brightness where it is: the key over the pixels surely backdrop (and not next to anything
    # else), smoothed and carried over the phantom from around it
    backdrop_mask = (keyed > 0.5).astype(np.uint8)
    backdrop_mask = cv2.erode(backdrop_mask, np.ones((5, 5), np.uint8))
    weight = cv2.GaussianBlur(backdrop_mask.astype(np.float32), (0, 0), BACKDROP_SMOOTHING_PX)
    level = cv2.GaussianBlur(keyed * backdrop_mask, (0, 0), BACKDROP_SMOOTHING_PX)
    local = np.where(weight > 1e-3, level / np.maximum(weight, 1e-3), 1.0)
    local = np.clip(local, MIN_BACKDROP_LEVEL, None)
    alpha: np.ndarray = np.clip(1.0 - keyed / local, 0.0, 1.0).astype(np.float32)
    # what mixes neither the backdrop's colour nor the phantom's (white tubes, a dark holder) lies off the plane
    # the two span: opaque, for it may hide the phantom behind it
    normal = np.cross(backdrop, direction)
    normal /= np.linalg.norm(normal)
    other = (np.abs(full @ normal.astype(np.float32)) > OTHER_DISTANCE * brightness).astype(np.uint8)
    other = cv2.morphologyEx(other, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))  # not the sensor's noise
    alpha[other == 1] = 1.0
    return alpha


def silhouette(image: np.ndarray, truncation_px: float = 48.0) -> Silhouette:
    """The silhouette of the largest piece of phantom in the picture, holes filled, and its signed distance."""
    return silhouette_of_alpha(alpha_matte(image), truncation_px)


def silhouette_of_alpha(alpha: np.ndarray, truncation_px: float = 48.0) -> Silhouette:
    """The silhouette of the largest piece of an alpha matte (the phantom's share of each pixel, 0..1, float32:
    a picture's, :func:`alpha_matte`, or a known surface's coverage, ``phantom.scan.hull_bias``), holes filled,
    and its signed distance. SilhouetteError when nothing in it is phantom."""
    with require_extra("scan"):
        import cv2

    height, width = alpha.shape
    # the largest piece, found on every fourth pixel, gives the crop the rest works in
    coarse = np.ascontiguousarray(alpha[::4, ::4] >= 0.5).astype(np.uint8)
    count, _, stats, _ = cv2.connectedComponentsWithStats(coarse, connectivity=8)
    if count < 2:
        raise SilhouetteError("no silhouette in the picture: is the phantom in view against the backdrop?")
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    left, top = 4 * stats[largest, cv2.CC_STAT_LEFT], 4 * stats[largest, cv2.CC_STAT_TOP]
    right = 4 * (stats[largest, cv2.CC_STAT_LEFT] + stats[largest, cv2.CC_STAT_WIDTH])
    bottom = 4 * (stats[largest, cv2.CC_STAT_TOP] + stats[largest, cv2.CC_STAT_HEIGHT])
    margin = int(np.ceil(truncation_px)) + 8
    x0, y0 = max(left - margin, 0), max(top - margin, 0)
    x1, y1 = min(right + margin, width), min(bottom + margin, height)
    crop_alpha = alpha[y0:y1, x0:x1]
    mask = (crop_alpha >= 0.5).astype(np.uint8)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    mask = (labels == largest).astype(np.uint8)
    # holes (a highlight the key took for backdrop) are filled: the backdrop pieces that do not reach the crop's
    # edge
    count, labels, stats, _ = cv2.connectedComponentsWithStats(1 - mask, connectivity=4)
    x, y, w, h = (stats[:, k] for k in (cv2.CC_STAT_LEFT, cv2.CC_STAT_TOP, cv2.CC_STAT_WIDTH, cv2.CC_STAT_HEIGHT))
    enclosed = (x > 0) & (y > 0) & (x + w < mask.shape[1]) & (y + h < mask.shape[0])
    enclosed[0] = False  # label 0 is the silhouette itself
    if np.any(enclosed):
        mask[np.isin(labels, np.flatnonzero(enclosed))] = 1
    crop_alpha = np.where(mask == 1, np.maximum(crop_alpha, 0.5), np.minimum(crop_alpha, 0.4999))
    outside = cv2.distanceTransform(1 - mask, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    inside = cv2.distanceTransform(mask, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    signed = np.where(mask == 1, 0.5 - inside, outside - 0.5)
    # along the edge, the alpha places it within the pixel
    edge = np.where(mask == 1, inside <= 1.0, outside <= 1.0)
    signed = np.where(edge, 0.5 - crop_alpha, signed)
    signed = np.clip(signed, -truncation_px, truncation_px).astype(np.float32)
    bx, by, bw, bh = cv2.boundingRect(mask)
    touches = bool(x0 + bx == 0 or y0 + by == 0 or x0 + bx + bw == width or y0 + by + bh == height)
    return Silhouette(np.ascontiguousarray(signed), (x0, y0, x1 - x0, y1 - y0), float(truncation_px),
                      float(crop_alpha[mask == 1].sum()), touches, bool(y0 + by == 0))
