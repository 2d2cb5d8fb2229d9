"""Exports: PLY (3DGS, dynamic, points); images and videos come with the viewer."""

from drivingscene.export.ply import PLY_KINDS, read_ply, write_ply

__all__ = ["PLY_KINDS", "read_ply", "write_ply"]
