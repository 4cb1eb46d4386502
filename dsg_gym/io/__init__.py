"""File formats: 3DGS PLY (``dsg_gym.io.ply``)."""

from dsg_gym.io.ply import PlyFormatError, PlyHeader, read_ply, read_ply_header, write_ply

__all__ = ["PlyFormatError", "PlyHeader", "read_ply", "read_ply_header", "write_ply"]
