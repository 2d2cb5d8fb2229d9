"""A reconstruction: dynamic Gaussians plus the frame pair's metadata and per-camera intermediates.

Stored as ``recon.npz`` (format ``drivingscene/reconstruction`` v1, no pickles), documented in
docs/reconstruction-format.md. Static Gaussians carry no flow in the file: only the dynamic ones are
listed, by index, with their flow.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from drivingscene.data.frame_pair import FramePair
from drivingscene.data.npz import load_format, save_npz
from drivingscene.data.validate import KeySpec, check_header, check_intrinsics, check_keys, check_rigid
from drivingscene.errors import Problem, SceneFormatError
from drivingscene.gaussians.core import Gaussians, sh0_to_rgb
from drivingscene.gaussians.ground import Ground, fit_ground, road_plane
from drivingscene.geometry.flow import cams_to_world
from drivingscene.geometry.se3 import interpolate_pose, invert_rigid

RECON_FORMAT = "drivingscene/reconstruction"
RECON_VERSION = 2
# Versions this reader also reads: 1 held every attribute below in float32 (2 may hold `HALF` in float16).
RECON_OLDER_VERSIONS = (1,)
# Written in float16 (read back as float32): attributes whose float16 rounding is far below what a
# picture shows (quaternions 5e-4, log scales 4e-3: 0.4 % of a scale, SH colour 1e-3). Means,
# depth, the flow maps and the Gaussians' world flows stay float32: float16 would put a point 100 m
# away 6 cm off, and the maps are read back by analyses (a residual on the rigid flow's grid).
HALF = ("quats", "log_scales", "opacity_logits", "sh")
PRECISIONS = ("float16", "float32")

REQUIRED = {
    "format": KeySpec("str", (), f'"{RECON_FORMAT}"'),
    "version": KeySpec("int", (), str(RECON_VERSION)),
    "means": KeySpec("float32", ("N", 3), "Gaussian centres, world, at their keyframe"),
    "quats": KeySpec("float16|float32", ("N", 4), "rotations w, x, y, z"),
    "log_scales": KeySpec("float16|float32", ("N", 3), "log of the standard deviations in metres"),
    "opacity_logits": KeySpec("float16|float32", ("N",), "logit of the opacities"),
    "sh": KeySpec("float16|float32", ("N", "K", 3), "SH colour coefficients"),
    "keyframes": KeySpec("uint8", ("N",), "source keyframe 0 or 1"),
    "cameras": KeySpec("int16", ("N",), "source camera, -1 unknown"),
    "dynamic_index": KeySpec("int64", ("D",), "indices of Gaussians with flow"),
    "dynamic_flows": KeySpec("float32", ("D", 3), "their world displacement to the other keyframe"),
    "intrinsics": KeySpec("float32", ("V", 3, 3), "camera intrinsics"),
    "cam_to_ego": KeySpec("float32", ("V", 4, 4), "camera-to-ego transforms"),
    "ego_to_world": KeySpec("float64", (2, 4, 4), "ego poses at the keyframes"),
    "timestamps": KeySpec("float64", (2,), "keyframe times in seconds"),
    "camera_names": KeySpec("str", ("V",), "camera names"),
    "image_size": KeySpec("int", (2,), "H, W of the input images"),
}
OPTIONAL = {
    "sky_sh": KeySpec("float32", ("S", 3), "sky colour as SH of the world direction"),
    "hidden": KeySpec("bool", ("N",), "Gaussians hidden by an edit"),
    "images": KeySpec("uint8", (2, "V", "H", "W", 3), "input images"),
    "depth": KeySpec("float32", (2, "V", "H", "W"), "predicted z-depth"),
    "rigid_flow": KeySpec("float32", (2, "V", "H", "W", 2), "rigid flow, pixels"),
    "residual_flow": KeySpec("float32", (2, "V", "H", "W", 2), "residual (non-rigid) flow proposed by R and the search, pixels"),
    "moving": KeySpec("bool", (2, "V", "H", "W"), "pixels whose Gaussian moves: the residual is applied there only"),
    "meta": KeySpec("str", (), "JSON: method, source, timings"),
    "valid_mask": KeySpec("bool", ("V", "H", "W"), "pixels that see the world (False: ego body, hood)"),
    "origin": KeySpec("float64", (3,), "world point that means and poses are relative to"),
    "ground_rgb": KeySpec("float32", (3,), "colour of the road plane, the background below the horizon"),
    "view_bound_index": KeySpec("int64", ("B",), "indices of view-bound Gaussians (drawn near their view ray only)"),
    "view_bound_rays": KeySpec("float32", ("B", 3), "their unit view rays, world (source camera to mean)"),
}
PER_CAMERA = ("images", "depth", "rigid_flow", "residual_flow", "moving")


@dataclass(frozen=True, eq=False)
class Reconstruction:
    """Gaussians of a frame pair with the rig, poses and optional per-camera maps (numpy, as stored)."""

    gaussians: Gaussians
    intrinsics: np.ndarray  # [V, 3, 3] float32
    cam_to_ego: np.ndarray  # [V, 4, 4] float32
    ego_to_world: np.ndarray  # [2, 4, 4] float64
    timestamps: np.ndarray  # [2] float64
    camera_names: tuple[str, ...]
    image_size: tuple[int, int]  # (H, W)
    sky_sh: Tensor | None = None  # [S, 3]
    hidden: Tensor | None = None  # [N] bool
    images: np.ndarray | None = None  # [2, V, H, W, 3] uint8
    depth: np.ndarray | None = None  # [2, V, H, W] float32
    rigid_flow: np.ndarray | None = None  # [2, V, H, W, 2] float32
    residual_flow: np.ndarray | None = None  # [2, V, H, W, 2] float32, as proposed (also where static)
    moving: np.ndarray | None = None  # [2, V, H, W] bool: pixels whose Gaussian moves
    valid_mask: np.ndarray | None = None  # [V, H, W] bool: the input pixels that see the world
    origin: np.ndarray | None = None  # [3] float64: the world point positions and poses are relative to (`FramePair.origin`)
    meta: dict = field(default_factory=dict)
    # [3] the road's colour, drawn below the horizon with the sky model (`ground`); fitted from the
    # Gaussians on the road plane when not given (files written before it existed too)
    ground_rgb: Tensor | None = None

    def __post_init__(self):
        if self.ground_rgb is None and self.sky_sh is not None:
            g = self.gaussians
            fitted = fit_ground(g.means.detach(), sh0_to_rgb(g.sh[:, 0].detach()), self.road_plane())
            object.__setattr__(self, "ground_rgb", None if fitted is None else fitted.rgb)

    def road_plane(self) -> Tensor:
        """``[4]`` the road plane (n, d) in the world frame: the ego frame's z = 0 at keyframe 0."""
        return road_plane(torch.from_numpy(np.asarray(self.ego_to_world[0], np.float64)))

    @property
    def ground(self) -> Ground | None:
        """The background below the horizon (`drivingscene.gaussians.ground.Ground`); None without a sky
        model or where too few Gaussians lie on the road plane to colour it."""
        if self.ground_rgb is None or self.sky_sh is None:
            return None
        return Ground(self.road_plane(), self.ground_rgb.float())

    @classmethod
    def from_pair(cls, pair: FramePair, gaussians: Gaussians, **kwargs) -> Reconstruction:
        """Wrap Gaussians with the rig and poses of ``pair`` (and its images unless given)."""
        kwargs.setdefault("images", pair.images)
        kwargs.setdefault("valid_mask", pair.valid_mask)
        kwargs.setdefault("origin", pair.origin)
        return cls(
            gaussians=gaussians,
            intrinsics=pair.intrinsics,
            cam_to_ego=pair.cam_to_ego,
            ego_to_world=pair.ego_to_world,
            timestamps=pair.timestamps,
            camera_names=pair.camera_names,
            image_size=pair.image_size,
            **kwargs,
        )

    @property
    def num_views(self) -> int:
        return len(self.camera_names)

    @property
    def applied_residual_flow(self) -> np.ndarray | None:
        """The residual flow the Gaussians carry out ``[2, V, H, W, 2]``: ``residual_flow`` where a
        pixel's Gaussian moves, 0 where it stays static (as proposed where ``moving`` is absent)."""
        if self.residual_flow is None or self.moving is None:
            return self.residual_flow
        return np.where(self.moving[..., None], self.residual_flow, 0.0).astype(np.float32)

    @property
    def applied_total_flow(self) -> np.ndarray | None:
        """Rigid + applied residual flow ``[2, V, H, W, 2]``: where each pixel's Gaussian goes."""
        if self.rigid_flow is None:
            return None
        residual = self.applied_residual_flow
        return self.rigid_flow if residual is None else self.rigid_flow + residual

    @property
    def total_flow(self) -> np.ndarray | None:
        """Rigid + residual flow ``[2, V, H, W, 2]`` where both are present."""
        if self.rigid_flow is None:
            return None
        return self.rigid_flow if self.residual_flow is None else self.rigid_flow + self.residual_flow

    def ego_to_world_at(self, t: float | Tensor) -> Tensor:
        """Ego pose ``[..., 4, 4]`` (float64) at normalised time t, by SE(3) interpolation."""
        poses = torch.from_numpy(self.ego_to_world)
        return interpolate_pose(poses[0], poses[1], torch.as_tensor(t, dtype=torch.float64))

    def cam_to_world_at(self, t: float | Tensor) -> Tensor:
        """Rig camera poses ``[V, 4, 4]`` (float64) at normalised time t."""
        return cams_to_world(torch.from_numpy(self.cam_to_ego).double(), self.ego_to_world_at(t))

    def world_to_cam_at(self, t: float | Tensor) -> Tensor:
        return invert_rigid(self.cam_to_world_at(t))

    def visible(self) -> Gaussians:
        """The Gaussians not hidden by an edit."""
        return self.gaussians if self.hidden is None else self.gaussians.index(~self.hidden)

    def with_gaussians(self, gaussians: Gaussians, hidden: Tensor | None = None) -> Reconstruction:
        return replace(self, gaussians=gaussians, hidden=hidden)


