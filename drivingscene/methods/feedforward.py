"""The DrivingScene model as a reconstruction method: frame pair -> Reconstruction, one forward pass.

    reconstruct(model, pair)  ->  Reconstruction with the dynamic Gaussians of both keyframes and the
                                  per-camera depth, rigid flow and residual flow.

Variants for the ablations: ``use_residual=False`` (static-only: rigid flow, every Gaussian static),
``search=None`` (R's flow as it is, without the search along the rigid flow) and a model trained in
one stage (it is the same code with other weights).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from safetensors.torch import load_file
from torch import Tensor

from drivingscene.data.frame_pair import FramePair
from drivingscene.data.tensors import pair_to_tensors, world_cameras
from drivingscene.errors import InputError
from drivingscene.gaussians.assembly import RAY_EXTENT, FootprintRule
from drivingscene.gaussians.core import sh0_to_rgb
from drivingscene.gaussians.ground import fit_ground, road_plane
from drivingscene.gaussians.parsimony import BlockMerge, KeyframeDedupe, keyframe_duplicates, merge_to_budget, sharpened
from drivingscene.gaussians.recon import Reconstruction
from drivingscene.gaussians.visibility import CarveConfig, carve
from drivingscene.methods.depth_edges import EdgeSharpen, sharpen_depth_edges
from drivingscene.methods.devices import on_cpu, sync
from drivingscene.methods.matched_depth import MatchedDepthConfig, match_depth
from drivingscene.methods.memory import check_reconstruct_memory
from drivingscene.methods.object_motion import ObjectMotionConfig, object_flows
from drivingscene.methods.rig_objects import RigObjectConfig, with_rig_objects
from drivingscene.models.lift import (
    LiftConfig,
    MotionSearchConfig,
    explain_by_parallax,
    lift_scene_flow,
    search_motion,
    sky_distance,
    sky_mask,
)
from drivingscene.models.model import DrivingSceneModel, ModelConfig
from drivingscene.models.pipeline import assemble, predict_flow, predict_static, with_depth, without_gaussian_head
from drivingscene.precision import resolve_amp
from drivingscene.render.color_solve import ITERATIONS as COLOR_ITERATIONS
from drivingscene.render.color_solve import solve_gaussian_colors
from drivingscene.render.composite import SURFACE_TOLERANCE
from drivingscene.render.project import EPS2D
from drivingscene.render.sky import fit_sky_from_pixels
from drivingscene.resources import asset_path

DEFAULT_WEIGHTS = "weights/drivingscene.safetensors"


# `InferenceOptions.far_layer`: the far layer's depth cap, in sky distances (1.5, 10 and 100 drew the
# same pictures on the test pairs measured; docs/magnification.md).
FAR_LAYER = 10.0
MOVING_DEPTHS = ("matched", "prior")  # `InferenceOptions.moving_depth` (docs/moving-objects.md)


@dataclass(frozen=True)
class InferenceOptions:
    use_residual: bool = True  # False: static-only ablation (rigid flow, no dynamic Gaussians)
    # Explained moving pixels (parallax before motion) take a depth triangulated from R's and the
    # search's flow only where matching did not already triangulate one and the image has texture
    # along the epipolar line (docs/choices-matching.md, run 4).
    lift: LiftConfig = LiftConfig(epipolar_depth="unmatched", epipolar_min_texture=0.02)
    # R's flow refined by a photometric search along the rigid flow (models/lift.py); None: R alone
    search: MotionSearchConfig | None = MotionSearchConfig()
    # Moving objects tracked as wholes (methods/object_motion.py): where one is found its warp is the
    # flow, in place of R's and the search's (docs/moving-objects.md: on twenty test pairs +0.77 dB
    # on moving pixels and +0.06 dB on all pixels over R and the search alone). None: not run.
    objects: ObjectMotionConfig | None = ObjectMotionConfig()
    # bf16 autocast for D and P (R runs in float32: faster there, see training-notes). None: where the
    # hardware does bf16 natively (drivingscene.precision: float32 on an AVX2-only CPU); True/False: forced.
    amp: bool | None = None
    threads: int | None = None
    # Free-space carving: drop Gaussians another image of the pair sees through
    # (gaussians/visibility.py); None: keep every Gaussian.
    carve: CarveConfig | None = None
    # Gaussians that another image sees through (the same test as ``carve``) are kept but made
    # view-bound (`Gaussians.view_rays`): drawn near the direction their camera saw them along and
    # faded away from it, where their wrong depth shows (docs/magnification.md). None: none.
    view_bound: CarveConfig | None = CarveConfig()
    # False: P's predictions unused, every pixel's Gaussian its default surfel (ablation, bench choices)
    gaussian_head: bool = True
    # D's depth corrected by classical matching between the keyframes (methods/matched_depth.py);
    # None: D's depth as it is.
    match: MatchedDepthConfig | None = MatchedDepthConfig()
    # Iterations of the colour solve that makes each input image's own Gaussians re-render it
    # (render/color_solve.py, docs/magnification.md); 0: P's colours as they are. With a merge that
    # solves over its Gaussians (``merge.fit_colors`` > 0, the default) that solve runs instead,
    # with its own iterations, and this is only on (> 0) or off.
    fit_colors: int = COLOR_ITERATIONS
    # The surface tolerance the colour solve fits each image's own layer for: the layered blends'
    # (render.scene.LayerBlend.surface_tolerance); 0: front-to-back compositing.
    surface_tolerance: float = SURFACE_TOLERANCE
    # The footprint rule on P's scales (gaussians/assembly.py); NO_FOOTPRINT_RULE: as 3DGS (ablation).
    footprints: FootprintRule = FootprintRule()
    # Each Gaussian extended along its view ray by this many times the depth step to its neighbours
    # on a slope, invisible in its own view (gaussians/assembly.py, docs/magnification.md, *Along the
    # rays*); 0: none.
    ray_extent: float = RAY_EXTENT
    # The pixels beyond the sky distance (far content and the sky itself) as Gaussians at their depth,
    # at most this many (> 1) times the sky distance away, static and view-bound
    # (docs/magnification.md, *Far layer*); 0: none, the sky model alone draws them.
    far_layer: float = FAR_LAYER
    # 2x2 blocks of an image's Gaussians that are one flat piece of surface of smooth colour moving
    # as one become one Gaussian, and the colours are solved over them (gaussians/parsimony.py,
    # docs/parsimony.md); None: one per pixel.
    merge: BlockMerge | None = BlockMerge()
    # Static Gaussians whose surface point the same camera's image at the other keyframe also holds
    # left to that copy (gaussians/parsimony.py); None (default): both kept. Lost on validation pairs:
    # 3 % fewer Gaussians for 0.04 dB at the in-between frame and 1-2 dB in the input views
    # (docs/parsimony.md).
    dedupe: KeyframeDedupe | None = None
    # depth edges made steps where the image has its edges (methods/depth_edges.py); None: off
    edges: EdgeSharpen | None = None
    # moving objects searched across the rig as translations of their surface, where the rigid flow
    # leaves the image or fails and nothing moves them yet (methods/rig_objects.py); None: off
    rig_objects: RigObjectConfig | None = None
    # the depth of the pixels whose Gaussians move: "matched" (the matching's, as every pixel) or
    # "prior" (D's own, from one instant: the matching over time reads an object's motion as depth)
    moving_depth: str = "matched"

    def __post_init__(self) -> None:
        if self.moving_depth not in MOVING_DEPTHS:
            raise ValueError(f"InferenceOptions.moving_depth: expected one of {MOVING_DEPTHS}, got {self.moving_depth!r}")


def load_model(path: str | Path | None = None, device: str = "cpu") -> DrivingSceneModel:
    """Model from ``NAME.safetensors`` + ``NAME.json`` (default: the shipped weights)."""
    path = Path(path) if path else asset_path(DEFAULT_WEIGHTS)
    config_path = path.with_suffix(".json")
    if not path.exists():
        raise InputError(f"{path}: model weights not found (train them with `drivingscene train`, or pass --weights)")
    if not config_path.exists():
        raise InputError(f"{config_path}: expected the model's JSON config beside its weights, found nothing")
    try:
        meta = json.loads(config_path.read_text())
        config = ModelConfig.from_dict(meta["model"])
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as e:
        raise InputError(f"{config_path}: model: expected the model's JSON config, found {_one_line(e)}") from None
    state = read_safetensors(path)
    # built on the meta device and given the file's tensors (cast to the model's dtypes): no random
    # initialisation to overwrite (~20 ms of a command's start-up); built as usual where a tensor
    # would stay on the meta device (one the file does not hold)
    with torch.device("meta"):
        model = DrivingSceneModel(config)
    dtypes = {name: t.dtype for name, t in model.state_dict().items()}
    state = {name: t.to(dtypes[name]) if name in dtypes else t for name, t in state.items()}
    tensors = (*model.named_parameters(), *model.named_buffers())
    assign = all(name in state or not t.is_meta for name, t in tensors)
    if not assign:
        model = DrivingSceneModel(config)
    try:
        missing, unexpected = model.load_state_dict(state, strict=False, assign=assign)
    except RuntimeError as e:  # a tensor of another shape than the config's model has
        first = next((line.strip() for line in str(e).splitlines() if "size mismatch" in line), _one_line(e))
        raise InputError(f"{path}: expected the tensor shapes of the model in {config_path.name}, found {first}") from None
    if missing or unexpected:
        raise InputError(
            f"{path}: weights do not match the model config (missing {len(missing)}, unexpected {len(unexpected)} tensors)"
        )
    assert not any(t.is_meta for t in (*model.parameters(), *model.buffers())), "load_model: a tensor left unloaded"
    return model.to(device).eval()


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split())


SAFETENSORS_MAX_HEADER = 100_000_000  # the format's own limit on the JSON header (bytes)


def read_safetensors_header(path: Path) -> dict:
    """The JSON header of a ``.safetensors`` file (8-byte little-endian length, then JSON), checked
    before the file is handed to safetensors. Raises ``InputError`` naming the file."""
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            prefix = f.read(8)
            if len(prefix) < 8:
                raise InputError(
                    f"{path}: header: expected a safetensors file (an 8-byte header length first), found {size} bytes"
                )
            length = int.from_bytes(prefix, "little")
            if length > min(size - 8, SAFETENSORS_MAX_HEADER):
                raise InputError(f"{path}: header: expected a header length of at most {size - 8} bytes, found {length}")
            header = json.loads(f.read(length).decode("utf-8"))
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as e:
        raise InputError(f"{path}: header: expected a JSON object of tensor names, found {_one_line(e)[:200]}") from None
    if not isinstance(header, dict):
        raise InputError(f"{path}: header: expected a JSON object of tensor names, found {type(header).__name__}")
    return header


def read_safetensors(path: Path) -> dict[str, torch.Tensor]:
    """Every tensor of a ``.safetensors`` file; one-line ``InputError``s for a damaged one."""
    from safetensors import SafetensorError

    read_safetensors_header(path)
    try:
        return load_file(str(path))
    except (SafetensorError, OSError, ValueError, RuntimeError) as e:
        raise InputError(f"{path}: expected a valid safetensors file, found {_one_line(e)[:200]}") from None


def _seen_through(gaussians, batch, depth, sky_pixels, config: CarveConfig) -> Tensor:
    """``[N]`` bool: the Gaussians some other image of the pair sees through (`carve`)."""
    from drivingscene.geometry.se3 import invert_rigid

    num_views = batch.num_views
    cams = world_cameras(batch).flatten(0, 1)
    world = None if batch.valid_mask is None else batch.valid_mask.repeat(2, 1, 1)
    keep = carve(
        gaussians,
        gaussians.keyframes * num_views + gaussians.cameras,
        invert_rigid(cams).float(),
        batch.intrinsics.repeat(2, 1, 1),
        depth.flatten(0, 1),
        sky_pixels.flatten(0, 1),
        world,
        config,
    )
    return ~keep


def _view_bound(gaussians, batch, bound: Tensor):
    """``gaussians`` with those of ``bound`` ``[N]`` made view-bound (some other image sees through
    them, or the far layer's): their view ray is the unit direction from their source camera's
    centre to their mean."""
    centres = world_cameras(batch)[..., :3, 3].to(gaussians.means)  # [2, V, 3]
    rays = F.normalize(gaussians.means - centres[gaussians.keyframes, gaussians.cameras], dim=-1)
    return replace(gaussians, view_rays=torch.where(bound[:, None], rays, torch.zeros_like(rays)))


# The stages of `reconstruct` as its progress callback names them, in order.
STAGES = {
    "static": "depth and Gaussian parameters (D, P) on {views} images",
    "match": "matching the keyframes (DIS flow, triangulation)",
    "flow": "motion: rigid flow, R and the search",
    "assembly": "assembling the Gaussians and the sky",
}


def _with_objects(flow, batch, pair: FramePair, depth: Tensor, excluded: Tensor, config: ObjectMotionConfig):
    """``flow`` with its total flow replaced by the tracked objects' (`object_flows`) where one was
    found, and by the rigid flow elsewhere when ``config.elsewhere`` is "rigid"."""
    rigid = flow.rigid.detach().cpu().numpy()
    other = flow.rigid if config.elsewhere == "rigid" else flow.total
    moved, owned = object_flows(
        pair.images, rigid, excluded.cpu().numpy(), depth.detach().cpu().numpy(), config, other.detach().cpu().numpy()
    )
    moved, owned = torch.from_numpy(moved).to(flow.rigid), torch.from_numpy(owned).to(flow.rigid.device)
    return replace(flow, searched=torch.where(owned[..., None], moved, other))


def _stage_reporter(progress, num_views: int) -> Callable[[str | None], None]:
    """``report(stage)``: ``progress(share of stages done, the stage's name)``; ``report(None)``: done."""
    names = list(STAGES)

    def report(stage: str | None) -> None:
        if progress is None:
            return
        if stage is None:
            progress(1.0, "reconstructed")
        else:
            progress(names.index(stage) / len(names), STAGES[stage].format(views=2 * num_views))

    return report


@torch.no_grad()
def reconstruct(
    model: DrivingSceneModel,
    pair: FramePair,
    options: InferenceOptions = InferenceOptions(),
    flow_predictor=None,
    progress: Callable[[float | None, str], None] | None = None,
) -> Reconstruction:
    """Dynamic Gaussians of both keyframes (world frame) and per-camera maps, with timings in ``meta``.

    ``flow_predictor(model, batch, depth) -> FlowPrediction`` replaces R and the search
    (diagnostics: ground-truth flow). ``progress(fraction, message)`` is called as each stage
    starts (`STAGES`; the fraction is the share of stages done), and with 1.0 at the end."""
    check_reconstruct_memory(pair.num_views, *pair.image_size)  # refuse before allocating (methods/memory.py)
    report = _stage_reporter(progress, pair.num_views)
    report("static")
    if options.threads:
        torch.set_num_threads(options.threads)
    device = next(model.parameters()).device
    use_amp = resolve_amp(options.amp, device)  # decided once per machine (cached), not timed
    timings = {}
    start = time.perf_counter()
    batch = pair_to_tensors(pair, with_gt=False, with_eval=False).to(device)
    with torch.autocast(device.type, dtype=torch.bfloat16, enabled=use_amp):
        static = predict_static(model, batch)
    if not options.gaussian_head:
        static = without_gaussian_head(model, static, batch)
    sync(device)
    timings["static_s"] = time.perf_counter() - start
    depth = static.depth.float()
    sky = sky_mask(depth, batch.intrinsics, model.config.depth.ref_focal, options.lift)
    # Pixels that do not see the world (ego body, hood: valid_mask) make no Gaussian, do not move
    # and do not colour the sky: from here on they are treated like sky, except in the sky fit.
    sky_pixels = sky if batch.valid_mask is None else sky & batch.valid_mask
    if batch.valid_mask is not None:
        sky = sky | ~batch.valid_mask
    matched = None  # pixels whose depth the matching triangulated
    refused = None  # pixels whose triangulation over time it refused as motion, and their matched flow
    prior_depth = depth  # D's own
    if options.match is not None:
        report("match")
        t0 = time.perf_counter()
        if options.match.prior_outlier is not None and options.match.refused_motion:
            depth, matched, match_timings, refused, refused_flow = match_depth(
                depth, sky, pair, batch, options.match, with_motion=True
            )
        else:
            depth, matched, match_timings = match_depth(depth, sky, pair, batch, options.match)
        timings["match_views"] = match_timings.get("match_fallback_views", 0.0)
        static = with_depth(static, depth)
        sync(device)
        timings["match_s"] = time.perf_counter() - t0
    if options.edges is not None:
        t0 = time.perf_counter()
        depth = sharpen_depth_edges(depth, batch.images, sky, options.edges)
        static = with_depth(static, depth)
        timings["edges_s"] = time.perf_counter() - t0
    report("flow")
    t0 = time.perf_counter()
    search = options.search if flow_predictor is None else None
    if not options.use_residual:
        flow = None
    elif flow_predictor is not None:
        flow = flow_predictor(model, batch, depth)
    else:  # with the search, R refines only down to the level whose flow the search proposes
        level = search.proposal_level if search is not None else 0
        flow = predict_flow(model, batch, depth, finest_level=level, all_levels=False)
    if flow is not None and search is not None:
        t1 = time.perf_counter()
        flow = search_motion(flow, batch, search, model.config.input_size)
        sync(device)
        timings["search_s"] = time.perf_counter() - t1
    # the refused pixels move as the matching saw them (tracked objects over it)
    if flow is not None and refused is not None and bool(refused.any()):
        flow = replace(flow, searched=torch.where(refused[..., None], refused_flow.to(flow.rigid), flow.total))
    if flow is not None and options.objects is not None and flow_predictor is None:
        t1 = time.perf_counter()
        flow = _with_objects(flow, batch, pair, depth, sky, options.objects)
        timings["objects_s"] = time.perf_counter() - t1
    net_width = model.config.input_size[1] if model.config.input_size else None
    scene_flow = applied = None
    if flow is not None:
        scene_flow, dynamic = lift_scene_flow(
            depth, flow.total, flow.residual, sky, batch, options.lift, net_width, rigid=flow.rigid, behind=flow.behind
        )
        if options.lift.epipolar_static:  # moving pixels that parallax explains: static, at their triangulated depth
            t1 = time.perf_counter()
            candidates = dynamic
            if options.lift.epipolar_candidates == "residual":
                threshold = options.lift.dynamic_threshold_px * (depth.shape[-1] / net_width if net_width else 1.0)
                candidates = dynamic | ((flow.residual.square().sum(-1) > threshold**2) & ~sky)
                if flow.behind is not None:
                    candidates &= ~flow.behind
            fixed = {"triangulated": None, "unmatched": matched, "keep": torch.ones_like(candidates)}[options.lift.epipolar_depth]
            if refused is not None:  # motion, not parallax: never explained by a static surface
                candidates = candidates & ~refused
            depth, flow, explained = explain_by_parallax(depth, flow, candidates, batch, options.lift, net_width, fixed)
            scene_flow = torch.where(explained[..., None], torch.zeros_like(scene_flow), scene_flow)
            static = with_depth(static, depth)
            timings["parallax_s"] = time.perf_counter() - t1
            dynamic = dynamic & ~explained
        # The pixels whose Gaussian moves: the residual is applied there only; elsewhere (below the
        # threshold, inconsistent, explained by parallax) it was a proposal of R and the search that
        # nothing follows (issue 21: 90 px proposed on cameras where nothing moves).
        applied = dynamic
        if options.moving_depth == "prior" and bool(applied.any()):
            depth = torch.where(applied, prior_depth, depth)
            static = with_depth(static, depth)
            lifted, _ = lift_scene_flow(
                depth, flow.total, flow.residual, sky, batch, options.lift, net_width, rigid=flow.rigid, behind=flow.behind
            )
            scene_flow = torch.where(applied[..., None], lifted, scene_flow)
    if options.rig_objects is not None and scene_flow is not None:
        t1 = time.perf_counter()
        scene_flow, applied = with_rig_objects(scene_flow, applied, depth, flow.rigid, sky, batch, pair, options.rig_objects)
        timings["rig_objects_s"] = time.perf_counter() - t1
    rigid = flow.rigid if flow is not None else None
    sync(device)
    timings["flow_s"] = time.perf_counter() - t0
    report("assembly")
    t0 = time.perf_counter()
    if device.type != "cpu":  # the assembly's steps are compiled CPU kernels (kernels/csrc): on a GPU they run on the CPU
        static, batch, sky, sky_pixels, scene_flow, depth = on_cpu((static, batch, sky, sky_pixels, scene_flow, depth))
    layer_static, layer_sky, layer_flow = static, sky, scene_flow
    if options.far_layer > 0:  # the pixels beyond the sky distance make static Gaussians there too
        distance = sky_distance(batch.intrinsics, depth.shape[-1], model.config.depth.ref_focal, options.lift)
        cap = options.far_layer * distance.to(depth)[:, None, None]
        layer_static = with_depth(static, torch.where(sky_pixels, torch.minimum(depth, cap), depth))
        layer_sky = sky & ~sky_pixels
        if scene_flow is not None:
            layer_flow = torch.where(sky_pixels[..., None], torch.zeros_like(scene_flow), scene_flow)
    # a merge that solves the colours over its Gaussians (when colours are solved at all) runs the
    # only solve: the per-pixel one before it would be redone
    refit = options.merge.fit_colors if options.merge is not None and options.fit_colors > 0 else 0
    gaussians = assemble(
        layer_static, batch, layer_sky, layer_flow, local_to_world=batch.local_to_world,
        fit_colors=0 if refit > 0 else options.fit_colors,
        footprints=options.footprints, surface_tolerance=options.surface_tolerance, ray_extent=options.ray_extent,
    )  # fmt: skip
    far = sky_pixels[~layer_sky]  # [N]: the far layer's Gaussians (pixel order, as assembled)
    pixels = (~layer_sky).flatten().nonzero().squeeze(1)  # [N]: each Gaussian's pixel
    if options.carve is not None:
        t1 = time.perf_counter()
        keep = ~_seen_through(gaussians, batch, depth, sky_pixels, options.carve)
        gaussians, far, pixels = gaussians.index(keep), far[keep], pixels[keep]
        timings["carve_s"] = time.perf_counter() - t1
    bound = far
    if options.view_bound is not None:
        t1 = time.perf_counter()
        bound = bound | _seen_through(gaussians, batch, depth, sky_pixels, options.view_bound)
        timings["view_bound_s"] = time.perf_counter() - t1
    if bound.any():
        gaussians = _view_bound(gaussians, batch, bound)
    if options.dedupe is not None:
        t1 = time.perf_counter()
        still = ~layer_sky if layer_flow is None else ~layer_sky & (layer_flow.abs().amax(-1) == 0)
        duplicate = keyframe_duplicates(
            layer_static.depth.detach(), still, batch.images, batch.cam_to_local, batch.intrinsics, options.dedupe
        ).flatten()[pixels]
        gaussians, pixels = gaussians.index(~duplicate), pixels[~duplicate]
        timings["dedupe_s"] = time.perf_counter() - t1
    if options.merge is not None:
        t1 = time.perf_counter()
        per_pixel = len(gaussians)
        depth_maps = layer_static.depth.detach().flatten(0, 1).float()
        images = batch.images.flatten(0, 1).permute(0, 2, 3, 1)  # [I, H, W, 3]
        intrinsics = batch.intrinsics.repeat(2, 1, 1)  # [I, 3, 3]
        merged = merge_to_budget(
            gaussians, pixels, depth_maps, intrinsics, options.merge, eps2d=EPS2D, with_owners=refit > 0,
            # the colours not solved yet: the merge reads the images as the solve will sharpen them
            colors=sharpened(images).reshape(-1, 3).index_select(0, pixels) if refit > 0 else None,
        )  # fmt: skip
        if refit > 0:  # every Gaussian's colour fitted over the pixels it stands for
            merged, owners = merged
            merged = solve_gaussian_colors(
                merged, owners, pixels, images,
                torch.linalg.inv(world_cameras(batch).flatten(0, 1)).float(), intrinsics, refit,
                surface_tolerance=options.surface_tolerance,
            )  # fmt: skip
        gaussians = merged
        timings["merge_s"] = time.perf_counter() - t1
    sky_sh = fit_sky_from_pixels(batch.images, sky_pixels, world_cameras(batch), batch.intrinsics)
    # the background below the horizon, here so that its cost is timed (Reconstruction fits it otherwise)
    ground = fit_ground(
        gaussians.means.detach(), sh0_to_rgb(gaussians.sh[:, 0].detach()), road_plane(torch.from_numpy(pair.ego_to_world[0]))
    )
    sync(device)
    timings["assembly_s"] = time.perf_counter() - t0
    timings["total_s"] = time.perf_counter() - start
    if rigid is None:
        from drivingscene.models.pipeline import rigid_flows

        rigid = rigid_flows(depth, batch)
    sky_np = sky.cpu().numpy()[..., None]
    report(None)
    return Reconstruction.from_pair(
        pair,
        gaussians.detach().to("cpu"),
        sky_sh=sky_sh.cpu(),
        ground_rgb=None if ground is None else ground.rgb,
        depth=np.where(sky_np[..., 0], 0.0, depth.cpu().numpy()).astype(np.float32),
        rigid_flow=np.where(sky_np, 0.0, rigid.cpu().numpy()).astype(np.float32),
        residual_flow=None if flow is None else np.where(sky_np, 0.0, flow.residual.cpu().numpy()).astype(np.float32),
        moving=None if applied is None else (applied.cpu() & ~sky.cpu()).numpy(),
        meta={
            "method": "drivingscene" if options.use_residual else "drivingscene-static",
            "timings": {k: round(v, 4) for k, v in timings.items()},
            "precision": "bf16 autocast" if use_amp else "float32",
            **({} if options.merge is None else {"per_pixel_gaussians": per_pixel}),
        },
    )
