"""3D Gaussian Splatting PLY files (the Inria layout), read and written with numpy.

Layout written (``binary_little_endian 1.0``, one ``vertex`` element, all ``float``)::

    x y z  [nx ny nz]  f_dc_0..2  f_rest_0..(3*((d+1)^2-1)-1)  opacity  scale_0..2  rot_0..3
    [obj_dc_0..obj_dc_{F-1}]  [label]

* ``f_rest`` is channel-major: all R coefficients of bands 1..d, then all G, then all B.
* ``opacity`` is stored as a logit, ``scale_*`` as natural logs, ``rot_*`` raw (w, x, y, z).
* ``nx ny nz`` are written as zeros unless ``normals=False`` (gsplat's exporter omits them);
  on read they are optional and ignored.
* ``obj_dc_*`` are Gaussian Grouping identity features (any count F, written when F > 0).
* ``label`` is the integer object label, **stored as float32** (exact for |label| < 2^24),
  because most splat viewers and loaders assume every vertex property is a float. On
  read, ``label`` may have any numeric type but must hold integers. By default it is
  written only when some label is non-zero; a missing ``label`` reads as zeros.

Reading accepts any property order and extra properties (ignored), the scalar types
char/uchar/short/ushort/int/uint/float/double (and their int8.. / float32 aliases),
little- and big-endian binary, and scalar-only elements before ``vertex``. ASCII files
and list properties in the elements read are refused. Every problem raises
``PlyFormatError`` (a ``ValueError``) whose message starts with the file name.

Activation (sigmoid / exp) and its inverse run in float64; see ``dsg_gym.gaussians``.
A set read from a file remembers its stored logits/log-scales, so
``write_ply(read_ply(f))`` reproduces a valid Inria-layout file byte for byte (zero
normals, no comments) and ``read_ply(write_ply(read_ply(f)))`` gives identical arrays.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from dsg_gym.gaussians import (
    MAX_SH_DEGREE,
    GaussianSet,
    activate_opacity,
    activate_scale,
    sh_degree_from_coeffs,
)
from dsg_gym.io.atomic import atomic_path, remove_partial

__all__ = ["PlyFormatError", "read_ply", "write_ply", "read_ply_header", "PlyHeader"]

_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
_FORMATS = {"binary_little_endian": "<", "binary_big_endian": ">"}
_MAX_HEADER = 1 << 20  # a header larger than 1 MiB is certainly not a splat file
_REQUIRED = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
             "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")  # fmt: skip


class PlyFormatError(ValueError):
    """A PLY file that cannot be read as 3D Gaussians; the message names the file."""


class PlyHeader:
    """Parsed header: ``fmt`` ('<' or '>'), ``vertex_count``, ``properties`` [(name, numpy
    type code)] of the vertex element, ``vertex_offset`` (bytes from the start of the
    file to the first vertex) and ``comments``."""

    def __init__(self, fmt: str, vertex_count: int, properties: list[tuple[str, str]], vertex_offset: int,
                 comments: list[str]) -> None:  # fmt: skip
        self.fmt = fmt
        self.vertex_count = vertex_count
        self.properties = properties
        self.vertex_offset = vertex_offset
        self.comments = comments

    @property
    def names(self) -> list[str]:
        return [n for n, _ in self.properties]

    def dtype(self) -> np.dtype:
        """Packed structured dtype of one vertex."""
        return np.dtype([(n, self.fmt + t) for n, t in self.properties])

    def __repr__(self) -> str:
        return (f"PlyHeader(fmt={self.fmt!r}, vertex_count={self.vertex_count}, "
                f"properties={len(self.properties)})")  # fmt: skip


def _parse_header(data: bytes, name: str) -> PlyHeader:
    def fail(msg: str) -> PlyFormatError:
        return PlyFormatError(f"{name}: {msg}")

    if not (data.startswith(b"ply\n") or data.startswith(b"ply\r\n")):
        raise fail("not a PLY file (missing 'ply' magic line)")
    m = re.search(rb"(^|\n)end_header[ \t]*\r?\n", data[:_MAX_HEADER])
    if m is None:
        raise fail("no 'end_header' line (truncated or not a PLY header)")
    body_start = m.end()
    try:
        lines = data[: m.start()].decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise fail("header is not ASCII text") from None

    fmt = None
    elements: list[list] = []  # [name, count, [(prop, type)], has_list]
    comments: list[str] = []
    for lineno, raw in enumerate(lines[1:], start=2):
        tok = raw.split()
        if not tok:
            continue
        key = tok[0]
        if key in ("comment", "obj_info"):
            comments.append(raw.partition(" ")[2])
        elif key == "format":
            if len(tok) != 3:
                raise fail(f"malformed format line {lineno}: {raw!r}")
            if tok[1] == "ascii":
                raise fail("ASCII PLY is not supported (3DGS files are binary_little_endian)")
            if tok[1] not in _FORMATS:
                raise fail(f"unsupported PLY format {tok[1]!r}")
            if tok[2] != "1.0":
                raise fail(f"unsupported PLY version {tok[2]!r}")
            fmt = _FORMATS[tok[1]]
        elif key == "element":
            if len(tok) != 3 or not tok[2].isdigit():
                raise fail(f"malformed element line {lineno}: {raw!r}")
            elements.append([tok[1], int(tok[2]), [], False])
        elif key == "property":
            if not elements:
                raise fail(f"property before any element on line {lineno}")
            if len(tok) >= 2 and tok[1] == "list":
                elements[-1][3] = True
                continue
            if len(tok) != 3:
                raise fail(f"malformed property line {lineno}: {raw!r}")
            if tok[1] not in _TYPES:
                raise fail(f"unsupported property type {tok[1]!r} for {tok[2]!r}")
            elements[-1][2].append((tok[2], _TYPES[tok[1]]))
        else:
            raise fail(f"unexpected header line {lineno}: {raw!r}")
    if fmt is None:
        raise fail("missing 'format' line")

    offset = body_start
    for ename, count, props, has_list in elements:
        if ename == "vertex":
            if has_list:
                raise fail("list properties in the vertex element are not supported")
            names = [p for p, _ in props]
            dup = sorted({p for p in names if names.count(p) > 1})
            if dup:
                raise fail(f"duplicate vertex properties {dup}")
            return PlyHeader(fmt, count, props, offset, comments)
        if has_list:
            raise fail(f"element {ename!r} before 'vertex' has list properties; cannot locate the vertices")
        offset += count * sum(np.dtype(t).itemsize for _, t in props)
    raise fail("no 'vertex' element")


def read_ply_header(path: str | os.PathLike) -> PlyHeader:
    """Parse only the header of a PLY file."""
    with open(path, "rb") as fh:
        data = fh.read(_MAX_HEADER)
    return _parse_header(data, str(path))


def _numbered(names: set[str], prefix: str) -> int:
    """Count of properties ``prefix0..prefix{k-1}``; error (returns -1) if not contiguous."""
    idx = sorted(int(n[len(prefix) :]) for n in names if re.fullmatch(re.escape(prefix) + r"\d+", n))
    return len(idx) if idx == list(range(len(idx))) else -1


def read_ply(path: str | os.PathLike) -> GaussianSet:
    """Read a 3DGS PLY file into a ``GaussianSet`` with activated values.

    Raises ``PlyFormatError`` (a ``ValueError`` naming the file) for: missing ``ply``
    magic, missing ``end_header``, unsupported format (ASCII, ...), missing required
    properties, an ``f_rest`` count that is not ``3 * ((d+1)^2 - 1)`` for d in 0..3,
    non-contiguous ``f_rest_*`` / ``obj_dc_*`` numbering, a body shorter than
    ``vertex_count * stride``, no vertices at all (``element vertex 0``), non-finite
    values, non-integer labels and activated values that overflow float32.
    """
    name = str(path)
    with open(path, "rb") as fh:
        data = fh.read()
    header = _parse_header(data, name)

    def fail(msg: str) -> PlyFormatError:
        return PlyFormatError(f"{name}: {msg}")

    names = set(header.names)
    missing = [p for p in _REQUIRED if p not in names]
    if missing:
        raise fail(f"missing required vertex properties {missing}")
    n_rest = _numbered(names, "f_rest_")
    if n_rest < 0:
        raise fail("f_rest_* properties are not numbered 0..k-1 without gaps")
    if n_rest % 3:
        raise fail(f"{n_rest} f_rest properties is not a multiple of 3")
    try:
        degree = sh_degree_from_coeffs(n_rest // 3 + 1)
    except ValueError:
        allowed = [3 * ((d + 1) ** 2 - 1) for d in range(MAX_SH_DEGREE + 1)]
        raise fail(f"{n_rest} f_rest properties does not match an SH degree 0..{MAX_SH_DEGREE} "
                   f"(expected one of {allowed})") from None  # fmt: skip
    n_feat = _numbered(names, "obj_dc_")
    if n_feat < 0:
        raise fail("obj_dc_* properties are not numbered 0..k-1 without gaps")

    dtype = header.dtype()
    n = header.vertex_count
    if n == 0:
        raise fail("the PLY has no Gaussians (element vertex 0); a 3DGS PLY holds at least one")
    need = n * dtype.itemsize
    have = len(data) - header.vertex_offset
    if have < need:
        raise fail(f"truncated: {n} vertices of {dtype.itemsize} bytes need {need} bytes after the header, "
                   f"found {max(have, 0)}")  # fmt: skip
    verts = np.frombuffer(data, dtype=dtype, count=n, offset=header.vertex_offset)

    def cols(props: list[str]) -> np.ndarray:
        out = np.empty((n, len(props)), np.float32)
        for i, p in enumerate(props):
            col = verts[p]
            if col.dtype.kind == "f" and not np.isfinite(col).all():
                raise fail(f"non-finite values in property {p!r}")
            with np.errstate(over="ignore"):
                out[:, i] = col
            if not np.isfinite(out[:, i]).all():
                raise fail(f"property {p!r} overflows float32")
        return out

    means = cols(["x", "y", "z"])
    k = (degree + 1) ** 2
    sh = np.empty((n, k, 3), np.float32)
    sh[:, 0] = cols(["f_dc_0", "f_dc_1", "f_dc_2"])
    if k > 1:
        rest = cols([f"f_rest_{i}" for i in range(n_rest)])
        sh[:, 1:] = rest.reshape(n, 3, k - 1).transpose(0, 2, 1)
    opacity_logits = cols(["opacity"])[:, 0]
    log_scales = cols(["scale_0", "scale_1", "scale_2"])
    quats = cols(["rot_0", "rot_1", "rot_2", "rot_3"])
    features = cols([f"obj_dc_{i}" for i in range(n_feat)])

    labels = None
    if "label" in names:
        raw = verts["label"]
        if raw.dtype.kind == "f":
            if not np.isfinite(raw).all() or (raw != np.round(raw)).any():
                raise fail("property 'label' holds non-integer values")
            if n and np.abs(raw).max() > 2**31 - 1:
                raise fail("property 'label' outside the int32 range")
        elif n and raw.dtype == np.uint32 and raw.max() > 2**31 - 1:
            raise fail("property 'label' outside the int32 range")
        labels = raw.astype(np.int32)

    opacities = activate_opacity(opacity_logits)
    scales = activate_scale(log_scales)
    if not np.isfinite(scales).all():
        raise fail("scale_* values too large: exp(scale) overflows float32")
    try:
        return GaussianSet(
            means=means, quats=quats, scales=scales, opacities=opacities, sh=sh,
            features=features, labels=labels, opacity_logits=opacity_logits, log_scales=log_scales,
        )  # fmt: skip
    except ValueError as err:
        raise fail(str(err)) from None


def _header_bytes(n: int, props: list[str]) -> bytes:
    lines = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    lines += [f"property float {p}" for p in props]
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def encode_vertices(gaussians: GaussianSet, *, normals: bool = True,
                    labels: bool | None = None) -> tuple[list[str], np.ndarray]:  # fmt: skip
    """Property names and the ``[N, P]`` little-endian float32 table ``write_ply`` stores."""
    g = gaussians
    n, k = g.num, g.sh.shape[1]
    names = ["x", "y", "z"]
    blocks = [g.means]
    if normals:
        names += ["nx", "ny", "nz"]
        blocks.append(np.zeros((n, 3), np.float32))
    names += [f"f_dc_{i}" for i in range(3)]
    blocks.append(g.sh[:, 0])
    if k > 1:
        names += [f"f_rest_{i}" for i in range(3 * (k - 1))]
        blocks.append(g.sh[:, 1:].transpose(0, 2, 1).reshape(n, 3 * (k - 1)))  # channel-major
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    blocks += [g.encoded_opacity_logits()[:, None], g.encoded_log_scales(), g.quats]
    if g.num_features:
        names += [f"obj_dc_{i}" for i in range(g.num_features)]
        blocks.append(g.features)
    if labels is None:
        labels = bool(g.labels.any())
    if labels:
        if g.labels.size and np.abs(g.labels.astype(np.int64)).max() >= 2**24:
            raise ValueError("labels with |label| >= 2^24 cannot be stored exactly as float32")
        names.append("label")
        blocks.append(g.labels.astype(np.float32)[:, None])
    table = np.concatenate(blocks, axis=1).astype("<f4", copy=False)
    return names, np.ascontiguousarray(table)


def write_ply(path: str | os.PathLike, gaussians: GaussianSet, *, normals: bool = True,
              labels: bool | None = None) -> Path:  # fmt: skip
    """Write ``gaussians`` as an Inria-layout 3DGS PLY, atomically.

    ``normals``: write zero ``nx ny nz`` (Inria layout, default) or omit them (gsplat).
    ``labels``: write the ``label`` property (float32) always (True), never (False) or only
    when some label is non-zero (None, default). The file is written atomically
    (:mod:`dsg_gym.io.atomic`; the temporaries of killed writes to ``path`` are deleted
    first). An empty set raises ``ValueError`` (a PLY without vertices is not read back).
    Returns the path.
    """
    path = Path(path)
    if gaussians.num == 0:
        raise ValueError(
            f"{path}: nothing to write, the set has no Gaussians (read_ply refuses a PLY without vertices)"
        )
    names, table = encode_vertices(gaussians, normals=normals, labels=labels)
    payload = _header_bytes(table.shape[0], names)
    remove_partial(path.parent, path.name, stale_only=True)
    with atomic_path(path) as tmp, open(tmp, "xb") as fh:
        fh.write(payload)
        fh.write(table.tobytes())
    return path