def recon_to_arrays(recon: Reconstruction, precision: str = "float32") -> dict[str, np.ndarray]:
    """The file's arrays; ``precision`` "float16" stores `HALF` in float16, "float32" everything in float32."""
    if precision not in PRECISIONS:
        raise ValueError(f"recon_to_arrays: precision must be one of {PRECISIONS}, got {precision!r}")
    g = recon.gaussians.detach().to("cpu")
    dynamic = g.dynamic.nonzero().squeeze(1)
    arrays = {
        "format": np.array(RECON_FORMAT),
        "version": np.array(RECON_VERSION, dtype=np.int64),
        "means": g.means.float().numpy(),
        "quats": g.quats.float().numpy(),
        "log_scales": g.log_scales.float().numpy(),
        "opacity_logits": g.opacity_logits.float().numpy(),
        "sh": g.sh.float().numpy(),
        "keyframes": g.keyframes.numpy().astype(np.uint8),
        "cameras": g.cameras.numpy().astype(np.int16),
        "dynamic_index": dynamic.numpy().astype(np.int64),
        "dynamic_flows": g.flows[dynamic].float().numpy(),
        "intrinsics": np.asarray(recon.intrinsics, dtype=np.float32),
        "cam_to_ego": np.asarray(recon.cam_to_ego, dtype=np.float32),
        "ego_to_world": np.asarray(recon.ego_to_world, dtype=np.float64),
        "timestamps": np.asarray(recon.timestamps, dtype=np.float64),
        "camera_names": np.array(recon.camera_names, dtype=np.str_),
        "image_size": np.array(recon.image_size, dtype=np.int64),
        "meta": np.array(json.dumps(recon.meta, sort_keys=True)),
    }
    if recon.sky_sh is not None:
        arrays["sky_sh"] = recon.sky_sh.detach().cpu().float().numpy()
    if recon.ground_rgb is not None:
        arrays["ground_rgb"] = recon.ground_rgb.detach().cpu().float().numpy()
    if recon.hidden is not None:
        arrays["hidden"] = recon.hidden.cpu().numpy().astype(bool)
    bound = g.view_bound.nonzero().squeeze(1)
    if len(bound):
        arrays["view_bound_index"] = bound.numpy().astype(np.int64)
        arrays["view_bound_rays"] = g.view_rays[bound].float().numpy()
    if recon.valid_mask is not None:
        arrays["valid_mask"] = np.asarray(recon.valid_mask, dtype=bool)
    if recon.origin is not None:
        arrays["origin"] = np.asarray(recon.origin, dtype=np.float64)
    for key in PER_CAMERA:
        value = getattr(recon, key)
        if value is not None:
            arrays[key] = np.asarray(value, dtype={"images": np.uint8, "moving": bool}.get(key, np.float32))
    if precision == "float16":
        arrays.update({k: arrays[k].astype(np.float16) for k in HALF if k in arrays})
    return arrays


