"""Tests for dsg_gym.gaussians.GaussianSet and dsg_gym.io.ply (3DGS PLY read/write)."""

from __future__ import annotations

import math
import os
import re
import struct
from pathlib import Path

import numpy as np
import pytest

from dsg_gym.gaussians import SH_C0, GaussianSet, activate_opacity, activate_scale
from dsg_gym.io import PlyFormatError, read_ply, read_ply_header, write_ply
from dsg_gym.io.ply import encode_vertices

REAL_PLY = (
    Path(__file__).resolve().parents[2] / "shared" / "external" / "gs_ply_small" / "point_cloud_iter7000.ply"
)
FIELDS = ("means", "quats", "scales", "opacities", "sh", "features", "labels")


def random_set(rng, n, degree, n_feat=0, labels=False, from_encoded=True):
    """Random set. ``from_encoded``: activated values come from float32 logits/log-scales (as
    if read from a file); otherwise opacities/scales are arbitrary float32 activated values."""
    k = (degree + 1) ** 2
    if from_encoded:
        opac = activate_opacity(rng.uniform(-12, 12, n).astype(np.float32))
        scales = activate_scale(rng.uniform(-9, 2, (n, 3)).astype(np.float32))
    else:
        opac = rng.uniform(0, 1, n).astype(np.float32)
        scales = rng.uniform(0, 0.5, (n, 3)).astype(np.float32)
    return GaussianSet(
        means=rng.normal(size=(n, 3)),
        quats=rng.normal(size=(n, 4)),
        scales=scales,
        opacities=opac,
        sh=rng.normal(size=(n, k, 3)),
        features=rng.normal(size=(n, n_feat)),
        labels=rng.integers(0, 7, n) if labels else None,
    )


def assert_same(a: GaussianSet, b: GaussianSet, fields=FIELDS):
    for f in fields:
        x, y = getattr(a, f), getattr(b, f)
        assert x.dtype == y.dtype and x.shape == y.shape, f
        assert np.array_equal(x, y), f"{f} differs in {(x != y).sum()} entries"


# --------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("n_feat,labels", [(0, False), (16, True), (3, False), (0, True)])
def test_round_trip_exact(tmp_path, degree, n_feat, labels):
    rng = np.random.default_rng(100 * degree + n_feat + labels)
    g0 = random_set(rng, 257, degree, n_feat, labels)
    p1 = write_ply(tmp_path / "a.ply", g0)
    g1 = read_ply(p1)
    assert (g1.num, g1.sh_degree, g1.num_features) == (257, degree, n_feat)
    assert_same(g0, g1)
    names = read_ply_header(p1).names
    assert ("label" in names) == labels
    assert names[:6] == ["x", "y", "z", "nx", "ny", "nz"]
    assert len(names) == 17 + 3 * ((degree + 1) ** 2 - 1) + n_feat + labels
    # read -> write -> read: identical arrays and identical bytes.
    p2 = write_ply(tmp_path / "b.ply", g1)
    assert p2.read_bytes() == p1.read_bytes()
    assert_same(g1, read_ply(p2))
    # gsplat layout (no normals) reads back the same.
    p3 = write_ply(tmp_path / "c.ply", g1, normals=False)
    assert "nx" not in read_ply_header(p3).names
    assert_same(g1, read_ply(p3))


@pytest.mark.parametrize("degree", [0, 3])
def test_round_trip_arbitrary_activated_values(tmp_path, degree):
    """Opacities/scales not from a file: the first trip is within float32 rounding of the
    logit/log, after that the set is a fixed point (also without stored encodings)."""
    rng = np.random.default_rng(7 + degree)
    g0 = random_set(rng, 1000, degree, 2, True, from_encoded=False)
    g1 = read_ply(write_ply(tmp_path / "a.ply", g0))
    assert_same(g0, g1, ("means", "quats", "sh", "features", "labels"))
    np.testing.assert_allclose(g1.opacities, g0.opacities, rtol=0, atol=1e-7)
    np.testing.assert_allclose(g1.scales, g0.scales, rtol=1e-6, atol=0)
    g2 = read_ply(write_ply(tmp_path / "b.ply", g1.without_encodings()))
    assert_same(g1, g2)


