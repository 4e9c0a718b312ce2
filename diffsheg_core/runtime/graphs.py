"""What a stored ONNX graph declares, read from its protobuf bytes without the onnx package
(which the runtime does not ship): the inputs it takes, and the tensors whose data live in
external files, which onnxruntime would open relative to the working directory.

Only the fields of onnx.proto that lead to tensors and inputs are followed; everything else
(raw weights included) is skipped by its length, so reading a 13 MB graph takes milliseconds.
`named_weights` reads the initializers that carry a network's parameter names (a graph
exported without constant folding holds every weight that way; an int8 one, under names of this
project, is read back dequantised), so that a model file stores each weight once, in its graph,
and the torch backend reads it from there. A graph may instead leave its weights out, each
marked external data at `SUPPLIED` (a model's live graphs, int8 copies of its own):
`supplied_weights` makes them from the model's weights when the graph is opened.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

EXTERNAL = 1  # TensorProto.DataLocation.EXTERNAL
ELEMENT_TYPES = {1: "float32", 7: "int64", 9: "bool", 10: "float16", 11: "float64", 6: "int32"}

# message -> {field number: message it holds}, for the fields through which tensors are reached
_TENSORS_IN = {
    "model": {7: "graph", 20: "training", 25: "function"},
    "training": {1: "graph", 2: "graph"},
    "graph": {1: "node", 5: "tensor", 15: "sparse"},
    "function": {7: "node", 11: "attribute"},
    "node": {5: "attribute"},
    "attribute": {5: "tensor", 6: "graph", 10: "tensor", 11: "graph", 22: "sparse", 23: "sparse"},
    "sparse": {1: "tensor", 2: "tensor"},
}


@dataclass
class GraphInputs:
    """A graph's inputs {name: (element type, shape)} (a dynamic axis is its name, a str) and
    the names of its tensors stored as external data."""

    inputs: dict[str, tuple[str, tuple]] = field(default_factory=dict)
    external: list[str] = field(default_factory=list)


def _varint(buf: memoryview, pos: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        byte = buf[pos]
        value |= (byte & 0x7F) << shift
        pos += 1
        if byte < 0x80:
            return value, pos
        shift += 7
        if shift > 63:
            raise ValueError("a varint runs past 10 bytes")


def _fields(buf: memoryview):
    """(field number, value) of one message: an int for varints, a memoryview for
    length-delimited fields (fixed-width ones are skipped)."""
    pos = 0
    while pos < len(buf):
        key, pos = _varint(buf, pos)
        number, wire = key >> 3, key & 7
        if number == 0:
            raise ValueError("field number 0 is not protobuf's")
        if wire == 0:
            value, pos = _varint(buf, pos)
        elif wire == 2:
            size, pos = _varint(buf, pos)
            value, pos = buf[pos:pos + size], pos + size
        elif wire in (1, 5):
            value, pos = None, pos + (8 if wire == 1 else 4)
        else:
            raise ValueError(f"wire type {wire} is not protobuf's")
        if pos > len(buf):
            raise ValueError("a field runs past the end of its message")
        if value is not None:
            yield number, value


def _is_external(tensor: memoryview) -> bool:
    return any(n == 13 or (n == 14 and v == EXTERNAL) for n, v in _fields(tensor))


def _tensor_name(tensor: memoryview) -> str:
    """A TensorProto's name: its last name field, as protobuf and onnxruntime read it."""
    names = [bytes(v).decode("utf-8", "replace") for n, v in _fields(tensor) if n == 8]
    return names[-1] if names else "?"


def _external(buf: memoryview, kind: str, found: list[str]) -> None:
    """Append to `found` the names of the tensors reached from message `buf` of `kind`
    that refer to external data."""
    if kind == "tensor":
        if _is_external(buf):
            found.append(_tensor_name(buf))
        return
    holds = _TENSORS_IN[kind]
    for number, value in _fields(buf):
        if number in holds and isinstance(value, memoryview):
            _external(value, holds[number], found)


def _input(buf: memoryview) -> tuple[str, tuple[str, tuple]]:
    """(name, (element type, shape)) of a ValueInfoProto holding a tensor type."""
    name, elem, dims = "", "?", []
    for number, value in _fields(buf):
        if number == 1:
            name = bytes(value).decode("utf-8", "replace")
        elif number == 2:  # TypeProto
            for n, tensor in _fields(value):
                if n != 1:  # not tensor_type
                    continue
                for m, part in _fields(tensor):
                    if m == 1:
                        elem = ELEMENT_TYPES.get(part, str(part))
                    elif m == 2:  # TensorShapeProto: dim
                        for _, dim in (f for f in _fields(part) if f[0] == 1):
                            got = dict(_fields(dim))
                            dims.append(bytes(got[2]).decode() if 2 in got else got.get(1, "?"))
    return name, (elem, tuple(dims))