def _check_recon_values(arrays: dict, dims: dict, source: str) -> list[Problem]:
    out = check_header(arrays, RECON_FORMAT, RECON_VERSION, source, RECON_OLDER_VERSIONS)
    if dims["K"] not in (1, 4, 9, 16):
        out.append(Problem(source, "sh", "1, 4, 9 or 16 coefficients (SH degree 0-3)", f"{dims['K']}"))
    optional = tuple(k for k in ("origin", "ground_rgb") if k in arrays)
    for key in ("means", "quats", "log_scales", "sh", "dynamic_flows", *optional):
        if not np.all(np.isfinite(arrays[key])):
            out.append(Problem(source, key, "finite values", "NaN or inf"))
    if np.any(np.isnan(arrays["opacity_logits"])):  # +-inf logits are opacities 1 and 0
        out.append(Problem(source, "opacity_logits", "numbers (+-inf allowed)", "NaN"))
    if arrays["quats"].size and np.linalg.norm(arrays["quats"], axis=-1).min() < 1e-8:
        out.append(Problem(source, "quats", "non-zero quaternions", "a zero quaternion"))
    if arrays["keyframes"].size and arrays["keyframes"].max() > 1:
        out.append(Problem(source, "keyframes", "0 or 1", f"maximum {arrays['keyframes'].max()}"))
    n = dims["N"]
    for key in ("dynamic_index", "view_bound_index"):
        idx = arrays.get(key, np.zeros(0, np.int64))
        if idx.size and (idx.min() < 0 or idx.max() >= n or np.unique(idx).size != idx.size):
            out.append(Problem(source, key, f"unique indices in [0, {n})", f"range [{idx.min()}, {idx.max()}]"))
    if ("view_bound_index" in arrays) != ("view_bound_rays" in arrays):
        out.append(Problem(source, "view_bound_rays", "view_bound_index and view_bound_rays together", "only one of them"))
    elif "view_bound_rays" in arrays:
        norms = np.linalg.norm(arrays["view_bound_rays"], axis=-1) if arrays["view_bound_rays"].size else np.ones(1)
        if not np.all(np.isfinite(norms)) or np.abs(norms - 1).max() > 1e-3:
            out.append(Problem(source, "view_bound_rays", "unit vectors", "other lengths, NaN or inf"))
    height, width = (int(v) for v in arrays["image_size"])
    if "H" in dims and (dims["H"], dims["W"]) != (height, width):
        out.append(Problem(source, "image_size", f"[{dims['H']}, {dims['W']}] like the per-camera maps", f"[{height}, {width}]"))
    out += check_intrinsics(arrays["intrinsics"], height, width, source)
    out += check_rigid("cam_to_ego", arrays["cam_to_ego"], source)
    out += check_rigid("ego_to_world", arrays["ego_to_world"], source)
    try:
        json.loads(str(arrays.get("meta", "{}")))
    except json.JSONDecodeError as e:
        out.append(Problem(source, "meta", "a JSON object", f"invalid JSON ({e.msg})"))
    return out