def test_extreme_values_are_clamped_not_infinite(tmp_path):
    g = GaussianSet(
        means=np.zeros((3, 3)), quats=np.tile([1.0, 0, 0, 0], (3, 1)), scales=[[0, 1e-30, 1e30]] * 3,
        opacities=[0.0, 1.0, 0.5], sh=np.zeros((3, 1, 3)),
    )  # fmt: skip
    names, table = encode_vertices(g)
    assert np.isfinite(table).all()
    op = table[:, names.index("opacity")]
    assert op[0] == np.float32(math.log(1e-7) - math.log1p(-1e-7)) and op[1] == -op[0] and op[2] == 0
    g1 = read_ply(write_ply(tmp_path / "x.ply", g))
    np.testing.assert_allclose(g1.opacities, [1e-7, 1 - 1e-7, 0.5], rtol=1e-6)
    assert 0 < g1.scales[0, 0] <= 2 * np.finfo(np.float32).tiny  # zero scale -> ~FLT_MIN, not -inf
    np.testing.assert_allclose(g1.scales[0, 1:], [1e-30, 1e30], rtol=1e-6)


# --------------------------------------------------------------------------- hand-written file


def _tiny_ply(path: Path, endian: str = "<", fmt: str = "binary_little_endian") -> None:
    """Degree-1 file, no normals, mixed types, a comment and an ignored property."""
    header = "\n".join([
        "ply", f"format {fmt} 1.0", "comment made by hand", "element vertex 2",
        "property double x", "property float y", "property float z",
        "property float f_dc_0", "property float f_dc_1", "property float f_dc_2",
        *[f"property float f_rest_{i}" for i in range(9)],
        "property float opacity", *[f"property float scale_{i}" for i in range(3)],
        "property float rot_0", "property float rot_1", "property float rot_2", "property float rot_3",
        "property uchar red", "property float obj_dc_0", "property float obj_dc_1", "property int label",
        "end_header",
    ]) + "\n"  # fmt: skip
    row_fmt = endian + "d" + "f" * 22 + "B" + "ff" + "i"
    rows = [
        (1.0, 2.0, 3.0, 0.1, 0.2, 0.3, *range(10, 19), 0.0, 0.0, math.log(2.0), math.log(0.5),
         1.0, 0.0, 0.0, 0.0, 255, 0.25, -0.5, 4),
        (-1.5, 0.0, 0.5, 0.0, 0.0, 0.0, *range(20, 29), math.log(3.0), -1.0, -2.0, -3.0,
         0.5, 0.5, 0.5, 0.5, 7, 1.0, 2.0, -2),
    ]  # fmt: skip
    body = b"".join(struct.pack(row_fmt, *r) for r in rows)
    path.write_bytes(header.encode("ascii") + body)


@pytest.mark.parametrize("endian,fmt", [("<", "binary_little_endian"), (">", "binary_big_endian")])
def test_hand_written_ply(tmp_path, endian, fmt):
    p = tmp_path / "tiny.ply"
    _tiny_ply(p, endian, fmt)
    g = read_ply(p)
    assert g.num == 2 and g.sh_degree == 1 and g.num_features == 2
    np.testing.assert_array_equal(g.means, np.float32([[1, 2, 3], [-1.5, 0, 0.5]]))
    np.testing.assert_allclose(g.opacities, [0.5, 0.75], rtol=1e-7)
    np.testing.assert_allclose(g.scales, [[1.0, 2.0, 0.5], np.exp([-1.0, -2.0, -3.0])], rtol=1e-7)
    np.testing.assert_array_equal(g.quats, np.float32([[1, 0, 0, 0], [0.5, 0.5, 0.5, 0.5]]))
    np.testing.assert_array_equal(g.features, np.float32([[0.25, -0.5], [1.0, 2.0]]))
    np.testing.assert_array_equal(g.labels, np.int32([4, -2]))
    assert g.labels.dtype == np.int32
    # f_rest is channel-major: f_rest_{c*3 + j} is coefficient j+1 of channel c.
    expected = np.zeros((2, 4, 3), np.float32)
    expected[0, 0] = [0.1, 0.2, 0.3]
    for r, base in enumerate((10, 20)):
        for c in range(3):
            for j in range(3):
                expected[r, 1 + j, c] = base + 3 * c + j
    np.testing.assert_array_equal(g.sh, expected)
    np.testing.assert_allclose(g.colors[0], 0.5 + SH_C0 * np.float32([0.1, 0.2, 0.3]), rtol=1e-6)


