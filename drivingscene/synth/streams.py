"""The seed's independent random streams: ``numpy.random.default_rng([seed, STREAMS[name]])``.

Streams 1-3 are the fixed benchmark's and their order of draws is frozen; every randomisation knob
draws only from its own newer stream, so with the knobs off a pair is byte-identical to before and
turning one knob on changes nothing that another stream decides.
"""

from __future__ import annotations

import numpy as np

STREAMS: dict[str, int] = {
    "town": 1,  # town layout and meshes, lighting, t0, world placement, ego lane
    "agents": 2,  # moving vehicles and pedestrians
    "noise": 3,  # --noise-std
    "rig": 4,  # --rig random
    "style": 5,  # town or suburb under --scene-style mixed
    "suburb": 6,  # the suburb's layout and meshes
    "lighting": 7,  # --lighting varied
    "motion": 8,  # --randomise-motion
    "ego_body": 9,  # --ego-body
    "photometric": 10,  # --photometric
    "capture": 11,  # the trigger order of --capture-spread
}


def stream(seed: int, name: str) -> np.random.Generator:
    return np.random.default_rng([seed, STREAMS[name]])
