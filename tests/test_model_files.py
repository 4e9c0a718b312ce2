"""Model files that are edited, mixed up or crafted are refused when they load, with one
line naming the file and what is wrong (issue 26, items 3-5): ONNX graphs that refer to
external data, metadata that disagrees with the graphs, a few bytes given as a checkpoint.
Every broken file is made from the real bundled model."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import pytest

from diffsheg_core import CheckpointError
from diffsheg_core.checkpoints import DEFAULT_WEIGHTS, load_model, read_safetensors, write_safetensors
from diffsheg_core.runtime.graphs import left_out, named_weights, read_graph, supplied_weights

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def default_file():
    return read_safetensors(DEFAULT_WEIGHTS, "")


def cli(*args: str, cwd: Path = REPO) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "diffsheg_core", "generate", *args], cwd=cwd,
                          capture_output=True, text=True, timeout=300)


def refused_by_the_cli(model: Path, tmp_path: Path, *expected: str) -> None:
    """`generate --model model` exits 2 with one line naming the file and `expected`, and writes nothing."""
    out = tmp_path / "motion.npz"
    result = cli("--model", str(model), "-o", str(out), cwd=tmp_path)
    error = [line for line in result.stderr.splitlines() if line.strip()]
    assert result.returncode == 2 and len(error) == 1, result.stderr
    assert error[0].startswith(f"error: {model}") and all(e in error[0] for e in expected), error
    assert "Traceback" not in result.stderr and not out.exists()


def with_external_data(graph: bytes, location: str) -> bytes:
    """`graph` with its largest initializer moved to external data at `location`."""
    proto = onnx.load_from_string(graph)
    tensor = max(proto.graph.initializer, key=lambda t: len(t.raw_data))
    tensor.ClearField("raw_data")
    tensor.data_location = onnx.TensorProto.EXTERNAL
    entry = tensor.external_data.add()
    entry.key, entry.value = "location", location
    return proto.SerializeToString()


def test_the_graph_reader_finds_what_onnx_finds(default_file):
    """Inputs as onnx reads them; external data in initializers and in a subgraph's constant."""
    _, tensors = default_file
    for name in ("expression", "gesture", "phonetic"):
        graph = tensors[f"onnx.{name}"].tobytes()
        proto = onnx.load_from_string(graph)
        found = read_graph(graph)
        assert list(found.inputs) == [i.name for i in proto.graph.input] and found.external == []
        for value in proto.graph.input:
            dims = tuple(d.dim_param or d.dim_value for d in value.type.tensor_type.shape.dim)
            assert found.inputs[value.name][1] == dims
    assert read_graph(with_external_data(tensors["onnx.phonetic"].tobytes(), "secret.txt")).external
    constant = onnx.helper.make_node("Constant", [], ["c"], value=onnx.numpy_helper.from_array(
        np.ones(3, np.float32), "hidden"))
    constant.attribute[0].t.data_location = onnx.TensorProto.EXTERNAL
    branch = onnx.helper.make_graph([constant], "branch", [], [onnx.helper.make_tensor_value_info("c", 1, [3])])
    model = onnx.helper.make_model(onnx.helper.make_graph(
        [onnx.helper.make_node("If", ["cond"], ["y"], then_branch=branch, else_branch=branch)], "g",
        [onnx.helper.make_tensor_value_info("cond", onnx.TensorProto.BOOL, [])],
        [onnx.helper.make_tensor_value_info("y", 1, [3])]))
    assert read_graph(model.SerializeToString()).external == ["hidden", "hidden"]
    for junk in (b"abc", b"\x00" * 10, np.random.default_rng(0).bytes(1000)):
        with pytest.raises(ValueError):
            read_graph(junk)


def test_the_graph_reader_reads_the_students_int8_weights_as_onnx_does(default_file, tmp_path):
    """The distilled student's products by weights are stored in int8 (a scale per output
    column; `.T`: stored transposed, as the product reads it): the reader gives each back as
    onnx's own tensors dequantise, under its parameter's name, and a student graph whose int8
    weight lost its scale is refused when the model loads."""
    meta, tensors = default_file
    for graph in ("expression", "gesture"):
        proto = onnx.load_from_string(tensors[f"onnx.student.{graph}"].tobytes())
        stored = {i.name: onnx.numpy_helper.to_array(i) for i in proto.graph.initializer}
        held = named_weights(proto.SerializeToString(), "model.")
        quantised = [name for name in stored if name.endswith(".int8")]
        assert len(quantised) >= 30 and all(stored[name].dtype == np.int8 for name in quantised)
        for name in quantised:
            value = (stored[name].astype(np.float32) - stored[f"{name}.zero"].astype(np.float32)) \
                * stored[f"{name}.scale"]
            parameter = name.removeprefix("model.").removesuffix(".int8")
            if parameter.endswith(".T"):
                value, parameter = value.T, parameter.removesuffix(".T")
            np.testing.assert_array_equal(held[parameter], value)
    scale = next(i for i in proto.graph.initializer if i.name.endswith(".int8.scale"))
    proto.graph.initializer.remove(scale)
    path = write_safetensors({**tensors, "onnx.student.gesture": np.frombuffer(proto.SerializeToString(), np.uint8)},
                             meta, tmp_path / "crafted.safetensors")
    with pytest.raises(CheckpointError, match="graphs of its distilled student are damaged .*lacks a float32 scale"):
        load_model(path)


