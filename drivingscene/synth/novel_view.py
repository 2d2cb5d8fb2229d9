"""Ground truth of a procedural scene seen from any camera, at any image size and time.

The scene of ``(config, seed)`` is rebuilt (`build_scene`) and rendered with the generator's own
renderer and shading (`SynthRenderer.render_color`, supersampled as ``config.supersample`` says),
exactly as `generate_pair` renders its keyframes, but from the cameras given: a viewer's camera
above the road, a rig camera moved sideways, a rig camera at a larger image size. Objects are posed
at the scene time of normalised time t, ``t0 + t * keyframe_gap`` (`Scene.agents_to_world`).

The colours are finished like the keyframe images (`generate.finish_images`): the exposure gain of
time t, then rounding to uint8 levels. What belongs to the input cameras rather than to the scene
is left out: image noise, the per-camera photometric looks and JPEG, the ego body and a blacked-out
camera. So at a rig pose, at the input size and at a keyframe or eval time, the ground truth equals
the pair's own image for configs without those (the default preset, with simultaneous triggers).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from drivingscene.synth.config import SynthConfig, validate_config
from drivingscene.synth.generate import finish_images, shading_uniforms
from drivingscene.synth.render import SynthRenderer, View
from drivingscene.synth.scene import Scene, build_scene

# Colour is rendered at supersample x the output size with all cameras of a call stacked in one
# framebuffer; at most this many supersampled rows go into one pass (llvmpipe allows 16384 and
# the framebuffer lives in host memory).
MAX_ROWS = 8192


@dataclass(frozen=True, eq=False)
class NovelViews:
    """Ground truth of ``B`` cameras at one time."""

    images: np.ndarray  # [B, H, W, 3] float32 in [0, 1], on the uint8 levels of the pair's images
    depth: np.ndarray | None  # [B, H, W] float32 camera z in metres, 0 = sky; None when not asked for


class ProceduralScene:
    """The scene of ``(config, seed)`` uploaded once and rendered from any cameras.

    Reuse a ``SynthRenderer`` across scenes (its GL context and programs); call ``close`` (or use
    the object as a context manager) to release the scene's GPU meshes.
    """

    def __init__(self, config: SynthConfig, seed: int, renderer: SynthRenderer | None = None) -> None:
        self.config = validate_config(config)
        self.seed = seed
        self.scene: Scene = build_scene(config, seed)
        self.renderer = renderer if renderer is not None else SynthRenderer()
        self._gpu = self.renderer.upload(self.scene.static_vertices, [a.vertices for a in self.scene.agents])
        self._shading = shading_uniforms(self.scene, config)

    def close(self) -> None:
        if self._gpu is not None:
            self._gpu.release()
            self._gpu = None

    def __enter__(self) -> ProceduralScene:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def seconds(self, t: float) -> float:
        """Scene time in seconds of normalised time t (0: keyframe 0, 1: keyframe 1)."""
        return self.scene.t0 + float(t) * self.scene.keyframe_gap

    def ego_to_world(self, t: float) -> np.ndarray:
        """``[4, 4]`` float64 exact ego pose at normalised time t (the generator's path)."""
        return self.scene.ego_to_world(self.seconds(t))

    def render(
        self,
        cams_to_world: np.ndarray,  # [B, 4, 4] float64, OpenCV camera axes, metres
        intrinsics: np.ndarray,  # [B, 3, 3] pixels, pixel centres at integer coordinates
        size: tuple[int, int],  # (H, W)
        t: float,
        *,
        with_depth: bool = False,
    ) -> NovelViews:
        """Finished colour (and with ``with_depth`` the z-depth) of every camera at normalised time t."""
        cams_to_world = np.asarray(cams_to_world, np.float64).reshape(-1, 4, 4)
        intrinsics = np.asarray(intrinsics, np.float64).reshape(-1, 3, 3)
        if len(cams_to_world) != len(intrinsics):
            raise ValueError(f"cams_to_world [{len(cams_to_world)}, 4, 4] and intrinsics [{len(intrinsics)}, 3, 3] differ in B")
        if self._gpu is None:
            raise RuntimeError("ProceduralScene.render after close()")
        height, width = int(size[0]), int(size[1])
        view = View(cams_to_world, self.scene.road_to_world, self.scene.agents_to_world(self.seconds(t)))
        per_pass = max(1, MAX_ROWS // (height * self.config.supersample))
        colours, depths = [], []
        for start in range(0, len(cams_to_world), per_pass):
            part = slice(start, start + per_pass)
            sub = View(view.cams_to_world[part], view.static_to_world, view.agents_to_world)
            colours.append(
                self.renderer.render_color(
                    self._gpu, sub, intrinsics[part], (height, width), self.config.supersample, self._shading
                )
            )
            if with_depth:
                now, other, _ = self.renderer.render_geometry(self._gpu, sub, sub, intrinsics[part], (height, width))
                depths.append(np.where(other[..., 3] > 0.5, now[..., 2], 0.0).astype(np.float32))
        images = finish_colours(np.concatenate(colours), t, self.config, self.seed)
        return NovelViews(images, np.concatenate(depths) if with_depth else None)


def finish_colours(colours: np.ndarray, t: float, config: SynthConfig, seed: int) -> np.ndarray:
    """Rendered colours ``[B, H, W, 3]`` finished as the generator finishes an image taken at
    normalised time t (exposure gain, uint8 rounding; no noise, looks, JPEG or blackout), as float32
    ``[B, H, W, 3]`` in [0, 1]."""
    clean = replace(config, noise_std=0.0, blackout_camera=None)
    return finish_images(colours[None], [float(t)], clean, seed)[0].astype(np.float32) / 255.0


def render_novel_views(
    config: SynthConfig,
    seed: int,
    cams_to_world: np.ndarray,  # [B, 4, 4]
    intrinsics: np.ndarray,  # [B, 3, 3]
    size: tuple[int, int],  # (H, W)
    t: float,
    renderer: SynthRenderer | None = None,
    with_depth: bool = False,
) -> NovelViews:
    """One-off `ProceduralScene.render` (builds and uploads the scene, renders, releases it)."""
    with ProceduralScene(config, seed, renderer) as scene:
        return scene.render(cams_to_world, intrinsics, size, t, with_depth=with_depth)
