"""ONNX export of a model's networks, so the torch-free runtime (onnxruntime) can run them.

Three graphs, each with dynamic batch and length: `expression` and `gesture` (the two
calls of one sampling step, `UniEG.expression` / `UniEG.gesture`) and, for models that
hear the phonetic encoder, `phonetic` (log-mel -> phone posteriors). They are exported
from float32 modules holding exactly the weights the file stores, so both backends run
the same numbers; a distilled student's products by weights are int8 (`_int8_matmuls`), and
the torch backend runs the weights they hold, dequantised. Constant folding is left to
onnxruntime (it folds when it loads a graph), so every weight stays an initializer named after
its parameter and the file stores it once, in the graph (`checkpoints.graph_weights`). Live
sessions run the network's two graphs once more with their products in int8 (`live_graphs`),
which hold no weights: each is made from the network's when they are opened. Needs
torch, onnx and onnxruntime (tooling: the trainer calls it when it exports).
"""

from __future__ import annotations

import io
import logging
import tempfile
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..checkpoints import MODEL_PREFIX, ModelBundle, graph_weights
from ..config import ModelConfig
from ..runtime.graphs import INT8, SCALE, SUPPLIED, TRANSPOSED, ZERO, supplied_weights
from .model import PhoneticEncoder, UniEG, load_state_strict

OPSET = 17
BATCH, FRAMES = "batch", "frames"


class _Call(nn.Module):
    """One of UniEG's sampling calls with positional inputs named `names` (what tracing needs)."""

    def __init__(self, model: UniEG, call: str, names: list[str]):
        super().__init__()
        self.model, self.call, self.names = model, call, names

    def forward(self, *inputs):
        given = dict(zip(self.names, inputs))
        if self.call == "expression":
            return self.model.expression(given["expression"], given["timesteps"], given["mel"],
                                         given.get("speech"), given["style"], given.get("null"))
        return self.model.gesture(given["gesture"], given["timesteps"], given["audio"], given.get("speech"),
                                  given["expression_x0"], given["style"], given.get("null"), given["attend"])


class _Posteriors(nn.Module):
    def __init__(self, encoder: PhoneticEncoder):
        super().__init__()
        self.encoder = encoder

    def forward(self, mel):
        return self.encoder(mel)[0].softmax(0).T


def _half_initializers(graph: bytes) -> bytes:
    """Store the float32 initializers that float16 holds exactly (the weights of a model
    exported in float16) as float16 with a Cast back in front: half the size, the same
    numbers (onnxruntime folds the casts when it loads the graph)."""
    import onnx
    from onnx import helper, numpy_helper

    proto = onnx.load_from_string(graph)
    casts = []
    for init in proto.graph.initializer:
        if init.data_type != onnx.TensorProto.FLOAT or init.name.endswith(SCALE):  # an int8 weight's scales stay
            continue
        values = numpy_helper.to_array(init)
        half = values.astype(np.float16)
        if values.size < 256 or not np.array_equal(half.astype(np.float32), values):
            continue
        name = init.name
        init.CopyFrom(numpy_helper.from_array(half, f"{name}.fp16"))
        casts.append(helper.make_node("Cast", [f"{name}.fp16"], [name], to=onnx.TensorProto.FLOAT))
    nodes = casts + list(proto.graph.node)
    del proto.graph.node[:]
    proto.graph.node.extend(nodes)
    return proto.SerializeToString()


FLOAT_PRODUCTS = ("joint_embed", "out", "out_layers", "feat_proj")  # modules whose products stay float


