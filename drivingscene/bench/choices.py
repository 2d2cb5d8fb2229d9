"""``drivingscene bench choices``: inference and rendering choices compared on validation pairs.

Each variant is a set of choices made after the networks: how the two keyframes' Gaussians are
combined when rendering (``blend``), free-space carving (``carve``, gaussians/visibility.py),
the search along the rigid flow (``search``) and how much better than the static world a moved
match must be (``bonus``, MotionSearchConfig.static_bonus), the photometric check of the lift
(``photo``), parallax before motion (``parallax``, LiftConfig.epipolar_static) and the
smallest dynamic region (``region``). For each,
pair by pair on the same inputs: the input views rendered back at their keyframes, the
intermediate frame on all and on moving pixels (and, pair by pair against the first variant, how
many pairs gain on moving pixels, with a two-sided sign test), the flow error, the share of dynamic Gaussians (with the
ground-truth share of moving pixels), and the seconds of the reconstruction. Run it on validation
pairs (``drivingscene synth --split val``), never on the test pairs the results report on.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from drivingscene.bench import write_report
from drivingscene.errors import InputError
from drivingscene.gaussians.timing import DEFAULT_BLEND
from drivingscene.machine import machine_description

DEFAULT_VARIANTS = [
    "blend=all,parallax=off",  # the defaults before docs/choices.md
    "blend=all,parallax=on",
    "blend=layers,parallax=on",  # one layer per keyframe
    "blend=cameras,parallax=on",  # the defaults now: one layer per keyframe and camera
    "blend=cameras,parallax=on,carve=same_time",
    "blend=cameras,parallax=on,carve=all",
    "blend=cameras,parallax=on,search=off",
    "blend=cameras,parallax=on,head=off",  # P ablated: every pixel's default surfel
]
CARVES = ("off", "same_time", "all")
OBJECTS = ("off", "search", "rigid")
MATCHES = ("off", "medium", "fast", "ultrafast")


@dataclass(frozen=True)
class Variant:
    name: str
    blend: str = DEFAULT_BLEND
    carve: str = "off"
    search: bool = True
    region: int | None = None  # LiftConfig.min_dynamic_region; None: the default
    bonus: float | None = None  # MotionSearchConfig.static_bonus; None: the default
    unseen: bool | None = None  # MotionSearchConfig.unseen_static; None: the default
    unseen_px: float | None = None  # MotionSearchConfig.unseen_residual_px; None: the default
    photo: bool | None = None  # LiftConfig.photometric_check; None: the default
    parallax: bool | None = None  # LiftConfig.epipolar_static; None: the default
    head: bool = True  # InferenceOptions.gaussian_head: P's predictions (False: default surfels)
    match: str | None = None  # InferenceOptions.match: "off" or a DIS preset; None: the default
    windows: tuple[float, ...] | None = None  # MatchedDepthConfig.sigmas; None: the default
    guide: str | None = None  # MatchedDepthConfig.guide
    levels: str | None = None  # MatchedDepthConfig.levels
    passes: int | None = None  # MatchedDepthConfig.passes
    mscale: float | None = None  # MatchedDepthConfig.scale
    pmatch: str | None = None  # MatchedDepthConfig.prior_preset: the fallback's DIS preset
    fdisp: float | None = None  # MatchedDepthConfig.fallback_dispersion (0: every camera matched again)
    mout: float | None = None  # MatchedDepthConfig.prior_outlier (-1: off); None: the default
    mmove: bool | None = None  # MatchedDepthConfig.refused_motion; None: the default
    rig: bool | None = None  # MatchedDepthConfig.cross: the stereo across the rig on (the default) or off
    fuse: str | None = None  # MatchedDepthConfig.fuse
    replace: bool | None = None  # MatchedDepthConfig.replace: determined pixels take the triangulated depth
    pdepth: str | None = None  # LiftConfig.epipolar_depth
    ptex: float | None = None  # LiftConfig.epipolar_min_texture
    objects: str | None = (
        None  # InferenceOptions.objects: "off", or tracked with "search" or "rigid" flow elsewhere; None: the default
    )
    residual: bool = True  # InferenceOptions.use_residual (False: static-only)
    osplit: bool | None = None  # ObjectMotionConfig.split; None: the default
    omotion: float | None = None  # ObjectMotionConfig.min_motion; None: the default
    odetect: str | None = None  # ObjectMotionConfig.detect: "rigid" or "fallback"; None: the default
    ounique: float | None = None  # ObjectMotionConfig.unique (a ratio in (0, 1]); None: the default
    omax: float | None = None  # ObjectMotionConfig.max_motion (a share of the width in (0, 1]); None: the default
    omargin: int | None = None  # ObjectMotionConfig.margin_x (pixels); None: the default
    oscales: tuple[float, ...] | None = None  # ObjectMotionConfig.scales; None: the default
    olocal: int | None = None  # ObjectMotionConfig.local_px; None: the default
    ocoarse: bool | None = None  # ObjectMotionConfig.coarse; None: the default
    owidth: int | None = None  # ObjectMotionConfig.max_width (0: off, at the image's size); None: the default
    oland: float | None = None  # ObjectMotionConfig.landing (-1: off); None: the default
    merge: float | None = None  # BlockMerge.color_range (gaussians/parsimony.py); -1: no merge; None: the default
    mtest: str | None = None  # BlockMerge.color_test: "detail" or "range"; None: the default
    mfit: int | None = None  # BlockMerge.fit_colors (0: per-pixel solve, block means); None: the default
    mbudget: float | None = None  # BlockMerge.budget (a share of the per-pixel Gaussians); None: the default
    dedupe: bool | None = None  # InferenceOptions.dedupe on (KeyframeDedupe()) or off; None: the default
    edges: int | None = None  # InferenceOptions.edges: EdgeSharpen(radius=edges), 0: off; None: the default
    esigma: float | None = None  # EdgeSharpen.sigma; None: the default
    mdepth: str | None = None  # InferenceOptions.moving_depth: "matched" or "prior"; None: the default
    robj: bool | None = None  # InferenceOptions.rig_objects on (RigObjectConfig()) or off; None: the default
    rratio: float | None = None  # RigObjectConfig.ratio (with robj on); None: its default
    rseen: str | None = None  # RigObjectConfig.seen, "front" or "depth" (with robj on); None: its default
    rleave: float | None = None  # RigObjectConfig.leaving, a share in [0, 1] (with robj on); None: its default

    def options(self, base):
        from drivingscene.gaussians.visibility import CarveConfig
        from drivingscene.methods.cross_camera import CrossCameraConfig
        from drivingscene.methods.matched_depth import MatchedDepthConfig

        carve = None if self.carve == "off" else CarveConfig(voters=self.carve)
        match = base.match
        if self.match == "off":
            match = None
        elif self.match is not None:
            match = replace(match or MatchedDepthConfig(), preset=self.match)
        if match is not None:
            changes = (
                ("sigmas", self.windows),
                ("guide", self.guide),
                ("levels", self.levels),
                ("passes", self.passes),
                ("scale", self.mscale),
                ("prior_preset", self.pmatch),
                ("fallback_dispersion", self.fdisp),
                ("fuse", self.fuse),
                ("replace", self.replace),
            )
            for name, value in changes:
                if value is not None:
                    match = replace(match, **{name: value})
            if self.rig is not None:
                match = replace(match, cross=CrossCameraConfig() if self.rig else None)
            if self.mout is not None:  # -1: off (None in the config)
                match = replace(match, prior_outlier=None if self.mout < 0 else self.mout)
            if self.mmove is not None:
                match = replace(match, refused_motion=self.mmove)
        lift = base.lift
        if self.region is not None:
            lift = replace(lift, min_dynamic_region=self.region)
        if self.photo is not None:
            lift = replace(lift, photometric_check=self.photo)
        if self.parallax is not None:
            lift = replace(lift, epipolar_static=self.parallax)
        if self.pdepth is not None:
            lift = replace(lift, epipolar_depth=self.pdepth)
        if self.ptex is not None:
            lift = replace(lift, epipolar_min_texture=self.ptex)
        search = _with(
            base.search if self.search else None,
            static_bonus=self.bonus, unseen_static=self.unseen, unseen_residual_px=self.unseen_px,
        )  # fmt: skip
        from drivingscene.methods.object_motion import ObjectMotionConfig

        chosen = {
            "split": self.osplit,
            "min_motion": self.omotion,
            "detect": self.odetect,
            "unique": self.ounique,
            "max_motion": self.omax,
            "margin_x": self.omargin,
            "scales": self.oscales,
            "local_px": self.olocal,
            "coarse": self.ocoarse,
        }  # None: the default
        chosen = {k: v for k, v in chosen.items() if v is not None}
        if self.owidth is not None:  # 0: off (None in the config)
            chosen["max_width"] = self.owidth or None
        if self.oland is not None:  # -1: off (None in the config)
            chosen["landing"] = None if self.oland < 0 else self.oland
        objects = base.objects
        if self.objects == "off":
            objects = None
        elif self.objects is not None:
            objects = replace(objects or ObjectMotionConfig(), elsewhere=self.objects, **chosen)
        elif objects is not None and chosen:
            objects = replace(objects, **chosen)
        from drivingscene.gaussians.parsimony import BlockMerge, KeyframeDedupe

        merge = base.merge
        if self.merge is not None:
            merge = None if self.merge < 0 else replace(merge or BlockMerge(), color_range=self.merge)
        merge = _with(merge, color_test=self.mtest, fit_colors=self.mfit, budget=self.mbudget)
        dedupe = base.dedupe if self.dedupe is None else (KeyframeDedupe() if self.dedupe else None)
        from drivingscene.methods.depth_edges import EdgeSharpen

        edges = base.edges
        if self.edges is not None:
            edges = None if self.edges == 0 else replace(edges or EdgeSharpen(), radius=self.edges)
        edges = _with(edges, sigma=self.esigma)
        from drivingscene.methods.rig_objects import RigObjectConfig

        rig = base.rig_objects if self.robj is None else (RigObjectConfig() if self.robj else None)
        rig = _with(rig, ratio=self.rratio, seen=self.rseen, leaving=self.rleave)
        return replace(
            base, carve=carve, search=search, lift=lift, gaussian_head=self.head, match=match, objects=objects,
            use_residual=self.residual, merge=merge, dedupe=dedupe, edges=edges,
            moving_depth=base.moving_depth if self.mdepth is None else self.mdepth, rig_objects=rig,
        )  # fmt: skip


def _with(config, **values):
    """``config`` with the fields of ``values`` that are not None replaced (a variant's choices);
    None stays None (the step is off)."""
    chosen = {name: value for name, value in values.items() if value is not None}
    return replace(config, **chosen) if config is not None and chosen else config


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _cell(value: float, decimals: int = 2) -> str:
    """A table cell: ``decimals`` decimals, or "n/a" where the pairs have no such figure (a real scene's moving pixels)."""
    return "n/a" if np.isnan(value) else f"{value:.{decimals}f}"


def _nanmean(values: list[float]) -> float:
    finite = [v for v in values if not np.isnan(v)]
    return float(np.mean(finite)) if finite else float("nan")


def sign_test(wins: int, losses: int) -> float:
    """Two-sided exact sign test: the probability of a split at least this uneven by chance (ties dropped)."""
    n = wins + losses
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, i) for i in range(min(wins, losses) + 1)) / 2**n
    return min(1.0, 2 * tail)