# --------------------------------------------------------------------------- refusals


def _valid_bytes(tmp_path) -> bytes:
    return write_ply(tmp_path / "ok.ply", random_set(np.random.default_rng(0), 5, 1)).read_bytes()


def _header_edit(data: bytes, old: bytes, new: bytes) -> bytes:
    end = data.index(b"end_header\n")
    return data[:end].replace(old, new) + data[end:]


@pytest.mark.parametrize(
    "case,pattern",
    [
        ("truncated", "truncated"),
        ("bad_magic", "magic"),
        ("no_end_header", "end_header"),
        ("ascii", "ASCII"),
        ("missing_property", "missing required"),
        ("bad_f_rest_count", "f_rest"),
        ("f_rest_gap", "f_rest"),
        ("non_finite", "non-finite"),
        ("list_property", "list"),
        ("float_label", "label"),
    ],
)
def test_refuses_bad_files(tmp_path, case, pattern):
    data = _valid_bytes(tmp_path)
    if case == "truncated":
        data = data[:-7]
    elif case == "bad_magic":
        data = b"plx" + data[3:]
    elif case == "no_end_header":
        data = data.replace(b"end_header\n", b"end_heathen\n")
    elif case == "ascii":
        data = _header_edit(data, b"binary_little_endian", b"ascii")
    elif case == "missing_property":
        data = _header_edit(data, b"property float opacity\n", b"property float opacityx\n")
    elif case == "bad_f_rest_count":
        extra = b"property float f_rest_9\nproperty float opacity\n"
        data = _header_edit(data, b"property float opacity\n", extra)
        data += b"\0" * 4 * 5
    elif case == "f_rest_gap":
        data = _header_edit(data, b"f_rest_8\n", b"f_rest_11\n")
    elif case == "non_finite":
        hdr_end = data.index(b"end_header\n") + len(b"end_header\n")
        nan = struct.pack("<f", float("nan"))
        data = data[: hdr_end + 4] + nan + data[hdr_end + 8 :]  # vertex 0, y
    elif case == "list_property":
        data = _header_edit(data, b"element vertex 5\n", b"element vertex 5\nproperty list uchar int idx\n")
    elif case == "float_label":
        g = random_set(np.random.default_rng(1), 5, 0, labels=True)
        data = write_ply(tmp_path / "l.ply", g, labels=True).read_bytes()
        data = data[:-2] + b"\x01\x3f"  # last label float -> non-integer
    p = tmp_path / f"bad_{case}.ply"
    p.write_bytes(data)
    with pytest.raises(ValueError, match=re.escape(str(p))) as info:
        read_ply(p)
    assert isinstance(info.value, PlyFormatError)
    assert re.search(pattern, str(info.value)), str(info.value)


def test_gaussian_set_validation_names_field():
    rng = np.random.default_rng(3)
    good = dict(means=np.zeros((4, 3)), quats=np.ones((4, 4)), scales=np.ones((4, 3)),
                opacities=np.full(4, 0.5), sh=np.zeros((4, 4, 3)))  # fmt: skip
    GaussianSet(**good)
    bad_cases = {
        "means": dict(means=np.zeros((4, 2))),
        "quats": dict(quats=np.ones((3, 4))),
        "scales": dict(scales=-np.ones((4, 3))),
        "opacities": dict(opacities=np.full(4, 1.5)),
        "sh": dict(sh=np.zeros((4, 5, 3))),
        "features": dict(features=np.full((4, 2), np.nan)),
        "labels": dict(labels=np.full(4, 0.5)),
    }
    for fld, override in bad_cases.items():
        with pytest.raises(ValueError, match=rf"GaussianSet\.{fld}"):
            GaussianSet(**{**good, **override})
    with pytest.raises(ValueError, match=r"GaussianSet\.means"):
        GaussianSet(**{**good, "means": np.full((4, 3), np.inf)})
    g = GaussianSet(**{**good, "means": rng.normal(size=(4, 3))})
    assert g.means.dtype == np.float32 and g.labels.dtype == np.int32 and g.features.shape == (4, 0)
    assert g.num == len(g) == 4 and g.sh_degree == 1


