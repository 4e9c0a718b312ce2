"""ONNX export of a model's networks, so the torch-free runtime (onnxruntime) can run them.

Three graphs, each with dynamic batch and length: `expression` and `gesture` (the two
calls of one sampling step, `UniEG.expression` / `UniEG.gesture`) and, for models that
hear the phonetic encoder, `phonetic` (log-mel -> phone posteriors). They are exported
from float32 modules holding exactly the weights the file stores, so both backends run
the same numbers. Constant folding is left to onnxruntime (it folds when it loads a graph), so
every weight stays an initializer named after its parameter and the file stores it once, in
the graph (`checkpoints.graph_weights`). Needs torch and onnx (tooling: the trainer calls it
when it exports).
"""

from __future__ import annotations

import io
import warnings

import numpy as np
import torch
from torch import nn

from ..checkpoints import ModelBundle
from ..config import ModelConfig
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
        if init.data_type != onnx.TensorProto.FLOAT:
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
    return _half_initializers(buffer.getvalue())


def network_graphs(cfg: ModelConfig, weights: dict[str, np.ndarray], source: str) -> dict[str, bytes]:
    """The `expression` and `gesture` graphs of the UniEG network holding `weights`."""
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
    return {call: _onnx(_Call(model, call, list(inputs)), inputs, outputs)
            for call, (inputs, outputs) in calls.items()}


def phonetic_graph(encoder_cfg, weights: dict[str, np.ndarray], source: str) -> bytes:
    """The `phonetic` graph: (1, n_mels, N) log-mel -> (N, phones) posteriors."""
    encoder = PhoneticEncoder(encoder_cfg)
    load_state_strict(encoder, weights, source)
    encoder.float().eval()
    return _onnx(_Posteriors(encoder), {"mel": torch.randn(1, encoder_cfg.n_mels, 40)},
                 {"posteriors": {0: FRAMES}}, {"mel": {2: FRAMES}})


def with_graphs(bundle: ModelBundle) -> ModelBundle:
    """`bundle` (and its distilled student) with ONNX graphs exported from its weights
    (replacing any it had)."""
    graphs = network_graphs(bundle.config, bundle.weights, bundle.source)
    if bundle.phonetic is not None:
        graphs["phonetic"] = phonetic_graph(bundle.phonetic, bundle.phonetic_weights,
                                            f"{bundle.source} (phonetic encoder)")
    bundle.graphs = graphs
    bundle.networks.clear()
    student = bundle.student
    if student is not None:  # it hears through the same phonetic encoder
        student.graphs = {**network_graphs(student.config, student.weights, student.source),
                          **({"phonetic": graphs["phonetic"]} if "phonetic" in graphs else {})}
        student.networks.clear()
    return bundle


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
