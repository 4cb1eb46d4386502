"""World files with hostile headers: any value of any header field, any tensor shape or dtype, deep nesting. The
reader answers with the world or a ``WorldFormatError`` naming the file and the field or tensor; the runtime model
with a ``WorldModelError``; never another exception."""

from __future__ import annotations

import hashlib
import json
import struct
from types import MappingProxyType

import numpy as np
import pytest
from _worlds import two_box_world
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from safetensors.numpy import save as st_save

from dsg_gym.world import META_KEY, World, WorldFormatError, WorldObject, encode_world, parse_world_bytes
from dsg_gym.world_header import DTYPES
from dsg_gym.world_model import WorldModel, WorldModelError

SRC = "fuzz.dsgworld"
SETTINGS = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _world() -> World:
    wm = two_box_world()
    k = wm.num_objects
    return World(
        background=wm.background,
        objects=MappingProxyType(
            {i + 1: WorldObject(n, g) for i, (n, g) in enumerate(zip(wm.object_names, wm.objects))}
        ),
        poses=MappingProxyType(dict(wm.states)),
        cameras=MappingProxyType({"state1": wm.cameras, "state2": wm.cameras}),
        classifier_weight=np.zeros((k + 1, 0), np.float32),
        classifier_bias=np.zeros(k + 1, np.float32),
        metadata={"reference_state": "state1", "table": {"bounds": [[-0.3, -0.2, 0.0], [0.3, 0.2, 0.0]]}},
        units="metres",
    )


BASE = encode_world(_world())


def _split(data: bytes) -> tuple[dict, dict, bytes]:
    (hlen,) = struct.unpack("<Q", data[:8])
    header = json.loads(data[8 : 8 + hlen])
    return header, json.loads(header["__metadata__"][META_KEY]), data[8 + hlen :]


def _join(header: dict, body: bytes) -> bytes:
    raw = json.dumps(header).encode()
    return struct.pack("<Q", len(raw)) + raw + body


def _paths(value, prefix=()) -> list[tuple]:
    """Every path into a JSON document (dict keys and list indices)."""
    out = [prefix] if prefix else []
    if isinstance(value, dict):
        for k, v in value.items():
            out += _paths(v, prefix + (k,))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            out += _paths(v, prefix + (i,))
    return out


_HEADER, DOC, BODY = _split(BASE)
DOC_PATHS = _paths(DOC)
TENSORS = sorted(k for k in _HEADER if k != "__metadata__")

json_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers()
    | st.sampled_from([0, -1, 1, 2**31, 2**63, -(2**64), 10**300])
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=6),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4),
    max_leaves=12,
)


def _file_error(data: bytes) -> str | None:
    """The reader's ``WorldFormatError`` message for ``data`` (None when it loads; then the runtime model loads
    too or raises ``WorldModelError``); any other exception fails the test."""
    try:
        world = parse_world_bytes(data, SRC)
    except WorldFormatError as e:
        assert str(e).startswith(f"{SRC}: "), e
        return str(e)
    try:
        WorldModel.from_world(world)
    except WorldModelError:
        pass
    return None


def test_the_base_world_loads():
    assert _file_error(BASE) is None
    assert WorldModel.from_world(parse_world_bytes(BASE)).num_objects == 2


@SETTINGS
@given(path=st.sampled_from(DOC_PATHS), value=json_values, delete=st.booleans())
def test_any_header_field_value(path, value, delete):
    doc = json.loads(json.dumps(DOC))
    node = doc
    for key in path[:-1]:
        node = node[key]
    if delete and isinstance(node, dict):
        del node[path[-1]]
    else:
        node[path[-1]] = value
    header = json.loads(json.dumps(_HEADER))
    header["__metadata__"][META_KEY] = json.dumps(doc)
    msg = _file_error(_join(header, BODY))
    top = str(path[0])
    if msg is not None and top not in ("sha256", "format", "format_version"):
        assert top in msg or "tensor" in msg, (path, msg)  # names the field, or the tensor it points to


@SETTINGS
@given(
    name=st.sampled_from(TENSORS), key=st.sampled_from(["dtype", "shape", "data_offsets"]), value=json_values
)
def test_any_tensor_header_entry(name, key, value):
    header = json.loads(json.dumps(_HEADER))
    header[name][key] = value
    msg = _file_error(_join(header, BODY))
    if msg is not None:
        assert "tensor" in msg or "truncated" in msg, msg