def _int8_matmuls(graph: bytes) -> bytes:
    """The graph with its matrix products by weights (MatMul, Gemm) in int8, onnxruntime's dynamic
    quantisation: each weight int8 with a scale per output column, each call's activations
    uint8 as they come. On one core the distilled student's calls take about 0.7x the time, in
    half the bytes of float16. The products of `FLOAT_PRODUCTS` stay float: the motion read in
    (`joint_embed`), the prediction written out (`out`), the attention's and feed-forward's
    output layers (`out_layers`) and the fusion of motion and speech features each layer starts
    with (`feat_proj`), where rounding the activations showed as jitter in the wrists. Weights
    stay 8-bit: on x86 without VNNI onnxruntime's u8 x s8 pair sums can saturate at 16 bits,
    but 7-bit weights, which cannot, moved the feet (the model card's "its products in int8"
    has both measures). A weight the product reads transposed (the export's Transpose, Gemm's
    transB) is stored so, and the quantised initializers take this project's names
    (`runtime.graphs`): `<parameter>[.T].int8`, `.int8.scale`, `.int8.zero`, which
    `named_weights` reads back dequantised under the parameter's name."""
    import onnx
    from onnx import numpy_helper
    from onnxruntime.quantization import QuantType, quantize_dynamic

    proto = onnx.load_from_string(graph)
    inits = {init.name: init for init in proto.graph.initializer}
    transposes = {node.output[0]: node.input[0] for node in proto.graph.node  # a weight's, 2-d
                  if node.op_type == "Transpose" and node.input[0] in inits
                  and all(list(a.ints) == [1, 0] for a in node.attribute if a.name == "perm")}
    quantised: set[str] = set()  # the initializers the int8 products read
    made: set[str] = set()
    excluded: list[str] = []

    def int8(parameter: str) -> bool:
        return not set(parameter.split(".")) & set(FLOAT_PRODUCTS)

    def transposed(name: str) -> str:
        if name not in made:
            made.add(name)
            proto.graph.initializer.append(numpy_helper.from_array(
                np.ascontiguousarray(numpy_helper.to_array(inits[name]).T), f"{name}{TRANSPOSED}"))
        return f"{name}{TRANSPOSED}"

    for node in proto.graph.node:
        if node.op_type not in ("MatMul", "Gemm"):
            continue
        if not node.name:
            raise RuntimeError("the exported graph has an unnamed matrix product, which the int8 export "
                               "cannot leave out of the quantisation")
        weight = transposes.get(node.input[1]) if node.op_type == "MatMul" else node.input[1]
        trans_b = next((a for a in node.attribute if a.name == "transB" and a.i), None)
        if node.op_type == "Gemm" and trans_b is not None and weight in inits:
            # stored as read: the quantiser would transpose it, int8 or not, under a name of its own
            node.input[1], trans_b.i = transposed(weight), 0
        if weight not in inits or not int8(weight):
            excluded += [node.name, f"{node.name}_MatMul"]  # a Gemm is quantised as the MatMul it becomes
            continue
        if node.op_type == "MatMul":
            node.input[1] = transposed(weight)
        quantised.add(node.input[1])
    used = {name for node in proto.graph.node for name in node.input}
    nodes = [node for node in proto.graph.node if node.output[0] not in transposes or node.output[0] in used]
    del proto.graph.node[:]
    proto.graph.node.extend(nodes)
    used = {name for node in proto.graph.node for name in node.input}
    kept = [init for init in proto.graph.initializer if init.name in used]
    del proto.graph.initializer[:]
    proto.graph.initializer.extend(kept)
    with tempfile.TemporaryDirectory() as tmp:
        float_path, int8_path = Path(tmp) / "float.onnx", Path(tmp) / "int8.onnx"
        float_path.write_bytes(proto.SerializeToString())
        level = logging.getLogger().level
        logging.getLogger().setLevel(logging.ERROR)  # its advice to pre-process, meant for static quantisation
        try:
            quantize_dynamic(float_path, int8_path, weight_type=QuantType.QInt8, op_types_to_quantize=["MatMul", "Gemm"],
                             per_channel=True, nodes_to_exclude=excluded)
        finally:
            logging.getLogger().setLevel(level)
        proto = onnx.load(int8_path)
    return _renamed_int8(proto, quantised).SerializeToString()


def _renamed_int8(proto, weights: set[str]):
    """`proto` with onnxruntime's names for each quantised weight (`<w>_quantized`, `_scale`,
    `_zero_point`) replaced by this project's (`<w>.int8`, `.int8.scale`, `.int8.zero`), the
    three stored as raw little-endian tensors (what `runtime.graphs` reads)."""
    from onnx import numpy_helper

    suffixes = {"_quantized": INT8, "_scale": SCALE, "_zero_point": ZERO}
    names = {f"{w}{old}": f"{w}{new}" for w in weights for old, new in suffixes.items()}
    inits = {init.name: init for init in proto.graph.initializer}
    unexpected = sorted(n for n in inits if n.endswith(tuple(suffixes)) and n not in names)
    missing = sorted(n for n in names if n not in inits) + sorted(w for w in weights if w in inits)
    if missing or unexpected:
        raise RuntimeError(f"onnxruntime's quantiser did not quantise the weights chosen for int8 as expected "
                           f"(left or named otherwise: {', '.join(missing[:3]) or 'none'}; quantised beside them: "
                           f"{', '.join(unexpected[:3]) or 'none'}); check the onnxruntime version against "
                           "torch_layer/export.py")
    for old, new in names.items():
        inits[old].CopyFrom(numpy_helper.from_array(numpy_helper.to_array(inits[old]), new))
    for node in proto.graph.node:
        node.input[:] = [names.get(name, name) for name in node.input]
    return proto