def _sign(values: list[float] | None, reference: list[float] | None) -> str:
    """ "wins / pairs (p ...)" of ``values`` against ``reference`` pair by pair; "–" without both."""
    if values is None or reference is None:
        return "–"
    pairs = [(a, b) for a, b in zip(values, reference) if not (np.isnan(a) or np.isnan(b))]
    if not pairs:
        return "–"
    wins, losses = sum(a > b for a, b in pairs), sum(a < b for a, b in pairs)
    return f"{wins} / {len(pairs)} (p {sign_test(wins, losses):.3f})"


def parse_variant(text: str) -> Variant:
    """A `Variant` from ``key=value,...`` with keys blend, carve, search, photo, parallax, rig, pdepth, ptex, head, match,
    windows, guide, levels, passes, mscale, pmatch, fdisp, mout, mmove, fuse, replace, bonus, region, unseen, unseenpx, objects,
    residual, osplit, omotion, odetect, ounique, omax, omargin, oscales, olocal, ocoarse, owidth, oland, robj, rratio, rseen, rleave, merge, mtest, mfit, mbudget, dedupe, edges, esigma, mdepth."""
    from drivingscene.gaussians.timing import BLEND_MODES
    from drivingscene.methods.feedforward import MOVING_DEPTHS
    from drivingscene.methods.matched_depth import FUSES, GUIDES, LEVELS
    from drivingscene.models.lift import EPIPOLAR_DEPTHS

    values: dict = {"name": text}
    for item in filter(None, text.split(",")):
        key, sep, value = item.partition("=")
        if key == "blend" and value in BLEND_MODES:
            values["blend"] = value
        elif key == "carve" and value in CARVES:
            values["carve"] = value
        elif key == "search" and value in ("on", "off"):
            values["search"] = value == "on"
        elif key == "region" and value.isdigit():
            values["region"] = int(value)
        elif key == "unseen" and value in ("static", "search"):
            values["unseen"] = value == "static"
        elif key == "unseenpx" and _is_number(value) and float(value) >= 0:
            values["unseen_px"] = float(value)
        elif key == "objects" and value in OBJECTS:
            values["objects"] = value
        elif key == "omotion" and _is_number(value) and float(value) >= 0:
            values["omotion"] = float(value)
        elif key == "odetect" and value in ("rigid", "fallback"):
            values["odetect"] = value
        elif key == "ounique" and _is_number(value) and 0 < float(value) <= 1:
            values["ounique"] = float(value)
        elif key == "omax" and _is_number(value) and 0 < float(value) <= 1:
            values["omax"] = float(value)
        elif key == "omargin" and value.isdigit():
            values["omargin"] = int(value)
        elif key == "oland" and (value == "off" or (_is_number(value) and float(value) >= 0)):
            values["oland"] = -1.0 if value == "off" else float(value)
        elif key == "olocal" and value.isdigit():
            values["olocal"] = int(value)
        elif key == "ocoarse" and value in ("on", "off"):
            values["ocoarse"] = value == "on"
        elif key == "owidth" and (value == "off" or (value.isdigit() and int(value) >= 16)):
            values["owidth"] = 0 if value == "off" else int(value)
        elif key == "robj" and value in ("on", "off"):
            values["robj"] = value == "on"
        elif key == "rratio" and _is_number(value) and float(value) > 0:
            values["rratio"] = float(value)
        elif key == "rseen" and value in ("front", "depth"):
            values["rseen"] = value
        elif key == "rleave" and _is_number(value) and 0 <= float(value) <= 1:
            values["rleave"] = float(value)
        elif key == "oscales" and value and all(_is_number(a) and float(a) > 0 for a in value.split("+")):
            values["oscales"] = tuple(float(a) for a in value.split("+"))
        elif key == "merge" and (value == "off" or (_is_number(value) and float(value) >= 0)):
            values["merge"] = -1.0 if value == "off" else float(value)
        elif key == "mtest" and value in ("detail", "range"):
            values["mtest"] = value
        elif key == "mfit" and value.isdigit():
            values["mfit"] = int(value)
        elif key == "edges" and (value == "off" or (value.isdigit() and int(value) >= 1)):
            values["edges"] = 0 if value == "off" else int(value)
        elif key == "mdepth" and value in MOVING_DEPTHS:
            values["mdepth"] = value
        elif key == "esigma" and _is_number(value) and float(value) > 0:
            values["esigma"] = float(value)
        elif key == "mbudget" and _is_number(value) and 0 < float(value) <= 1:
            values["mbudget"] = float(value)
        elif key in ("photo", "parallax", "head", "rig", "replace", "residual", "osplit", "dedupe") and value in ("on", "off"):
            values[key] = value == "on"
        elif key == "match" and value in MATCHES:
            values["match"] = value
        elif key == "ptex" and _is_number(value) and float(value) >= 0:
            values["ptex"] = float(value)
        elif key == "pdepth" and value in EPIPOLAR_DEPTHS:
            values["pdepth"] = value
        elif key == "guide" and value in GUIDES:
            values["guide"] = value
        elif key == "fuse" and value in FUSES:
            values["fuse"] = value
        elif key == "levels" and value in LEVELS:
            values["levels"] = value
        elif key == "mscale" and _is_number(value) and 0 < float(value) <= 1:
            values["mscale"] = float(value)
        elif key == "pmatch" and value in MATCHES[1:]:
            values["pmatch"] = value
        elif key == "mmove" and value in ("on", "off"):
            values["mmove"] = value == "on"
        elif key == "mout" and (value == "off" or (_is_number(value) and float(value) > 0)):
            values["mout"] = -1.0 if value == "off" else float(value)
        elif key == "fdisp" and _is_number(value) and float(value) >= 0:
            values["fdisp"] = float(value)
        elif key == "passes" and value.isdigit() and int(value) >= 1:
            values["passes"] = int(value)
        elif key == "windows" and value and all(_is_number(w) and float(w) > 0 for w in value.split("+")):
            values["windows"] = tuple(float(w) for w in value.split("+"))
        elif key == "bonus" and _is_number(value) and float(value) >= 0:
            values["bonus"] = float(value)
        else:
            raise InputError(
                f"--variant: expected blend={'|'.join(BLEND_MODES)}, carve={'|'.join(CARVES)}, search=on|off, "
                f"photo=on|off, parallax=on|off, rig=on|off, replace=on|off, residual=on|off, merge=off|RANGE, mtest=detail|range, mfit=N, mbudget=SHARE (0, 1], dedupe=on|off, edges=off|RADIUS, esigma=COLOUR, mdepth={'|'.join(MOVING_DEPTHS)}, objects={'|'.join(OBJECTS)}, osplit=on|off, omotion=PX, odetect=rigid|fallback, ounique=RATIO (0, 1], omax=SHARE (0, 1], omargin=PX, oscales=A+A..., olocal=PX, ocoarse=on|off, owidth=off|PX, oland=off|COST, robj=on|off, rratio=RATIO, rseen=front|depth, rleave=SHARE [0, 1], pdepth={'|'.join(EPIPOLAR_DEPTHS)}, ptex=LUMA, head=on|off, match={'|'.join(MATCHES)}, windows=PX+PX..., guide={'|'.join(GUIDES)}, "
                f"levels={'|'.join(LEVELS)}, fuse={'|'.join(FUSES)}, passes=N, mscale=FRACTION, pmatch={'|'.join(MATCHES[1:])}, fdisp=MAD (>= 0), mout=off|LOG (> 0), mmove=on|off, bonus=LUMA (>= 0), region=PIXELS, unseen=static|search or unseenpx=PIXELS (>= 0), found {item!r}"
            )
    return Variant(**values)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--data", type=Path, nargs="+", required=True, help="validation pair folders or single scene files (each reported apart)"
    )
    p.add_argument("--count", type=int, default=6, help="pairs per folder (default 6)")
    p.add_argument("--weights", type=Path, default=None, help="model (default: the shipped weights)")
    p.add_argument(
        "--variant",
        action="extend",
        nargs="+",
        default=None,
        metavar="KEY=VALUE,...",
        help="variants to score, space-separated, each a comma-separated list of choices ('' the defaults; default: a built-in list)",
    )
    p.add_argument("--device", default="cpu", help="the networks on cpu (default), cuda or cuda:N")
    p.add_argument("-o", "--out", type=Path, default=None, help="write the markdown report here (default: print it)")


