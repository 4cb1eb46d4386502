"""Files: the 3DGS PLY format (``dsg_gym.io.ply``) and atomic writes (``dsg_gym.io.atomic``)."""

from dsg_gym.io.ply import PlyFormatError, PlyHeader, read_ply, read_ply_header, write_ply

__all__ = ["PlyFormatError", "PlyHeader", "read_ply", "read_ply_header", "write_ply"]