def _onnx(module: nn.Module, inputs: dict[str, torch.Tensor], outputs: dict[str, dict[int, str]],
          input_axes: dict[str, dict[int, str]] | None = None) -> bytes:
    """The graph of `module` on `inputs`; by default inputs vary in batch (and length when 3-d)."""
    axes = input_axes or {name: {0: BATCH, 1: FRAMES} if value.ndim == 3 else {0: BATCH}
                          for name, value in inputs.items()}
    axes = {**axes, **outputs}
    buffer = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation and tracer notes
        torch.onnx.export(module, tuple(inputs.values()), buffer, dynamo=False, opset_version=OPSET,
                          do_constant_folding=False,
                          input_names=list(inputs), output_names=list(outputs), dynamic_axes=axes)
    return buffer.getvalue()


def network_graphs(cfg: ModelConfig, weights: dict[str, np.ndarray], source: str, int8: bool = False
                   ) -> dict[str, bytes]:
    """The `expression` and `gesture` graphs of the UniEG network holding `weights`, their
    matrix products by weights in int8 if `int8` (a distilled student's: `_int8_matmuls`)."""
    model = UniEG(cfg)
    load_state_strict(model, weights, source)
    model.float().eval()
    b, t = 2, min(cfg.clip_len, 8)
    speech = {"speech": torch.randn(b, t, cfg.speech_dim)} if cfg.has_speech_input else {}
    style = torch.eye(cfg.style_dim)[:1].repeat(b, 1)
    null = torch.tensor([cfg.classifier_free, False])
    both = {0: BATCH, 1: FRAMES}
    nulls = {"null": null} if cfg.classifier_free else {}
    calls = {
        "expression": ({"expression": torch.randn(b, t, cfg.expression_dim), "timesteps": torch.tensor([960, 40]),
                        "mel": torch.rand(b, t, cfg.mel_dim), **speech, "style": style, **nulls},
                       {"eps": both, "audio": both}),
        "gesture": ({"gesture": torch.randn(b, t, cfg.gesture_dim), "timesteps": torch.tensor([960, 40]),
                     "audio": torch.rand(b, t, 2 * cfg.mel_dim), **speech,
                     "expression_x0": torch.randn(b, t, cfg.expression_dim), "style": style, **nulls,
                     "attend": torch.tensor([True, False])},
                    {"eps": both}),
    }
    graphs = {call: _onnx(_Call(model, call, list(inputs)), inputs, outputs)
              for call, (inputs, outputs) in calls.items()}
    return {call: _half_initializers(_int8_matmuls(graph) if int8 else graph) for call, graph in graphs.items()}


def _weights_left_out(graph: bytes, weights: dict[str, np.ndarray]) -> bytes:
    """The graph with each initializer left out, marked external data at `SUPPLIED`: the
    onnx backend makes it from `weights` when it opens the graph (`runtime.graphs.supplied_weights`,
    which gives each exactly the values the graph held: checked here)."""
    import onnx
    from onnx import numpy_helper

    proto = onnx.load_from_string(graph)
    try:
        made = supplied_weights([init.name for init in proto.graph.initializer], weights, MODEL_PREFIX)
    except ValueError as exc:
        raise RuntimeError(f"the graph holds an initializer the model's weights do not make ({exc}); check the "
                           "onnxruntime version against torch_layer/export.py") from None
    for init in proto.graph.initializer:
        value = numpy_helper.to_array(init)
        if made[init.name].dtype != value.dtype or not np.array_equal(made[init.name], value):
            raise RuntimeError(f"the graph's initializer {init.name} is not what the model's weights make "
                               "(runtime.graphs.supplied_weights); check the onnxruntime version against "
                               "torch_layer/export.py")
        name, kind, dims = init.name, init.data_type, list(init.dims)
        init.Clear()
        init.name, init.data_type, init.data_location = name, kind, onnx.TensorProto.EXTERNAL
        init.dims.extend(dims)
        init.external_data.add(key="location", value=SUPPLIED)
    return proto.SerializeToString()


