"""Where to search: windows of the image (or of its rectified view) around where the previous
frame's markers were and where the target's plane puts the others, so that tracking passes
look at a part of the frame, not all of it."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from perchpose.detection.rectification import Rectification
from perchpose.numeric.linalg import homography_of_4, through_homography
from perchpose.target import TargetSpec
from perchpose.values import MarkerDetection

Array = NDArray[np.float64]
Box = tuple[int, int, int, int]  # x0, y0, x1, y1 (x1, y1 exclusive)


def _plane_homography(target: TargetSpec, index: int, corners_px: Array) -> Array | None:
    """The homography taking the target's plane (m) to the image (or view) where marker
    ``index`` has ``corners_px`` (4, 2); None where the corners make none."""
    plane = np.ascontiguousarray(target.markers[index].corners_target_m[:, :2])
    found, H = homography_of_4(plane, np.ascontiguousarray(corners_px, np.float64))
    return H if found else None


def _plane_quad(target: TargetSpec, index: int, H: Array) -> Array:
    """Marker ``index``'s corners under the homography ``H`` from the target's plane (m)."""
    return through_homography(H, target.markers[index].corners_target_m[:, :2])


def predicted_quads(target: TargetSpec, hint: tuple[MarkerDetection, ...]) -> dict[int, Array]:
    """Where each marker should be: the hinted markers where they were, the others where
    the plane through the largest hinted marker puts them."""
    quads = {d.marker_index: d.corners_px for d in hint}
    reference = max(hint, key=lambda d: d.side_px)
    H = _plane_homography(target, reference.marker_index, reference.corners_px)
    if H is not None:
        for index in range(len(target.markers)):
            if index not in quads:
                quads[index] = _plane_quad(target, index, H)
    return {i: q for i, q in quads.items() if np.isfinite(q).all()}


def extrapolated(
    hint: tuple[MarkerDetection, ...],
    hint_t_s: float,
    earlier: tuple[MarkerDetection, ...],
    earlier_t_s: float,
    t_s: float,
    max_ratio: float = 2.0,
) -> tuple[MarkerDetection, ...]:
    """``hint`` (a frame's detections at ``hint_t_s``) carried on to ``t_s``: each corner at
    the velocity it had from ``earlier`` (the detections at ``earlier_t_s``). A marker not in
    both stays where it was, and so does every marker when the step ahead is over
    ``max_ratio`` times the step between the two frames (a gap: the motion then is unknown)."""
    step_s = hint_t_s - earlier_t_s
    if not hint or not earlier or not step_s > 0 or not 0 <= t_s - hint_t_s <= max_ratio * step_s:
        return hint
    ratio = (t_s - hint_t_s) / step_s
    before = {d.marker_index: d.corners_px for d in earlier}
    out = []
    for d in hint:
        last = before.get(d.marker_index)
        if last is None:
            out.append(d)
            continue
        corners = d.corners_px + ratio * (d.corners_px - last)
        out.append(MarkerDetection(d.marker_index, corners, d.image_pass))
    return tuple(out)


def padded_box(
    quads: list[Array], shape: tuple[int, ...], pad_fraction: float, pad_px: float
) -> Box | None:
    """The box around ``quads`` padded by a fraction of their extent plus ``pad_px``, clipped
    to ``shape``; None if under 16 px either way."""
    h, w = shape[:2]
    points = np.concatenate(quads)
    lo, hi = points.min(axis=0), points.max(axis=0)
    pad = pad_fraction * float(np.max(hi - lo)) + pad_px
    x0, y0 = int(max(0, np.floor(lo[0] - pad))), int(max(0, np.floor(lo[1] - pad)))
    x1, y1 = int(min(w, np.ceil(hi[0] + pad))), int(min(h, np.ceil(hi[1] + pad)))
    if x1 - x0 < 16 or y1 - y0 < 16:
        return None
    return (x0, y0, x1, y1)


def tracking_window(shape: tuple[int, ...], quads: dict[int, Array]) -> Box | None:
    """A window of the image around the predicted ``quads`` (``predicted_quads``), or None
    when it would cover most of the image anyway."""
    if not quads:
        return None
    box = padded_box(list(quads.values()), shape, 0.5, 16.0)
    h, w = shape[:2]
    if box is None or (box[2] - box[0]) * (box[3] - box[1]) > 0.6 * w * h:
        return None
    return box


def rectified_box(quad: Array, shape: tuple[int, ...]) -> Box | None:
    """A window of the rectified view around ``quad`` (rectified pixels), padded by 0.3 of its
    extent plus 8 px, or None if not finite or under 16 px."""
    if not np.isfinite(quad).all():
        return None
    h, w = shape[:2]
    lo, hi = quad.min(axis=0), quad.max(axis=0)
    pad = 0.3 * float(np.max(hi - lo)) + 8.0
    x0, y0 = (int(max(0, np.floor(v - pad))) for v in lo)
    x1 = int(min(w, np.ceil(hi[0] + pad)))
    y1 = int(min(h, np.ceil(hi[1] + pad)))
    return (x0, y0, x1, y1) if x1 - x0 >= 16 and y1 - y0 >= 16 else None


def rectified_windows(
    rectification: Rectification,
    target: TargetSpec,
    found: dict[int, MarkerDetection],
    curved_side_px: float,
    border_margin_px: float = 0.0,
) -> list[Box]:
    """Windows of the rectified view to search: around each found marker of
    ``curved_side_px`` or more (its edges curved in the original), and around where the plane
    through the largest found marker puts each missing one, where that lies wholly in the
    original image, ``border_margin_px`` from its border (a marker across the border, leaving
    the view near contact, is no quad that maps back into the image: its window would be most
    of the view, searched for nothing)."""
    reference = max(found.values(), key=lambda d: d.side_px)
    ref_rect = rectification.to_rectified(reference.corners_px)
    H = _plane_homography(target, reference.marker_index, ref_rect)
    windows = []
    for index in range(len(target.markers)):
        det = found.get(index)
        if det is not None and det.side_px < curved_side_px:
            continue
        if det is not None:
            quad = rectification.to_rectified(det.corners_px)
        elif H is not None:
            quad = _plane_quad(target, index, H)
            uv, ok = rectification.to_original(quad)
            if not ok or not rectification.camera.in_image(uv, border_margin_px):
                continue
        else:
            continue
        window = rectified_box(quad, rectification.size)
        if window is not None:
            windows.append(window)
    return windows
