"""The report of ``drivingscene bench views``: per-image records summarised into rows, the model
against the mesh baseline per viewpoint class and magnification, and the markdown page.

The report is a JSON-ready dict (``FORMAT``/``VERSION``); the markdown and the charts
(`views_charts`) are drawn from it alone.
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import asdict

from drivingscene.bench.views_cameras import CLASSES
from drivingscene.bench.views_run import BICUBIC, CLASSICAL, MESH, MODEL, ORACLE, PER_PIXEL, ViewRecord

FORMAT = "drivingscene/bench-views"
VERSION = 1
METHOD_ORDER = (MODEL, PER_PIXEL, MESH, CLASSICAL, ORACLE, BICUBIC)
METRICS = ("psnr", "ssim", "lpips", "holes", "psnr_down", "ssim_down", "psnr_seen")


def _mean(values: list) -> float | None:
    kept = [v for v in values if v is not None and math.isfinite(v)]
    return sum(kept) / len(kept) if kept else None


def method_rank(name: str) -> int:
    return METHOD_ORDER.index(name) if name in METHOD_ORDER else len(METHOD_ORDER)


def _view_rank(viewpoint: str, magnification: int) -> tuple:
    return (CLASSES.index(viewpoint) if viewpoint in CLASSES else len(CLASSES), magnification)


def summarise(records: list[ViewRecord]) -> list[dict]:
    """Mean of every metric per (set, viewpoint, magnification, t, method) over pairs and cameras,
    with the number of images and pairs; NaN and missing values are left out of a mean."""
    groups: dict[tuple, list[ViewRecord]] = defaultdict(list)
    for r in records:
        groups[(r.set, r.viewpoint, r.magnification, r.t, r.method)].append(r)
    rows = []
    for (set_, viewpoint, k, t, method), rs in groups.items():
        row = {
            "set": set_,
            "viewpoint": viewpoint,
            "magnification": k,
            "t": t,
            "method": method,
            "images": len(rs),
            "pairs": len({r.pair for r in rs}),
        }
        row.update({m: _mean([getattr(r, m) for r in rs]) for m in METRICS})
        rows.append(row)
    return sorted(
        rows,
        key=lambda r: (r["set"], _view_rank(r["viewpoint"], r["magnification"]), r["t"], method_rank(r["method"]), r["method"]),
    )


def find(rows: list[dict], set_: str, viewpoint: str, k: int, t: float, method: str) -> dict | None:
    return next(
        (
            r
            for r in rows
            if (r["set"], r["viewpoint"], r["magnification"], r["t"], r["method"]) == (set_, viewpoint, k, t, method)
        ),
        None,
    )


def verdicts(rows: list[dict]) -> list[dict]:
    """Per procedural (viewpoint, magnification): whether the model's mean PSNR is above the mesh
    baseline's at every time scored (``beats``), the margins, and whether SSIM (higher) and ST-LPIPS
    (lower) agree at every time."""
    keys = sorted({(r["viewpoint"], r["magnification"]) for r in rows if r["set"] == "procedural"}, key=lambda v: _view_rank(*v))
    out = []
    for viewpoint, k in keys:
        times = sorted(
            {r["t"] for r in rows if r["set"] == "procedural" and (r["viewpoint"], r["magnification"]) == (viewpoint, k)}
        )
        pairs = [
            (find(rows, "procedural", viewpoint, k, t, MODEL), find(rows, "procedural", viewpoint, k, t, MESH)) for t in times
        ]
        pairs = [(a, b) for a, b in pairs if a and b and a["psnr"] is not None and b["psnr"] is not None]
        if not pairs:
            continue

        def agree(metric: str, higher: bool, pairs=pairs) -> bool | None:
            got = [(a[metric], b[metric]) for a, b in pairs if a[metric] is not None and b[metric] is not None]
            return None if not got else all((x > y) if higher else (x < y) for x, y in got)

        out.append(
            {
                "viewpoint": viewpoint,
                "magnification": k,
                "times": [a["t"] for a, _ in pairs],
                "model_psnr": [a["psnr"] for a, _ in pairs],
                "mesh_psnr": [b["psnr"] for _, b in pairs],
                "beats": all(a["psnr"] > b["psnr"] for a, b in pairs),
                "ssim_agrees": agree("ssim", True),
                "lpips_agrees": agree("lpips", False),
            }
        )
    return out


def build_report(records: list[ViewRecord], flying: dict, meta: dict) -> dict:
    """The report dict: ``meta`` (command, machine, settings, ...) plus rows, verdicts and flying
    shares (``flying``: set -> pair -> method -> (flying, counted))."""
    rows = summarise(records)
    verdict = verdicts(rows)
    pooled: dict[str, dict[str, list[int]]] = {}
    for set_, by_pair in flying.items():
        for per_method in by_pair.values():
            for method, (f, n) in per_method.items():
                acc = pooled.setdefault(set_, {}).setdefault(method, [0, 0])
                acc[0] += f
                acc[1] += n
    flying_rows = [
        {"set": s, "method": m, "flying": f, "counted": n, "share": f / n if n else None}
        for s, ms in pooled.items()
        for m, (f, n) in sorted(ms.items(), key=lambda x: method_rank(x[0]))
    ]
    return {
        "format": FORMAT,
        "version": VERSION,
        **meta,
        "rows": rows,
        "verdicts": verdict,
        "floor_holds": bool(verdict) and all(v["beats"] for v in verdict),
        "flying": flying_rows,
        "images": [{k: _finite(v) for k, v in asdict(r).items()} for r in records],
    }


def _finite(value):
    """``value`` with non-finite floats as None (strict JSON)."""
    return None if isinstance(value, float) and not math.isfinite(value) else value


def _f(value, fmt: str) -> str:
    return "–" if value is None or (isinstance(value, float) and not math.isfinite(value)) else fmt.format(value)


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows]) + "\n"


def _k_label(viewpoint: str, k: int) -> str:
    return viewpoint if k == 1 else f"{viewpoint} {k}x"


def _wide_table(rows: list[dict], set_: str, keys: list[tuple[str, int]], times: list[float], first: str) -> str:
    """One row per (viewpoint, method), a column per metric and time; the best non-oracle PSNR of
    each (viewpoint, time) in bold."""
    metrics = (
        ("psnr", "PSNR", "{:.2f}"),
        ("ssim", "SSIM", "{:.3f}"),
        ("lpips", "ST-LPIPS", "{:.3f}"),
        ("holes", "holes", "{:.1%}"),
        ("psnr_seen", "PSNR seen", "{:.2f}"),
    )
    header = [first, "method"] + [f"{label} t={t:g}" for _, label, _ in metrics for t in times]
    out = []
    for viewpoint, k in keys:
        methods = sorted(
            {r["method"] for r in rows if (r["set"], r["viewpoint"], r["magnification"]) == (set_, viewpoint, k)}, key=method_rank
        )
        best = {}
        for t in times:
            cands = [find(rows, set_, viewpoint, k, t, m) for m in methods if m != ORACLE]
            vals = [c["psnr"] for c in cands if c and c["psnr"] is not None]
            best[t] = max(vals) if vals else None
        for m in methods:
            cells = [_k_label(viewpoint, k), m]
            for key, _, fmt in metrics:
                for t in times:
                    r = find(rows, set_, viewpoint, k, t, m)
                    text = _f(r and r[key], fmt)
                    if key == "psnr" and r and m != ORACLE and r["psnr"] is not None and r["psnr"] == best[t]:
                        text = f"**{text}**"
                    cells.append(text)
            out.append(cells)
    return _table(header, out)


def _verdict_lines(report: dict) -> str:
    lines = []
    for v in report["verdicts"]:
        model = " / ".join(_f(x, "{:.2f}") for x in v["model_psnr"])
        mesh = " / ".join(_f(x, "{:.2f}") for x in v["mesh_psnr"])
        times = " / ".join(f"t={t:g}" for t in v["times"])
        word = "**beats**" if v["beats"] else "**does not beat**"
        extra = ", ".join(
            f"{name}: {'agrees' if ok else 'disagrees'}"
            for name, ok in (("SSIM", v["ssim_agrees"]), ("ST-LPIPS", v["lpips_agrees"]))
            if ok is not None
        )
        lines.append(
            f"- {_k_label(v['viewpoint'], v['magnification'])}: the model {word} the mesh baseline, PSNR {model} against {mesh} dB ({times}; {extra})."
        )
    failed = [_k_label(v["viewpoint"], v["magnification"]) for v in report["verdicts"] if not v["beats"]]
    if report["floor_holds"]:
        lines.append(
            "\n**The floor holds**: the model's PSNR is above the mesh baseline's at every viewpoint class and magnification, at every time."
        )
    else:
        lines.append(
            f"\n**The floor does not hold**: the model is not above the mesh baseline at {', '.join(failed) or 'any scored viewpoint'}."
        )
    return "\n".join(lines) + "\n"


def _real_table(rows: list[dict], pairs: list[str]) -> str:
    header = [
        "magnification",
        "method",
        "PSNR vs bicubic",
        "SSIM vs bicubic",
        "ST-LPIPS vs bicubic",
        "PSNR area-down vs input",
        "SSIM area-down vs input",
        "holes",
    ]
    out = []
    for k in sorted({r["magnification"] for r in rows if r["set"] == "real"}):
        for m in sorted({r["method"] for r in rows if r["set"] == "real" and r["magnification"] == k}, key=method_rank):
            r = find(rows, "real", "rig", k, 0.0, m)
            down = (_f(r["psnr_down"], "{:.2f}"), _f(r["ssim_down"], "{:.3f}")) if k > 1 else ("(= left)", "(= left)")
            out.append(
                [
                    f"{k}x",
                    m,
                    _f(r["psnr"], "{:.2f}"),
                    _f(r["ssim"], "{:.3f}"),
                    _f(r["lpips"], "{:.3f}"),
                    *down,
                    _f(r["holes"], "{:.1%}"),
                ]
            )
    return _table(header, out)


def _flying_table(report: dict) -> str:
    sets = sorted({f["set"] for f in report["flying"]})
    methods = sorted({f["method"] for f in report["flying"]}, key=method_rank)
    header = ["method"] + [f"flying share, {s}" for s in sets] + [f"Gaussians counted, {s}" for s in sets]
    rows = []
    for m in methods:
        got = {f["set"]: f for f in report["flying"] if f["method"] == m}
        rows.append(
            [m]
            + [_f(got[s]["share"], "{:.1%}") if s in got else "–" for s in sets]
            + [f"{got[s]['counted']:,}" if s in got else "–" for s in sets]
        )
    return _table(header, rows)


def markdown(report: dict, charts: dict[str, str]) -> str:
    """The markdown page; ``charts`` maps a chart key to its path relative to the page."""
    s = report["settings"]
    rows = report["rows"]

    def link(key: str, alt: str) -> str:
        return f"![{alt}]({charts[key]})\n" if key in charts else ""

    lines = [
        "# Quality where the viewer's user looks\n",
        f"Made by `{report['command']}` on {report['machine']}; networks in {report['precision']}; {report['created']}; "
        f"the run took {report['run_seconds'] / 60:.1f} min.\n",
        "Every method is rendered from the viewpoints a user of the viewer takes and scored against the procedural generator's "
        "ground truth rendered at the same poses, sizes and times (`drivingscene.synth.novel_view`: the scene rebuilt from its seed, "
        "finished like the input images). Viewpoints start from each rig camera at normalised time t (ego pose interpolated between "
        f"the keyframes, as the viewer does): *rig* (the pose itself; at t=0 the input views), *side 1 m* / *side 2 m* (moved along the "
        f"ego's lateral axis, {s['side']}), *up 2 m*, *up 10 m, 45° down* (moved up, then pitched down about the camera's x axis), "
        f"and the viewer's default *overview* (chase view 28 m back, pitch -0.45 rad, target 10 m ahead, 60° fov; one camera at "
        f"{s['overview_size'][1]}x{s['overview_size'][0]}). Magnification k renders the rig pose at k times the input size with the "
        "pixel grid refined in place (f' = k f, c' = (c + 0.5) k - 0.5); at t=0 the input upsampled bicubically is scored too.\n",
        f"PSNR, SSIM and ST-LPIPS (alex; shift-tolerant LPIPS, not the original) per image, then averaged over pairs and cameras. "
        f"{s['lpips_note']} Scored pixels: the pair's `valid_mask` at rig poses (nearest-neighbour upsampled), every pixel elsewhere. "
        f"*holes*: the share of pixels with true depth (not sky) whose accumulated alpha (for the mesh: coverage) is below 0.95. "
        f"*PSNR seen*: PSNR over the pixels with true depth that the oracle covers (alpha at least 0.95), i.e. surfaces some input "
        f"image saw, the same pixels for every method: what a method makes of what was seen, without what nobody saw. "
        f'Gaussians render with the default "cameras" blend and rasterizer settings, over their reconstruction\'s background: the '
        f"sky model, and below the horizon the ground (the road's colour where a ray from a camera above the road plane descends; "
        f"`drivingscene.render.sky.with_ground`).\n",
        f"The mesh baseline (`drivingscene.methods.depth_mesh`): the model's per-camera depth as one triangle mesh per input image, "
        f"vertices at pixel centres, coloured by the image; a triangle is dropped where its source camera sees it within "
        f"{90 - s['mesh_max_angle_deg']:g}° of edge-on (normal more than {s['mesh_max_angle_deg']:g}° from the ray: depth edges); vertices move "
        "with the model's Gaussian of the same pixel; the images' meshes are blended with the Gaussians' \"cameras\" weights over the model's sky and ground.\n",
    ]
    proc = [r for r in rows if r["set"] == "procedural"]
    if proc:
        times = sorted({r["t"] for r in proc})
        lines.append(f"## Procedural pairs ({s['procedural']})\n")
        lines.append("### The acceptance floor: the model against the mesh baseline\n")
        lines.append(_verdict_lines(report))
        lines.append("### Viewpoint classes\n")
        lines.append(link("classes", "PSNR, SSIM and ST-LPIPS per viewpoint class and method"))
        keys = sorted({(r["viewpoint"], 1) for r in proc if r["magnification"] == 1}, key=lambda v: _view_rank(*v))
        lines.append(_wide_table(rows, "procedural", keys, times, "viewpoint"))
        lines.append("### Magnification at the rig poses\n")
        lines.append(link("magnification", "PSNR against magnification per method"))
        mags = sorted({r["magnification"] for r in proc if r["viewpoint"] == "rig"})
        lines.append(_wide_table(rows, "procedural", [("rig", k) for k in mags], times, "view"))
        lines.append(link("examples", "one camera of the first pair at t=0 from every viewpoint: ground truth and each method"))
    real = [r for r in rows if r["set"] == "real"]
    if real:
        lines.append(f"## Real pairs ({s['real']})\n")
        lines.append(
            "No ground truth away from the rig: each method's render at the magnified rig pose (t=0, each camera where its image was "
            "taken) against the input upsampled "
            "bicubically, and the render area-downsampled back to the input size against the input; holes over the pixels that see "
            "the world (`valid_mask`) and are not the model's sky. Means over scenes and cameras.\n"
        )
        lines.append(_real_table(rows, s["real_names"]))
        for name, path in report.get("real_pictures", {}).items():
            lines.append(
                f"The viewer's default overview of {name} at t=0, per method: [{path}]({path}) (real frames: not for the repository).\n"
            )
    if report["flying"]:
        lines.append("## Flying Gaussians\n")
        lines.append(
            "A Gaussian is flying when its camera z in its own source image (keyframe k, camera c) is more than 5% of the true depth "
            "off the true depth at the pixel it projects to; only pixels with true depth count (procedural: the generator's depth; "
            "real: LiDAR returns). Pooled over pairs; it does not depend on the viewpoint.\n"
        )
        lines.append(_flying_table(report))
    return "\n".join(lines)