def score_variant(model, pair, variant: Variant) -> dict[str, float]:
    from drivingscene.eval.reconstruction import score_depth, score_flow, score_input_views, score_novel_views
    from drivingscene.methods.feedforward import InferenceOptions, reconstruct

    tic = time.perf_counter()
    recon = reconstruct(model, pair, variant.options(InferenceOptions()))
    seconds = time.perf_counter() - tic
    out = {"inputs": score_input_views(recon, pair, variant.blend)["psnr_input"], "seconds": seconds}
    out["dynamic"] = float(recon.visible().dynamic.float().mean())
    out["gaussians"] = float(len(recon.visible()))
    if pair.gt_depth is not None:  # as docs/results.md and docs/real-data.md score it
        depth = score_depth(recon, pair)
        out["abs_rel"] = depth["depth_abs_rel"]
        out["abs_rel_dyn"] = depth.get("depth_abs_rel_dyn", float("nan"))
    if pair.num_eval:
        novel = score_novel_views(recon, pair, None, variant.blend)
        out["psnr"], out["psnr_dyn"] = novel["psnr"], novel.get("psnr_dyn", float("nan"))
    flow = score_flow(recon, pair)
    out["epe_dyn"], out["epe_static"] = flow.get("epe_dyn_total", float("nan")), flow.get("epe_static_total", float("nan"))
    out["epe_dyn_applied"] = flow.get("epe_dyn_applied", float("nan"))
    out["epe_static_applied"] = flow.get("epe_static_applied", float("nan"))
    return out