def live_graphs(cfg: ModelConfig, weights: dict[str, np.ndarray], source: str) -> dict[str, bytes]:
    """The `expression` and `gesture` graphs live sessions run on onnxruntime: the network's,
    its products by weights in int8 (`_int8_matmuls`), holding no weights (`_weights_left_out`)."""
    return {call: _weights_left_out(graph, weights)
            for call, graph in network_graphs(cfg, weights, source, int8=True).items()}


def phonetic_graph(encoder_cfg, weights: dict[str, np.ndarray], source: str) -> bytes:
    """The `phonetic` graph: (1, n_mels, N) log-mel -> (N, phones) posteriors."""
    encoder = PhoneticEncoder(encoder_cfg)
    load_state_strict(encoder, weights, source)
    encoder.float().eval()
    return _half_initializers(_onnx(_Posteriors(encoder), {"mel": torch.randn(1, encoder_cfg.n_mels, 40)},
                                    {"posteriors": {0: FRAMES}}, {"mel": {2: FRAMES}}))


def with_graphs(bundle: ModelBundle) -> ModelBundle:
    """`bundle` (and its distilled student, `with_student_graphs`, and its languages' own faces)
    with ONNX graphs exported from its weights, its live graphs among them (replacing any it had)."""
    graphs = network_graphs(bundle.config, bundle.weights, bundle.source)
    bundle.live_graphs = live_graphs(bundle.config, bundle.weights, bundle.source)
    if bundle.phonetic is not None:
        graphs["phonetic"] = phonetic_graph(bundle.phonetic, bundle.phonetic_weights,
                                            f"{bundle.source} (phonetic encoder)")
    bundle.graphs = graphs
    bundle.networks.clear()
    for face in bundle.faces.values():
        face.graph = face_graph(bundle.config, {**bundle.weights, **face.weights}, bundle.source)
        face.weights = graph_weights({"expression": face.graph})
    bundle.languages.clear()
    if bundle.student is not None:
        with_student_graphs(bundle.student, graphs.get("phonetic"))
    return bundle


def face_graph(cfg: ModelConfig, weights: dict[str, np.ndarray], source: str) -> bytes:
    """A language's own face (`checkpoints.Face`): the `expression` graph of the network holding
    `weights`, its products by weights in int8 as a distilled student's are (`_int8_matmuls`:
    8.3 MB where float16 takes 13.4, which keeps the bundled file with its Mandarin face under
    60 MB). Its weights are what it holds, dequantised (`checkpoints.graph_weights`)."""
    return network_graphs(cfg, weights, source, int8=True)["expression"]


def with_student_graphs(student: ModelBundle, phonetic: bytes | None) -> ModelBundle:
    """A distilled student with graphs exported from its weights, its products by weights in
    int8 (`_int8_matmuls`), hearing through its teacher's `phonetic` graph; its weights become
    what its graphs hold, dequantised, so the torch backend runs those and the file stores each
    once."""
    student.graphs = {**network_graphs(student.config, student.weights, student.source, int8=True),
                      **({"phonetic": phonetic} if phonetic is not None else {})}
    student.weights = {**student.weights, **graph_weights(student.graphs)}
    student.networks.clear()
    return student


def main(argv: list[str] | None = None) -> int:
    """Add ONNX graphs to a model file (one exported before graphs were stored, or re-export them)."""
    import argparse

    from ..checkpoints import load_model, save_checkpoint

    parser = argparse.ArgumentParser(prog="python -m diffsheg_core export-onnx", description=main.__doc__)
    parser.add_argument("model", help="model file (.safetensors) of this project")
    parser.add_argument("--out", help="where to write it (default: over the input, atomically)")
    args = parser.parse_args(argv)
    bundle = load_model(args.model)
    if not bundle.source.endswith(".safetensors") or bundle.model_id.startswith("official-"):
        from ..errors import DiffshegError

        raise DiffshegError(f"{args.model}: only this project's .safetensors model files carry graphs; "
                            "official checkpoints run on the torch backend")
    path = save_checkpoint(with_graphs(bundle), args.out or args.model)
    print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB) with graphs {', '.join(bundle.graphs)}")
    return 0