def _with_arrays(arrays: dict[str, np.ndarray]) -> bytes:
    probe = st_save(arrays, metadata={META_KEY: json.dumps({**DOC, "sha256": ""})})
    (hlen,) = struct.unpack("<Q", probe[:8])
    digest = hashlib.sha256(probe[8 + hlen :]).hexdigest()
    return st_save(arrays, metadata={META_KEY: json.dumps({**DOC, "sha256": digest})})


@SETTINGS
@given(
    name=st.sampled_from(TENSORS),
    dtype=st.sampled_from(sorted(DTYPES)),
    shape=st.lists(st.integers(0, 5), max_size=4),
    fill=st.sampled_from([0.0, 1.0, -1.0, np.nan, np.inf, 1e30]),
    drop=st.booleans(),
)
def test_any_tensor_shape_and_dtype(name, dtype, shape, fill, drop):
    from safetensors.numpy import load

    arrays = load(BASE)
    if drop:
        del arrays[name]
    else:
        with np.errstate(invalid="ignore", over="ignore"):
            arrays[name] = np.full(shape, fill).astype(DTYPES[dtype])
    msg = _file_error(_with_arrays(arrays))
    if msg is not None:
        prefix = name.rsplit("/", 1)[0]
        assert name in msg or prefix in msg or "tensor" in msg or "states" in msg, (name, msg)


@pytest.mark.parametrize("where", ["header", "document", "metadata"])
def test_deep_nesting_is_refused_cleanly(where):
    deep = "[" * 100_000 + "]" * 100_000
    header, doc, body = _split(BASE)
    if where == "header":
        raw = json.dumps(header).encode()
        raw = raw[:-1] + b', "deep": ' + deep.encode() + b"}"
        data = struct.pack("<Q", len(raw)) + raw + body
    else:
        text = json.dumps(doc)
        if where == "document":
            text = text[:-1] + f', "deep": {deep}}}'
        else:
            text = text.replace('"metadata": {', f'"metadata": {{"deep": {deep}, ', 1)
        header["__metadata__"][META_KEY] = text
        data = _join(header, body)
    with pytest.raises(WorldFormatError, match=f"{SRC}: not a world file"):
        parse_world_bytes(data, SRC)


@pytest.mark.parametrize(
    "field,value,msg",
    [
        ("objects", {"1": "red"}, "header field 'objects' must be a list, got dict"),
        ("objects", [{"id": "1", "name": "red"}], r"'objects\[0\].id' must be a new integer"),
        ("objects", [{"id": 1, "name": 7}], r"'objects\[0\].name' must be a string, got 7"),
        ("states", "state1", "header field 'states' must be a list of strings, got 'state1'"),
        ("cameras", [], "header field 'cameras' must be an object, got list"),
        ("cameras", {"state1": {"width": 10**30, "height": 64}}, "'cameras.state1.width' must be an integer"),
        ("metadata", [1], "header field 'metadata' must be an object, got list"),
        ("format_version", 1.0, "unknown world format version 1.0"),
    ],
)
def test_wrong_header_types_name_the_field(field, value, msg):
    header, doc, body = _split(BASE)
    doc[field] = value
    header["__metadata__"][META_KEY] = json.dumps(doc)
    with pytest.raises(WorldFormatError, match=msg):
        parse_world_bytes(_join(header, body), SRC)


def test_wrong_tensor_sizes_name_the_tensor():
    header, doc, body = _split(BASE)
    header["poses/state1"]["shape"] = [3, 4, 4]  # the bytes of [2, 4, 4]
    with pytest.raises(
        WorldFormatError, match=r"tensor 'poses/state1': shape \[3, 4, 4\] of F64 needs 384 bytes"
    ):
        parse_world_bytes(_join(header, body), SRC)
    header, doc, body = _split(BASE)
    header["poses/state1"]["dtype"] = "F16"
    with pytest.raises(WorldFormatError, match="tensor 'poses/state1' has unsupported dtype 'F16'"):
        parse_world_bytes(_join(header, body), SRC)


def test_table_metadata_of_the_wrong_type_is_a_world_model_error():
    for table, msg in (
        ({"bounds": "wide"}, "table.bounds"),
        ({"bounds": [[0, 0, 0], [1, 1]]}, "table.bounds"),
        ({"bounds": [[-1, -1, 0], [1, 1, 0]], "top_z": "high"}, "table.top_z"),
        ({"bounds": [[-1, -1, 0], [1, 1, 0]], "top_z": 10**400}, "table.top_z"),
    ):
        header, doc, body = _split(BASE)
        doc["metadata"]["table"] = table
        header["__metadata__"][META_KEY] = json.dumps(doc)
        world = parse_world_bytes(_join(header, body), SRC)
        with pytest.raises(WorldModelError, match=msg):
            WorldModel.from_world(world)
