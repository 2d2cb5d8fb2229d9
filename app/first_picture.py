"""Time to the first picture in the window: ``python -m drivingscene_view.first_picture SCENE [--runs N]``
(needs a display: ``xvfb-run -s "-screen 0 1600x900x24" python -m drivingscene_view.first_picture
assets/demo_scene.npz``). Prints a Markdown table.

From ``open`` of the scene, per run (one window per run, in one process): the model's reconstruction
done (the background load's result taken by the window), the first picture on screen (the full-quality
pass shows as its chunks are drawn), and the full-quality picture finished. Two ways to run the
window's frames while the model works: at the window's pacing (`ViewerWindow.pause_s`: a few frames
a second while only a load runs) and flat out (what the window did before: frames drawn as fast as
they go, competing with the model for the cores and the GIL); and two ways to draw the full-quality
picture: as now (a chunk resolves the layers over the sky only when its picture is on screen, at
most every `Viewport.show_every_s`, and the levels of detail are built once the picture is done)
and as before 2026-12-03 (every chunk resolved, the levels built at once, in a thread that competes
with the picture for the cores).
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

from drivingscene.arguments import positive_int
from drivingscene.machine import machine_description


def time_open(scene: Path, paced: bool, before: bool = False, timeout: float = 180.0) -> dict[str, float]:
    """Seconds from ``open`` to: the model done, the first picture, the full-quality picture;
    ``before``: the refinement as it was before 2026-12-03 (`Viewport.before_2026_12_03`)."""
    from drivingscene_view.window import ViewerWindow

    win = ViewerWindow(1600, 900, method="auto")
    v = win.viewer
    v.viewport.before_2026_12_03 = before
    try:
        start = time.perf_counter()
        v.open(scene)
        marks: dict[str, float] = {}
        while time.perf_counter() - start < timeout and "full" not in marks:
            win.step()
            time.sleep(win.pause_s if paced else 0.0)
            now = time.perf_counter() - start
            if v.doc is not None and v.job is None:
                marks.setdefault("model", now)
                if v.viewport.target is not None:
                    marks.setdefault("first", now)
                if v.viewport.settled:
                    marks["full"] = now
        model = v.doc.recon.meta.get("timings", {}).get("total_s", float("nan")) if v.doc else float("nan")
        return marks | {"reconstruct": model}
    finally:
        win.close()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m drivingscene_view.first_picture", description=__doc__.splitlines()[0])
    p.add_argument("scene", type=Path, help="scene.npz to open (e.g. assets/demo_scene.npz)")
    p.add_argument("--runs", type=positive_int, default=3, help="windows opened per way of pacing (default 3; medians)")
    args = p.parse_args(argv)
    rows = []
    ways = (
        (False, True, "frames flat out while loading, the refinement as before 2026-12-03"),
        (True, True, "frames paced while loading, the refinement as before 2026-12-03"),
        (True, False, "frames paced while loading, chunks resolved when seen, levels of detail after the picture (now)"),
    )
    for paced, before, name in ways:
        runs = [time_open(args.scene, paced, before) for _ in range(args.runs)]
        med = {k: statistics.median(r.get(k, float("nan")) for r in runs) for k in ("reconstruct", "model", "first", "full")}
        rows.append(f"| {name} | {med['reconstruct']:.2f} | {med['model']:.2f} | {med['first']:.2f} | {med['full']:.2f} |")
    print(
        f"Measured with `python -m drivingscene_view.first_picture {args.scene} --runs {args.runs}` under Xvfb (Mesa llvmpipe) "
        f"on {machine_description()}; medians of {args.runs} windows each, seconds from opening the scene.\n"
    )
    print("| window frames | the model's reconstruction | model done | first picture | full-quality picture |")
    print("|---|---|---|---|---|")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
