"""``drivingscene-view SCENE --headless --out DIR``: render views and a PLY without a window.

Uses an EGL standalone context (no X server). Writes, for every requested time t:
``DIR/<camera>_t<t>.png`` for each rig camera (rig resolution times ``--scale``, exact intrinsics),
``DIR/overview_t<t>.png`` from the default chase camera, and ``DIR/gaussians_t<t0>.ply`` (standard
3DGS at the first time). Where time changes nothing (`time_changes_nothing`: a PLY of static
Gaussians, no rig), only the first time is rendered, with a note on stdout. Existing files are an
error unless ``--force``, which replaces each one atomically (a kill leaves the old file or the new
one, never none). The camera's up axis is the file's (``Loaded.info["up"]``, as in the window), so a
y-down PLY from another tool renders upright.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import numpy as np
from drivingscene_view.camera import CameraController
from drivingscene_view.export import export_ply, export_rig_views, export_view
from drivingscene_view.loader import Loaded, MissingWeightsError, open_path, reconstruct_pair
from drivingscene_view.renderer import RenderOptions
from drivingscene_view.state import SceneDoc

from drivingscene.errors import InputError
from drivingscene.gaussians.timing import LAYERED_BLENDS
from drivingscene.render.project import EPS2D

log = logging.getLogger(__name__)


def load_for_cli(path: Path, method: str, weights: Path | None) -> Loaded:
    """Open ``path``; with ``--method auto`` and no model weights, fall back to the oracle when the scene has ground truth."""
    try:
        return open_path(path, method, weights)
    except MissingWeightsError as e:
        if method != "auto" or e.pair.gt_depth is None:
            raise
        print(f"drivingscene-view: note: {e}; showing the oracle reconstruction (ground truth) instead", file=sys.stderr)
        return reconstruct_pair(e.pair, e.source, "oracle", None, lambda f, m: None)


def time_changes_nothing(doc: SceneDoc, blend: str) -> bool:
    """True when every time t renders the same images: no rig (rig views and the chase view follow
    the ego through time), no moving Gaussian, and no blend weight that changes with t ("fade" and
    "nearest" weight each keyframe by t; the layered blends weight two keyframes' layers by t, which
    cancels when one keyframe holds every Gaussian)."""
    splats = doc.splats
    if doc.num_views or splats.dynamic.any():
        return False
    return blend == "all" or (blend in LAYERED_BLENDS and len(np.unique(splats.keyframes)) <= 1)


def planned_outputs(out: Path, times: list[float], cameras: list[str], ply: bool) -> list[Path]:
    paths = [out / f"{name}_t{t:.3f}.png" for t in times for name in cameras]
    paths += [out / f"overview_t{t:.3f}.png" for t in times]
    if ply:
        paths.append(out / f"gaussians_t{times[0]:.3f}.ply")
    return paths


def run_headless(args) -> int:
    from drivingscene_view.viewport import Viewport

    from drivingscene.gl import create_offscreen_context

    loaded = load_for_cli(args.path, args.method, args.weights)
    doc = SceneDoc(loaded.recon, loaded.source, loaded.info)
    names = list(doc.recon.camera_names)
    if args.camera:
        unknown = [c for c in args.camera if c not in names]
        if unknown:
            raise InputError(f"--camera: unknown camera {unknown[0]!r}; expected one of {', '.join(names) or '(none: no rig)'}")
        names = args.camera
    times = args.time or [0.0, 0.5, 1.0]
    if len(times) > 1 and time_changes_nothing(doc, args.blend):
        print(f"{loaded.source}: static Gaussians and no rig, time changes nothing; rendering t={times[0]:.3f} only")
        times = times[:1]
    out = Path(args.out)
    existing = [p for p in planned_outputs(out, times, names, not args.no_ply) if p.exists()]
    if existing and not args.force:
        raise InputError(
            f"{existing[0]}: exists ({len(existing)} output file(s) would be overwritten); pass --force or choose another --out"
        )
    ctx = create_offscreen_context()
    viewport = Viewport(ctx)
    opts = RenderOptions(mode=args.mode, blend=args.blend, eps2d=loaded.info.get("low_pass", EPS2D))
    controller = CameraController(up=loaded.info.get("up", "z"))  # as the window does (viewer.set_loaded)
    written = []
    try:
        for t in times:
            if names:
                written += export_rig_views(viewport, doc, t, opts, out, names=names, overwrite=args.force, scale=args.scale)
            controller.reset(doc.recon, t, doc.splats.means_at(t))
            cam = controller.view(doc.recon, t, *args.size)
            written.append(export_view(viewport, doc, cam, t, opts, out / f"overview_t{t:.3f}.png", overwrite=args.force))
        if not args.no_ply:
            written.append(export_ply(doc, out / f"gaussians_t{times[0]:.3f}.ply", "3dgs", times[0], overwrite=args.force))
    finally:
        viewport.close()
        ctx.release()
    stats = doc.stats()
    print(
        f"{loaded.source}: {stats['total']} Gaussians ({stats['dynamic']} dynamic), method {doc.info.get('method')}; "
        f"wrote {len(written)} files to {out}"
    )
    return 0
