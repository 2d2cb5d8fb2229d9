"""Scene files: the frame-pair format (v1), safe npz I/O and validation."""

from drivingscene.data.frame_pair import (
    FORMAT_NAME,
    FORMAT_VERSION,
    FramePair,
    load_frame_pair,
    save_frame_pair,
    validate_frame_pair_file,
)

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "FramePair",
    "load_frame_pair",
    "save_frame_pair",
    "validate_frame_pair_file",
]