def _graph_body(buf: memoryview) -> memoryview:
    """The GraphProto of a serialised ModelProto (its last `graph` field)."""
    body = [v for n, v in _fields(buf) if n == 7]
    if not body or not isinstance(body[-1], memoryview):
        raise ValueError("it holds no graph")
    return body[-1]


def read_graph(graph: bytes) -> GraphInputs:
    """The inputs and external-data tensors of a serialised ONNX ModelProto; ValueError
    when the bytes are not one."""
    buf = memoryview(graph)
    out = GraphInputs()
    try:
        _external(buf, "model", out.external)
        out.inputs = dict(_input(v) for n, v in _fields(_graph_body(buf)) if n == 11)
    except (IndexError, UnicodeDecodeError, KeyError, TypeError) as exc:
        raise ValueError(f"it is not an ONNX model ({exc})") from None
    return out


def left_out(graph: bytes) -> list[str]:
    """The initializers a graph leaves out (external data, made by `supplied_weights` and given
    to onnxruntime by name when it opens the graph); ValueError when the bytes are not an ONNX
    model, or when any external tensor is not one of the graph's own dense initializers with a
    name of its own: onnxruntime would read such a tensor (a sparse initializer, a node's
    constant, a subgraph's) from its file before the supplied ones apply."""
    external = read_graph(graph).external
    try:
        own = [_tensor_name(tensor) for number, body in _fields(memoryview(graph)) if number == 7
               for field_number, tensor in _fields(body)
               if field_number == 5 and isinstance(tensor, memoryview) and _is_external(tensor)]
    except (IndexError, UnicodeDecodeError, TypeError) as exc:
        raise ValueError(f"it is not an ONNX model ({exc})") from None
    if sorted(external) != sorted(own) or len(set(own)) != len(own):
        strays = sorted(set(external) - set(own)) or sorted({n for n in own if own.count(n) > 1})
        raise ValueError(f"external data outside the graph's own initializers, or under one name twice "
                         f"({', '.join(strays[:3])})")
    return own


def _dims(value) -> list[int]:
    """A TensorProto's dims field: one varint, or a packed run of them."""
    if isinstance(value, int):
        return [value]
    dims, pos = [], 0
    while pos < len(value):
        dim, pos = _varint(value, pos)
        dims.append(dim)
    return dims


RAW_TYPES = {1: np.float32, 10: np.float16, 3: np.int8}  # the element types a network's weights are stored as
INT8, SCALE, ZERO, TRANSPOSED, HALF = ".int8", ".int8.scale", ".int8.zero", ".T", ".fp16"
SUPPLIED = "supplied-from-the-model-weights"  # the external data location of a weight a graph leaves out


def named_weights(graph: bytes, prefix: str) -> dict[str, np.ndarray]:
    """{name: array} of the graph's initializers named `prefix` + a parameter name; ValueError
    when the bytes are not an ONNX model. Tensors not stored as raw bytes are left out.

    A weight is stored as one of (`torch_layer.export` writes them), transposed if `.T`
    follows its name (as a product reads it):
      `<name>[.T]` or `<name>[.T].fp16`  float32, or the half-stored copy the graph casts back;
      `<name>[.T].int8` with `.int8.scale` and `.int8.zero`: int8 for a product by the weight
                        (a distilled student's), read back dequantised, (int8 - zero) * scale
                        (a scale per column, or one), in float32."""
    raw: dict[str, np.ndarray] = {}
    try:
        for number, tensor in _fields(_graph_body(memoryview(graph))):
            if number != 5 or not isinstance(tensor, memoryview):
                continue
            dims, kind, name, data = [], None, "", None
            for n, value in _fields(tensor):
                if n == 1:
                    dims += _dims(value)
                elif n == 2:
                    kind = value
                elif n == 8:
                    name = bytes(value).decode("utf-8")
                elif n == 9:
                    data = value
            if not name.startswith(prefix) or kind not in RAW_TYPES or data is None:
                continue
            array = np.frombuffer(data, dtype=np.dtype(RAW_TYPES[kind]).newbyteorder("<"))
            if array.size != int(np.prod(dims, dtype=np.int64)):
                raise ValueError(f"tensor {name} holds {array.size} values for shape {tuple(dims)}")
            raw[name[len(prefix):]] = array.reshape(dims).copy()
    except (IndexError, UnicodeDecodeError, TypeError) as exc:
        raise ValueError(f"it is not an ONNX model ({exc})") from None
    found: dict[str, np.ndarray] = {}
    for name, array in raw.items():
        if name.endswith((SCALE, ZERO)):
            continue
        if name.endswith(INT8):
            array, name = _dequantised(raw, name), name.removesuffix(INT8)
        elif array.dtype == np.int8:
            continue
        name = name.removesuffix(HALF)
        if name.endswith(TRANSPOSED):
            array, name = np.ascontiguousarray(array.T), name.removesuffix(TRANSPOSED)
        found[name] = array
    return found