@pytest.mark.parametrize("graph", ["phonetic", "gesture"])
def test_a_graph_that_refers_to_external_data_is_refused(default_file, tmp_path, graph):
    """onnxruntime would read `secret.txt` from the working directory into the weights."""
    meta, tensors = default_file
    crafted = with_external_data(tensors[f"onnx.{graph}"].tobytes(), "secret.txt")
    path = write_safetensors({**tensors, f"onnx.{graph}": np.frombuffer(crafted, np.uint8)}, meta,
                             tmp_path / "crafted.safetensors")
    (tmp_path / "secret.txt").write_bytes(b"\x00" * 4 * 1_000_000)
    with pytest.raises(CheckpointError, match=f"graph '{graph}' refers to external data.*never use external"):
        load_model(path)
    refused_by_the_cli(path, tmp_path, "external data")


def test_the_live_graphs_leave_their_weights_to_the_model_and_an_edited_one_is_refused(default_file, tmp_path):
    """The bundled file's live graphs (int8, for live sessions on onnxruntime) hold no weights:
    every initializer is external data, made from the model's own weights when they are opened,
    so onnxruntime reads no file for one. A live graph that leaves out a weight the model does
    not have, or a file with one live graph of two, is refused when it loads."""
    from diffsheg_core.runtime.backends import live_network, open_network

    meta, tensors = default_file
    model = load_model(DEFAULT_WEIGHTS)
    assert set(model.live_graphs) == {"expression", "gesture"} and sum(map(len, model.live_graphs.values())) < 1e6
    for name, graph in model.live_graphs.items():
        names = left_out(graph)
        assert sorted(names) == sorted(read_graph(graph).external)
        made = supplied_weights(names, model.weights, "model.")
        int8 = [n for n in names if n.endswith(".int8")]
        assert len(int8) >= 30 and all(made[n].dtype == np.int8 and np.abs(made[n]).max() == 127 for n in int8)
    network = open_network(model, backend="onnx", threads=1)
    live = live_network(model, network)
    assert live is not network and live is live_network(model, network) and set(live.sessions) == set(network.sessions)
    proto = onnx.load_from_string(tensors["onnx.live.gesture"].tobytes())
    proto.graph.initializer[0].name = "model.not_a_weight"
    crafted = write_safetensors({**tensors, "onnx.live.gesture": np.frombuffer(proto.SerializeToString(), np.uint8)},
                                meta, tmp_path / "crafted.safetensors")
    with pytest.raises(CheckpointError, match="live ONNX graph 'gesture' leaves out what the model's weights do not "
                                              "make .*not_a_weight"):
        load_model(crafted)
    half = write_safetensors({k: v for k, v in tensors.items() if k != "onnx.live.gesture"}, meta,
                             tmp_path / "half.safetensors")
    with pytest.raises(CheckpointError, match="its live graphs are incomplete"):
        load_model(half)
    refused_by_the_cli(half, tmp_path, "live graphs are incomplete")
    assert model.student.live_graphs == {}  # made from the teacher's weights, not the student's
    weight = next(n for n in left_out(model.live_graphs["gesture"]) if n.endswith(".fp16"))
    parameter = weight.removeprefix("model.").removesuffix(".fp16").removesuffix(".T")
    other = {**model.weights, parameter: model.weights[parameter].astype(np.float32) + np.float32(1e-5)}
    with pytest.raises(ValueError, match=f"weight {parameter} is not held in float16"):
        supplied_weights([weight], other, "model.")


def _sparse_external(proto, name: str) -> None:
    values = onnx.numpy_helper.from_array(np.ones(2, np.float32), name)
    values.data_location = onnx.TensorProto.EXTERNAL
    values.external_data.add(key="location", value="secret.txt")
    proto.graph.sparse_initializer.append(onnx.helper.make_sparse_tensor(
        values, onnx.numpy_helper.from_array(np.array([0, 1], np.int64), f"{name}.indices"), [4]))