def score_blend(pair) -> dict[str, float]:
    """The baseline without geometry: the two keyframes blended by time, scored as the variants."""
    from drivingscene.eval.baselines import blend_frames
    from drivingscene.eval.reconstruction import score_frames

    scores = score_frames(blend_frames(pair), pair, None)
    return {"psnr": scores["psnr"], "psnr_dyn": scores.get("psnr_dyn", float("nan"))}


def run(args: argparse.Namespace) -> int:
    from drivingscene.data.frame_pair import load_frame_pair
    from drivingscene.methods.devices import gpu_name, resolve_device
    from drivingscene.methods.feedforward import load_model
    from drivingscene.train.data import pair_files

    variants = [parse_variant(v) for v in (args.variant or DEFAULT_VARIANTS)]  # errors before any work
    device = resolve_device(args.device)
    model = load_model(args.weights, device=device)
    sections = []
    for folder in args.data:
        files = pair_files(folder, args.count)
        pairs = [load_frame_pair(f) for f in files]
        moving = np.mean([p.gt_dynamic.mean() for p in pairs if p.gt_dynamic is not None] or [np.nan])
        rows = []
        first = None  # the first variant's moving-pixel PSNR per pair: the others' pair-by-pair reference
        for variant in variants:
            scores = [score_variant(model, p, variant) for p in pairs]
            keys = dict.fromkeys(k for s in scores for k in s)  # a pair without eval frames has no psnr
            mean = {k: _nanmean([s.get(k, np.nan) for s in scores]) for k in keys}
            per_pair = [s.get("psnr_dyn", np.nan) for s in scores]
            rows.append(
                f"| {variant.name or '(defaults)'} | {mean['inputs']:.2f} | {mean.get('psnr', np.nan):.2f} "
                f"| {_cell(mean.get('psnr_dyn', np.nan))} | {_sign(per_pair, first)} "
                f"| {_cell(mean.get('epe_dyn', np.nan))} / {_cell(mean.get('epe_static', np.nan))} "
                f"| {_cell(mean.get('epe_dyn_applied', np.nan))} / {_cell(mean.get('epe_static_applied', np.nan))} "
                f"| {100 * mean['dynamic']:.1f} % | {mean['gaussians'] / 1000:.0f} | {mean.get('abs_rel', np.nan):.3f} "
                f"/ {_cell(mean.get('abs_rel_dyn', np.nan), 3)} | {np.median([s['seconds'] for s in scores]):.2f} |"
            )
            first = per_pair if first is None else first
            print(f"{folder}: {rows[-1]}", flush=True)
        with_eval = [p for p in pairs if p.num_eval]
        if with_eval:
            blend = [score_blend(p) for p in with_eval]
            per_pair = [b["psnr_dyn"] for b in blend] if len(with_eval) == len(pairs) else None
            rows.append(
                f"| *keyframes blended (no geometry)* | – | {_nanmean([b['psnr'] for b in blend]):.2f} "
                f"| {_cell(_nanmean([b['psnr_dyn'] for b in blend]))} | {_sign(per_pair, first)} | – | – | – | – | – | – |"
            )
        motion = "no ground-truth motion" if np.isnan(moving) else f"moving pixels in the ground truth: {100 * moving:.1f} %"
        sections += [
            f"### {folder} ({len(pairs)} {'pair' if len(pairs) == 1 else 'pairs'}; {motion})",
            "",
            "| variant | input views PSNR | intermediate PSNR | intermediate PSNR, moving | moving: pairs above the first row (sign test) "
            "| flow EPE moving / static (px) | flow the Gaussians follow: EPE moving / static (px) | dynamic Gaussians "
            "| Gaussians (thousands) | depth AbsRel: all / moving objects | s / pair |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
            *rows,
            "",
        ]
    cmd = "drivingscene bench choices --data " + " ".join(str(d) for d in args.data) + f" --count {args.count}"
    cmd += " --variant " + " ".join(f"'{v}'" for v in args.variant) if args.variant else ""
    cmd += f" --weights {args.weights}" if args.weights else ""
    cmd += f" --device {args.device}" if device.type != "cpu" else ""
    text = "\n".join(
        [
            "# Inference and rendering choices on validation pairs",
            "",
            f"Measured with `{cmd}` on {machine_description()}{gpu_name(device)}, {time.strftime('%Y-%m-%d')}. Means over the pairs (seconds: "
            "the median); PSNR in dB over the pixels that see the world. Flow EPE: rigid + the residual flow as R and the "
            "search propose it; the flow the Gaussians follow: rigid + the residual where a pixel's Gaussian moves.",
            "",
            *sections,
        ]
    )
    write_report(text, args.out, announce=False)
    return 0