def _dequantised(raw: dict[str, np.ndarray], name: str) -> np.ndarray:
    """The float32 weight of int8 tensor `name`, from its scale and zero point."""
    scale, zero = raw.get(name[:-len(INT8)] + SCALE), raw.get(name[:-len(INT8)] + ZERO)
    values = raw[name]
    if scale is None or zero is None or values.ndim != 2 or scale.dtype != np.float32 \
            or scale.size not in (1, values.shape[1]) or zero.size != scale.size:
        raise ValueError(f"int8 weight {name} lacks a float32 scale and a zero point, one or one per column")
    return ((values.astype(np.float32) - zero.astype(np.float32).reshape(-1)) * scale.reshape(-1)).astype(np.float32)


def int8_columns(weight: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(int8 values, float32 scale per column, int8 zero points) of a 2-d float weight: symmetric,
    each column's largest magnitude at 127, as onnxruntime's dynamic quantisation makes a
    weight per channel (the same numbers, tested)."""
    weight = np.asarray(weight, np.float32)
    scale = np.abs(weight).max(axis=0) / np.float32(127.0)
    scale = np.where(scale == 0, np.float32(1.0), scale).astype(np.float32)
    values = np.clip(np.rint(weight / scale), -127, 127).astype(np.int8)
    return values, scale, np.zeros(scale.shape, np.int8)


def _supplied_from(name: str, weights: dict[str, np.ndarray], prefix: str) -> tuple[str, bool, str]:
    """(parameter, transposed, suffix) of `weights` that make initializer `name` (`supplied_weights`)."""
    part = name[len(prefix):] if name.startswith(prefix) else ""
    suffix = next((s for s in (SCALE, ZERO, INT8, HALF) if part.endswith(s)), "")
    base = part[:len(part) - len(suffix)]
    parameter = base.removesuffix(TRANSPOSED)
    if parameter not in weights or (suffix in (INT8, SCALE, ZERO) and np.ndim(weights[parameter]) != 2):
        raise ValueError(f"no weight of the model makes the graph's initializer {name}")
    return parameter, base.endswith(TRANSPOSED), suffix


def check_supplied(names: list[str], weights: dict[str, np.ndarray], prefix: str) -> None:
    """ValueError naming an initializer of `names` that `supplied_weights` cannot make."""
    for name in names:
        _supplied_from(name, weights, prefix)


def supplied_weights(names: list[str], weights: dict[str, np.ndarray], prefix: str) -> dict[str, np.ndarray]:
    """{name: array} for initializers a graph leaves out (`SUPPLIED`), each named `prefix` + a
    parameter of `weights` + what `named_weights` reads: `.T` (transposed), then `.fp16` (half)
    or `.int8`, `.int8.scale`, `.int8.zero` (`int8_columns`). ValueError names one that no
    weight makes."""
    found: dict[str, np.ndarray] = {}
    quantised: dict[tuple[str, bool], dict[str, np.ndarray]] = {}  # a weight's three int8 tensors, made once
    for name in names:
        parameter, transposed, suffix = _supplied_from(name, weights, prefix)
        value = np.asarray(weights[parameter])
        value = np.ascontiguousarray(value.T) if transposed else value
        if suffix in (INT8, SCALE, ZERO):
            if (parameter, transposed) not in quantised:
                quantised[parameter, transposed] = dict(zip((INT8, SCALE, ZERO), int8_columns(value)))
            value = quantised[parameter, transposed][suffix]
        elif suffix == HALF:
            half = value.astype(np.float16)
            if not np.array_equal(half.astype(value.dtype), value):
                raise ValueError(f"the weight {parameter} is not held in float16, as the graph's initializer "
                                 f"{name} is: the graph was made from other weights")
            value = half
        elif value.dtype.kind == "f":  # exported from float32 modules, whatever the weights are held as
            value = value.astype(np.float32)
        found[name] = value
    return found