def _constant_external(proto, name: str) -> None:
    value = onnx.numpy_helper.from_array(np.ones(4, np.float32), name)
    value.ClearField("raw_data")
    value.data_location = onnx.TensorProto.EXTERNAL
    value.external_data.add(key="location", value="secret.txt")
    proto.graph.node.append(onnx.helper.make_node("Constant", [], ["stray"], value=value))


def _twice(proto, name: str) -> None:
    proto.graph.initializer.append(next(i for i in proto.graph.initializer if i.name == name))


@pytest.mark.parametrize("craft", [_sparse_external, _constant_external, _twice])
def test_a_live_graph_whose_external_data_onnxruntime_would_read_is_refused(default_file, tmp_path, craft):
    """onnxruntime reads a sparse initializer's or a node's external data from its file while it
    builds the graph, before the weights a live graph leaves out are given to it, and a name
    given twice is ambiguous: a live graph may leave out only its own dense initializers, each
    under a name of its own, even one a weight of the model makes."""
    meta, tensors = default_file
    proto = onnx.load_from_string(tensors["onnx.live.gesture"].tobytes())
    craft(proto, next(i.name for i in proto.graph.initializer if i.name.endswith(".int8")))
    (tmp_path / "secret.txt").write_bytes(b"\x00" * 64)
    path = write_safetensors({**tensors, "onnx.live.gesture": np.frombuffer(proto.SerializeToString(), np.uint8)},
                             meta, tmp_path / "crafted.safetensors")
    with pytest.raises(CheckpointError, match="live ONNX graph 'gesture' .*external data outside the graph's own"):
        load_model(path)


def edited(default_file, path: Path, meta_change=None, tensor_change=None) -> Path:
    meta, tensors = default_file
    meta, tensors = dict(meta), dict(tensors)
    info, config = json.loads(meta["info"]), json.loads(meta["config"])
    if meta_change:
        meta_change(meta, info, config)
    if tensor_change:
        tensor_change(tensors)
    meta.setdefault("info", json.dumps(info))
    return write_safetensors(tensors, {**meta, "config": json.dumps(config)}, path)


def swap_graphs(tensors: dict) -> None:
    tensors["onnx.expression"], tensors["onnx.gesture"] = tensors["onnx.gesture"], tensors["onnx.expression"]


@pytest.mark.parametrize("case,meta_change,tensor_change,expected", [
    ("four style names", lambda m, info, c: m.update(info=json.dumps(
        {**info, "style_names": info["style_names"] + ["shouty"]})), None, "are not 3 different names"),
    ("non-string style names", lambda m, info, c: m.update(info=json.dumps({**info, "style_names": [1, 2, 3]})),
     None, "are not 3 different names"),
    ("info a list", lambda m, info, c: m.update(info="[1, 2]"), None, "metadata 'info' is a JSON list"),
    ("style_dim unlike the graph's", lambda m, info, c: c.update(style_dim=4), None,
     "input 'style' is float32 (batch, 3) where the metadata's config gives float32 (?, 4)"),
    ("graphs swapped", None, swap_graphs, "missing inputs expression, mel"),
    ("a default style it lacks", lambda m, info, c: m.update(info=json.dumps({**info, "default_style": "shouty"})),
     None, "default style 'shouty' is not one of its styles"),
])
def test_metadata_that_disagrees_with_the_graphs_is_named_when_the_model_loads(
        default_file, tmp_path, case, meta_change, tensor_change, expected):
    path = edited(default_file, tmp_path / "edited.safetensors", meta_change, tensor_change)
    with pytest.raises(CheckpointError) as err:
        load_model(path)
    assert str(path) in str(err.value) and expected in str(err.value) and "again" in str(err.value), case
    refused_by_the_cli(path, tmp_path, expected)


def test_a_few_bytes_given_as_a_checkpoint_are_named_for_what_they_are(tmp_path):
    pytest.importorskip("torch")
    for name, data in (("three.pt", b"abc"), ("empty.pt", b""), ("brace.pt", b"{ab")):
        path = tmp_path / name
        path.write_bytes(data)
        with pytest.raises(CheckpointError, match="cannot read this torch checkpoint .*damaged"):
            load_model(path)
    refused_by_the_cli(tmp_path / "three.pt", tmp_path, "damaged or cut short", "download it again")


def test_an_output_that_is_not_npz_is_refused_naming_the_format_flags(tmp_path):
    """-o writes the motion as .npz; a .bvh there once got an npz under that name, silently."""
    result = cli("-o", str(tmp_path / "take.bvh"), cwd=tmp_path)
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    assert "-o/--output writes the motion as .npz, not take.bvh" in result.stderr and "--bvh" in result.stderr
    assert not (tmp_path / "take.bvh").exists()
