"""The procedural surround-view benchmark with exact ground truth (``drivingscene synth``).

``generate_pair(config, seed)`` returns a ``FramePair`` (images, calibration, ego poses, depth,
flow both ways, scene flow, dynamic masks, evaluation frames). The data path inside: ``config`` ->
``scene`` (``town``/``streetscape`` static layout, ``traffic`` agents, ``motion`` exact poses) ->
``render`` (colour and ground-truth GL passes) -> ``ground_truth`` -> ``generate``; ``dataset``
writes folders, ``preview`` draws contact sheets. See docs/synth.md.
"""

from drivingscene.synth.config import PRESETS, SPLITS, SynthConfig, resolve_config, split_seeds
from drivingscene.synth.generate import generate_pair

__all__ = ["PRESETS", "SPLITS", "SynthConfig", "generate_pair", "resolve_config", "split_seeds"]
