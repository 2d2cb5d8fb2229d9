"""The real viewer window opening bad files of the corpus one after another (run under Xvfb by
``test_viewer_xvfb.py``):  python -m tests.reliability.xvfb_corpus_session OUT_DIR

For each bad file: the one-line error appears in the status bar, the window keeps drawing frames;
then a good reconstruction opens in the same window. Writes ``OUT_DIR/result.json``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from tests.app.xvfb_session import Session
from tests.reliability.corpus import build

BAD_CASES = ("npz_pickled_view", "npz_truncated_view", "ply_truncated_view", "scene_reflected_view")


def run(out: Path) -> dict:
    from drivingscene.gaussians.recon import save_reconstruction
    from tests.app.scenes import street_recon

    s = Session(out)
    viewer = s.win.viewer
    result: dict = {"cases": []}
    for case_id in BAD_CASES:
        case = build(case_id, out / case_id)
        viewer.open(case.files[0])
        s.pump(3, until=lambda: viewer.job is None and viewer.status.error)
        for _ in range(5):  # the window keeps drawing
            s.win.step()
        shot = s.win.screenshot()
        result["cases"].append(
            {
                "id": case_id,
                "status": viewer.status.text,
                "error": viewer.status.error,
                "expect": list(case.expect),
                "marker": case.marker is not None and case.marker.exists(),
                "frame_drawn": bool(shot.size and np.asarray(shot).std() > 0),
            }
        )
    viewer.open(save_reconstruction(street_recon(height=24, width=32, flow=8.0), out / "recon.npz"))
    s.pump(5, until=lambda: viewer.job is None and viewer.doc is not None)
    result["loaded_after"] = viewer.doc is not None and not viewer.status.error
    s.win.close()
    return result


if __name__ == "__main__":
    out_dir = Path(sys.argv[1])
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "result.json").write_text(json.dumps(run(out_dir), indent=1))