def test_concat_subset_keep_file_bytes(tmp_path):
    rng = np.random.default_rng(5)
    a = read_ply(write_ply(tmp_path / "a.ply", random_set(rng, 50, 3, 4, True)))
    b = random_set(rng, 30, 1, 4, False, from_encoded=False)
    c = GaussianSet.concat([a, b])
    assert c.num == 80 and c.sh_degree == 3
    np.testing.assert_array_equal(c.sh[50:, 4:], 0)  # padded degree-1 -> 3
    assert_same(c.subset(np.arange(50)), a)
    mask = np.zeros(80, bool)
    mask[50:] = True
    np.testing.assert_array_equal(c.subset(mask).sh[:, :4], b.sh)
    # Rows from the file are written back bit for bit (stored encodings survive concat/subset).
    _, table_a = encode_vertices(a, labels=True)
    _, table_c = encode_vertices(c, labels=True)
    assert table_c[:50].tobytes() == table_a.tobytes()
    _, table_s = encode_vertices(a.subset(slice(10, 20)), labels=True)
    assert table_s.tobytes() == table_a[10:20].tobytes()
    # Editing an activated value discards the stale stored logit for that row only.
    op = a.opacities.copy()
    op[0] = 0.5
    edited = GaussianSet(**{**{f: getattr(a, f) for f in FIELDS}, "opacities": op,
                            "opacity_logits": a.opacity_logits, "log_scales": a.log_scales})  # fmt: skip
    logits = edited.encoded_opacity_logits()
    assert logits[0] == 0 and np.array_equal(logits[1:], a.opacity_logits[1:])
    with pytest.raises(ValueError, match="feature widths"):
        GaussianSet.concat([a, random_set(rng, 3, 0, 1)])
    assert GaussianSet.empty(2, 3).num == 0 and GaussianSet.empty(2, 3).sh.shape == (0, 9, 3)


def test_write_is_atomic(tmp_path, monkeypatch):
    rng = np.random.default_rng(9)
    target = write_ply(tmp_path / "w.ply", random_set(rng, 10, 0))
    before = target.read_bytes()

    def boom(src, dst):
        raise OSError("simulated failure")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError, match="simulated"):
        write_ply(target, random_set(rng, 20, 2))
    assert target.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["w.ply"]  # no temp file left


# --------------------------------------------------------------------------- the real file


@pytest.mark.skipif(not REAL_PLY.is_file(), reason=f"{REAL_PLY} not present")
def test_real_file(tmp_path):
    header = read_ply_header(REAL_PLY)
    assert header.vertex_count == 9080 and len(header.properties) == 62
    g = read_ply(REAL_PLY)
    assert g.num == 9080 and g.sh_degree == 3 and g.num_features == 0
    for f in FIELDS:
        assert np.isfinite(getattr(g, f)).all(), f
    assert (g.opacities > 0).all() and (g.opacities < 1).all() and (g.scales > 0).all()
    out = write_ply(tmp_path / "rewritten.ply", g)
    assert out.read_bytes() == REAL_PLY.read_bytes()  # the file's normals are all zero
    assert_same(g, read_ply(out))
    # Without the stored encodings the bytes may differ, but the parsed arrays may not.
    stripped = read_ply(write_ply(tmp_path / "stripped.ply", g.without_encodings()))
    assert_same(g, stripped)


# --------------------------------------------------------------------------- empty files


def test_a_ply_without_vertices_is_a_clear_error(tmp_path):
    data = write_ply(tmp_path / "a.ply", random_set(np.random.default_rng(0), 3, 1, labels=True)).read_bytes()
    header = data[: data.index(b"end_header\n") + len(b"end_header\n")]
    p = tmp_path / "empty.ply"
    p.write_bytes(header.replace(b"element vertex 3\n", b"element vertex 0\n"))
    with pytest.raises(
        PlyFormatError, match=re.escape(str(p)) + r": the PLY has no Gaussians \(element vertex 0\)"
    ):
        read_ply(p)
    with pytest.raises(ValueError, match="nothing to write, the set has no Gaussians"):
        write_ply(tmp_path / "b.ply", GaussianSet.empty(1))
    assert sorted(os.listdir(tmp_path)) == ["a.ply", "empty.ply"]
