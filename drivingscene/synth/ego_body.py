"""The ego car's own body at the bottom of the images, as real rigs see it (DDAD: five of six cameras
see the hood, a body panel or the rear deck, with the street reflected in the paint).

Drawn in image space over the rendered world: a smooth curved region per camera (hood for front
cameras, rear deck for back cameras, a panel rising from the lower corner toward the car for the
others, a low sill for cameras looking straight sideways), identical in every frame of that camera
(it is rigid on the ego), painted with the car's colour, a vertical gradient, a specular band and a
dimmed, blurred, vertically flipped reflection of the image above it (which follows each frame).
The pair's ``valid_mask`` is False under the body, dilated by 1 px (2 px from 256 rows); the
ground truth under it stays the world's, and losses and metrics leave masked pixels out.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

PAINTS = np.array(  # display RGB of the ego car (the same car in every camera)
    [
        [0.50, 0.05, 0.04],  # red, like DDAD's
        [0.05, 0.05, 0.06],  # black
        [0.82, 0.82, 0.80],  # white
        [0.55, 0.56, 0.58],  # silver
        [0.10, 0.16, 0.36],  # dark blue
        [0.22, 0.23, 0.24],  # graphite
        [0.30, 0.05, 0.06],  # dark red
    ]
)


@dataclass(frozen=True, eq=False)
class EgoBody:
    """Per camera: where the body is, and how its paint looks."""

    alpha: np.ndarray  # [V, H, W] float32 in [0, 1]: share of each pixel covered by the body
    boundary: np.ndarray  # [V, W] float32 row (pixels, pixel centres at integers) where the body starts
    paint: np.ndarray  # [3] display RGB
    reflectance: np.ndarray  # [V] strength of the mirrored street
    squash: np.ndarray  # [V] vertical scale of the mirror image
    band: np.ndarray  # [V, 3] specular band: offset below the boundary and width (fractions of H), strength

    def valid_mask(self) -> np.ndarray:
        """``[V, H, W]`` bool: False on the body and a 1 px ring (2 px from 256 rows) around it."""
        radius = 1 if self.alpha.shape[1] < 256 else 2
        kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
        covered = [cv2.dilate((a > 1e-3).astype(np.uint8), kernel) for a in self.alpha]
        return ~np.stack(covered).astype(bool)


def _dome(u: np.ndarray, centre: float, half_width: float, power: float) -> np.ndarray:
    return np.maximum(0.0, 1.0 - np.abs((u - centre) / half_width) ** power)


def _profile(rng: np.random.Generator, yaw_deg: float, u: np.ndarray) -> np.ndarray:
    """Body height above the image bottom per column ``[W]`` (fractions of H) for a camera at ``yaw``."""
    yaw = np.radians(yaw_deg)
    front, back = abs(yaw_deg) <= 35.0, abs(yaw_deg) >= 145.0
    if front or back:  # hood or rear deck: a dome across the bottom
        shape = _dome(u, 0.5 + rng.uniform(-0.12, 0.12), rng.uniform(0.45, 1.2), rng.uniform(1.6, 3.5))
        coverage = rng.uniform(0.03, 0.2) if front else rng.uniform(0.05, 0.28)
        return shape * min(coverage / max(shape.mean(), 1e-3), 0.5)
    if abs(np.cos(yaw)) < 0.26:  # straight sideways: a low sill, slightly tilted
        tilt = rng.uniform(-0.6, 0.6)
        return rng.uniform(0.03, 0.12) * (1.0 + tilt * (u - 0.5))
    # the car's flank toward the front (front-side cameras) or the back appears on this side
    right = np.sin(2 * yaw) > 0
    x = u if right else 1.0 - u
    start = rng.uniform(0.0, 0.55)
    shape = np.clip((x - start) / (1.0 - start), 0.0, 1.0) ** rng.uniform(1.2, 2.6)
    lip = rng.uniform(0.0, 0.035)
    coverage = rng.uniform(0.04, 0.3)
    tallest = 0.9 if rng.uniform() < 0.2 else 0.6  # sometimes up to a mirror or pillar at the top
    return lip + shape * np.clip((coverage - lip) / max(shape.mean(), 1e-3), 0.0, tallest)


def sample_ego_body(rng: np.random.Generator, probability: float, yaws: np.ndarray, height: int, width: int) -> EgoBody | None:
    """Bodies of a rig whose cameras look along ``yaws`` [V] degrees; each camera has one with
    ``probability``. None if no camera has one. Every draw is made for every camera, so the stream
    does not depend on which cameras got a body."""
    views = len(yaws)
    u = (np.arange(width) + 0.5) / width
    paint = PAINTS[rng.integers(len(PAINTS))] * rng.uniform(0.85, 1.1, 3)
    has = rng.uniform(size=views) < probability
    profiles = np.stack([_profile(rng, float(y), u) for y in yaws])
    reflectance = (rng.uniform(0.1, 0.3, views) + 0.3 * (1.0 - paint.mean())) * (1.0 - 0.5 * paint.mean())
    squash = rng.uniform(0.35, 0.9, views)
    strength = rng.uniform(0.15, 0.5, views) * (1.0 - 0.6 * paint.mean())  # a highlight shows less on light paint
    band = np.stack([rng.uniform(0.005, 0.05, views), rng.uniform(0.006, 0.02, views), strength], -1)
    if not has.any():
        return None
    profiles = np.where(has[:, None], profiles, 0.0)
    boundary = (1.0 - profiles) * height - 0.5  # row of the edge, in pixel-centre coordinates
    slope = np.gradient(boundary, axis=1)
    rows = np.arange(height, dtype=np.float64)[None, :, None]
    distance = (rows - boundary[:, None, :]) / np.sqrt(1.0 + slope[:, None, :] ** 2)  # signed, pixels
    alpha = np.clip(0.5 + distance, 0.0, 1.0) * (profiles[:, None, :] > 0)
    return EgoBody(alpha.astype(np.float32), boundary.astype(np.float32), np.clip(paint, 0, 1), reflectance, squash, band)


def _paint_layer(body: EgoBody, v: int, image: np.ndarray) -> np.ndarray:
    """``[H, W, 3]`` the body's colour in camera v over the world ``image`` of one frame."""
    height, width = image.shape[:2]
    rows = np.arange(height, dtype=np.float32)[:, None]
    edge = body.boundary[v][None, :]
    below = np.maximum(rows - edge, 0.0)  # pixels into the body
    mirror_y = (edge - below * body.squash[v]).astype(np.float32)
    mirror_x = np.broadcast_to(np.arange(width, dtype=np.float32)[None, :], mirror_y.shape)
    mirrored = cv2.remap(image, np.ascontiguousarray(mirror_x), mirror_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    mirrored = cv2.GaussianBlur(mirrored, (0, 0), max(0.7, 0.02 * height))
    depth = np.clip(below / (0.3 * height), 0.0, 1.0)[..., None]  # 0 at the edge, 1 deep inside
    shade = 1.0 - 0.6 * depth**0.7  # the surface turns away from the sky further down
    grazing = 0.55 + 0.45 * np.exp(-4.0 * depth)  # Fresnel: stronger mirror near the edge
    offset, width_, strength = body.band[v]
    band = strength * np.exp(-(((below / height - offset) / width_) ** 2))[..., None]
    mirror = body.reflectance[v] * grazing  # what the clear coat reflects is not diffused by the paint
    colour = body.paint[None, None] * shade * (1.0 - mirror) + mirror * mirrored + band
    return np.clip(colour, 0.0, 1.0).astype(np.float32)


def composite(colours: np.ndarray, body: EgoBody) -> np.ndarray:
    """Float images ``[T, V, H, W, 3]`` with the body drawn over the bottom of each camera."""
    out = colours.astype(np.float32, copy=True)
    for v in range(colours.shape[1]):
        alpha = body.alpha[v][..., None]
        if not alpha.any():
            continue
        for t in range(colours.shape[0]):
            out[t, v] = out[t, v] * (1.0 - alpha) + _paint_layer(body, v, out[t, v]) * alpha
    return out