def validate_recon_arrays(arrays: dict[str, np.ndarray], source: str = "<memory>") -> list[Problem]:
    problems, dims = check_keys(arrays, REQUIRED, OPTIONAL, source)
    if problems:
        return problems
    return _check_recon_values(arrays, dims, source)


def recon_from_arrays(arrays: dict[str, np.ndarray], source: str = "<memory>") -> Reconstruction:
    problems = validate_recon_arrays(arrays, source)
    if problems:
        raise SceneFormatError(problems)
    arrays = {k: (v.astype(np.float32) if k in HALF else v) for k, v in arrays.items()}
    flows = np.zeros_like(arrays["means"])
    flows[arrays["dynamic_index"]] = arrays["dynamic_flows"]
    view_rays = np.zeros_like(arrays["means"])
    if "view_bound_index" in arrays:
        view_rays[arrays["view_bound_index"]] = arrays["view_bound_rays"]
    t = torch.from_numpy
    gaussians = Gaussians(
        means=t(arrays["means"]),
        quats=t(arrays["quats"]),
        log_scales=t(arrays["log_scales"]),
        opacity_logits=t(arrays["opacity_logits"]),
        sh=t(arrays["sh"]),
        flows=t(flows),
        keyframes=t(arrays["keyframes"].astype(np.int64)),
        cameras=t(arrays["cameras"].astype(np.int64)),
        view_rays=t(view_rays),
    )
    return Reconstruction(
        gaussians=gaussians,
        intrinsics=arrays["intrinsics"],
        cam_to_ego=arrays["cam_to_ego"],
        ego_to_world=arrays["ego_to_world"],
        timestamps=arrays["timestamps"],
        camera_names=tuple(str(n) for n in arrays["camera_names"]),
        image_size=(int(arrays["image_size"][0]), int(arrays["image_size"][1])),
        sky_sh=t(arrays["sky_sh"]) if "sky_sh" in arrays else None,
        ground_rgb=t(arrays["ground_rgb"]) if "ground_rgb" in arrays else None,
        hidden=t(arrays["hidden"]) if "hidden" in arrays else None,
        valid_mask=arrays.get("valid_mask"),
        origin=arrays.get("origin"),
        meta=json.loads(str(arrays.get("meta", "{}"))),
        **{k: arrays[k] for k in PER_CAMERA if k in arrays},
    )


def save_reconstruction(
    recon: Reconstruction, path: str | os.PathLike, precision: str = "float16", compress: bool = False
) -> Path:
    """Validate and write ``recon.npz`` atomically: `HALF` in float16 (``precision``) and the zip
    stored, not deflated (``compress``): for a 6x176x320 pair 43.1 MB in 0.31 s against 42.9 MB in
    2.1-2.4 s for float32 deflated (the Gaussians barely compress; docs/reconstruction-format.md)."""
    arrays = recon_to_arrays(recon, precision)
    problems = validate_recon_arrays(arrays, str(path))
    if problems:
        raise SceneFormatError(problems)
    return save_npz(path, arrays, compress=compress, level=1)


def load_reconstruction(path: str | os.PathLike) -> Reconstruction:
    return recon_from_arrays(load_format(path, REQUIRED, OPTIONAL), str(path))


def is_reconstruction_file(arrays: dict[str, np.ndarray]) -> bool:
    return "format" in arrays and str(arrays["format"]) == RECON_FORMAT
