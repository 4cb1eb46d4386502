"""World file: exact round trip, refusal of truncated/corrupt/unknown-version files, object frames."""

from __future__ import annotations

import json
import struct
import subprocess
import sys
from types import MappingProxyType

import numpy as np
import pytest
from safetensors.numpy import save as st_save

from dsg_gym.cameras import Cameras
from dsg_gym.gaussians import GaussianSet
from dsg_gym.world import (
    World,
    WorldFormatError,
    WorldObject,
    build_world,
    encode_world,
    load_world,
    parse_world_bytes,
    write_world,
)


def _random_set(rng, n, degree=1, nf=16, encodings=True):
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    logits = rng.normal(size=n).astype(np.float32)
    log_s = rng.normal(-4, 1, size=(n, 3)).astype(np.float32)
    return GaussianSet(
        means=rng.normal(size=(n, 3)),
        quats=q,
        scales=np.exp(log_s.astype(np.float64)),
        opacities=1 / (1 + np.exp(-logits.astype(np.float64))),
        sh=rng.normal(size=(n, (degree + 1) ** 2, 3)),
        features=rng.normal(size=(n, nf)),
        labels=rng.integers(0, 3, n),
        opacity_logits=logits if encodings else None,
        log_scales=log_s if encodings else None,
    )


def _rigid(rng):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    R = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, rng.normal(size=3)
    return T


@pytest.fixture
def world():
    rng = np.random.default_rng(3)
    objects = {1: WorldObject("red_box", _random_set(rng, 7)), 4: WorldObject("ball", _random_set(rng, 0))}
    return World(
        background=_random_set(rng, 11, encodings=False),
        objects=MappingProxyType(objects),
        poses=MappingProxyType(
            {"state1": np.stack([_rigid(rng), _rigid(rng)]), "state2": np.stack([_rigid(rng), _rigid(rng)])}
        ),
        cameras=MappingProxyType(
            {
                "state1": Cameras(
                    rng.normal(size=(3, 4, 4)).astype(np.float32),
                    rng.normal(size=(3, 3, 3)).astype(np.float32),
                    32,
                    24,
                )
            }
        ),
        classifier_weight=rng.normal(size=(3, 16)).astype(np.float32),
        classifier_bias=rng.normal(size=3).astype(np.float32),
        metadata={"reference_state": "state1", "train_config": {"seed": 0, "preset": {"name": "quick"}}},
        units="metres",
    )


def _same_set(a: GaussianSet, b: GaussianSet):
    for f in (
        "means",
        "quats",
        "scales",
        "opacities",
        "sh",
        "features",
        "labels",
        "opacity_logits",
        "log_scales",
    ):
        va, vb = getattr(a, f), getattr(b, f)
        if va is None or vb is None:
            assert va is None and vb is None, f
        else:
            assert va.dtype == vb.dtype and np.array_equal(va, vb), f


def test_round_trip_is_exact(tmp_path, world):
    path = write_world(tmp_path / "w.dsgworld", world)
    back = load_world(path)
    _same_set(world.background, back.background)
    assert back.object_ids == (1, 4) and back.object_names == ("red_box", "ball")
    for oid in world.object_ids:
        _same_set(world.objects[oid].gaussians, back.objects[oid].gaussians)
    for s in world.poses:
        assert back.poses[s].dtype == np.float64 and np.array_equal(back.poses[s], world.poses[s])
    cam = back.cameras["state1"]
    assert (cam.width, cam.height) == (32, 24)
    assert np.array_equal(cam.viewmats, world.cameras["state1"].viewmats)
    assert np.array_equal(cam.Ks, world.cameras["state1"].Ks)
    assert np.array_equal(back.classifier_weight, world.classifier_weight)
    assert np.array_equal(back.classifier_bias, world.classifier_bias)
    assert dict(back.metadata) == world.metadata and back.units == "metres" and back.format_version == 1
    # deterministic bytes, and re-encoding the loaded world gives the same file
    assert encode_world(world) == encode_world(back) == path.read_bytes()
    # no temp files left behind by the atomic write
    assert [p.name for p in tmp_path.iterdir()] == ["w.dsgworld"]


@pytest.mark.parametrize("keep", [0, 5, 8, 40, -1, -100])
def test_truncated_file_is_refused(tmp_path, world, keep):
    data = encode_world(world)
    (hlen,) = struct.unpack("<Q", data[:8])
    cut = {0: 0, 5: 5, 8: 8, 40: 40, -1: len(data) - 1, -100: 8 + hlen + 10}[keep]
    p = tmp_path / "t.dsgworld"
    p.write_bytes(data[:cut])
    with pytest.raises(WorldFormatError, match="truncated"):
        load_world(p)


def _rewrite_meta(data: bytes, **changes) -> bytes:
    (hlen,) = struct.unpack("<Q", data[:8])
    header = json.loads(data[8 : 8 + hlen])
    doc = json.loads(header["__metadata__"]["dsg_world"])
    doc.update(changes)
    header["__metadata__"]["dsg_world"] = json.dumps(doc)
    new = json.dumps(header).encode()
    return struct.pack("<Q", len(new)) + new + data[8 + hlen :]


def test_unknown_version_and_foreign_files_are_refused(world):
    data = encode_world(world)
    with pytest.raises(WorldFormatError, match="unknown world format version 2"):
        parse_world_bytes(_rewrite_meta(data, format_version=2))
    with pytest.raises(WorldFormatError, match="not a world file"):
        parse_world_bytes(_rewrite_meta(data, format="something-else"))
    with pytest.raises(WorldFormatError, match="not a world file"):
        parse_world_bytes(st_save({"a": np.zeros(3, np.float32)}))
    with pytest.raises(WorldFormatError):
        parse_world_bytes(b"ply\nformat binary_little_endian 1.0\nend_header\n" + bytes(64))


def test_corrupt_byte_is_refused(world):
    data = bytearray(encode_world(world))
    data[-3] ^= 0xFF
    with pytest.raises(WorldFormatError, match="checksum"):
        parse_world_bytes(bytes(data))


def test_build_world_puts_objects_in_their_frame_and_back():
    rng = np.random.default_rng(0)
    g = _random_set(rng, 40, encodings=False)
    classes = rng.integers(0, 3, 40)
    P = np.stack([_rigid(rng), _rigid(rng)])
    w = build_world(
        g,
        classes,
        (2, 5),
        ("a", "b"),
        {"s1": P},
        "s1",
        {"s1": Cameras(np.eye(4, dtype=np.float32)[None], np.eye(3, dtype=np.float32)[None], 8, 8)},
        np.zeros((3, 16), np.float32),
        np.zeros(3, np.float32),
        "metres",
        {},
    )
    assert w.background.num == int((classes == 0).sum())
    assert w.objects[5].gaussians.num == int((classes == 2).sum())
    assert set(np.unique(w.objects[2].gaussians.labels)) <= {2}
    # object 2's Gaussians, expressed in its frame, map back to the world with its pose
    local = w.objects[2].gaussians.means.astype(np.float64)
    back = local @ P[0, :3, :3].T + P[0, :3, 3]
    assert np.allclose(back, g.means[classes == 1], atol=1e-5)
    # composing at the reference state reproduces the trained field (up to float32 rounding)
    world_set = w.gaussians("s1")
    order = np.argsort(np.concatenate([np.flatnonzero(classes == c) for c in range(3)]))
    assert np.allclose(world_set.means[order], g.means, atol=1e-5)
    dots = np.abs((world_set.quats[order] * g.quats).sum(-1))
    assert np.allclose(dots, 1.0, atol=1e-5)
    # another pose moves only that object
    P2 = P.copy()
    P2[1, :3, 3] += [1.0, 0.0, 0.0]
    moved = w.gaussians(poses=P2)
    nb, n1 = w.background.num, w.objects[2].gaussians.num
    assert np.allclose(moved.means[: nb + n1], world_set.means[: nb + n1])
    assert np.allclose(moved.means[nb + n1 :] - world_set.means[nb + n1 :], [1.0, 0.0, 0.0], atol=1e-5)


def test_reader_does_not_need_torch(tmp_path, world):
    path = write_world(tmp_path / "w.dsgworld", world)
    code = (
        "import sys; sys.modules['torch'] = None\n"
        "from dsg_gym.world import load_world\n"
        f"w = load_world({str(path)!r}); print(w.background.num, 'torch' in sys.modules and sys.modules['torch'])"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=False
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.split()[0] == "11"
