"""A language's own face: add one to a model file, or take one out (issue 42).

A model's face is shared by every language. The bundled model's was fine-tuned on a real
captured Mandarin face with English rehearsed beside it, and one set of face weights trades
one language's jaw for the other's (the model card, "Where the limit is"). A language's own
face is the model's expression branch fine-tuned on that language's captured faces alone
(`trains = "face"` from the model itself: weights/default_face_zh_own.toml). Added to the model
file it sits beside the shared face, and a job that names the language (`language` in the
settings, `--language`, the add-on's Language) runs it in its place; every other job runs the
model as it was, to the bit. The body is the model's own, fed the language's face.

    python -m diffsheg_core add-face MODEL TUNED --language zh
    python -m diffsheg_core add-face MODEL --remove zh
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np

from ..checkpoints import Face, ModelBundle, graph_weights, load_model, save_checkpoint
from ..errors import DiffshegError
from ..torch_layer.export import face_graph
from ..validate import check_language


def add_face(model: ModelBundle, tuned: ModelBundle, language: str) -> ModelBundle:
    """`model` with `tuned`'s expression branch as `language`'s own face (replacing one it had),
    stored as `torch_layer.export.face_graph` exports it (its products by weights in int8).
    Refuses a `tuned` that is not `model` with its face alone fine-tuned."""
    language = check_language(language)
    for bundle in (model, tuned):
        if "expression" not in bundle.graphs:
            raise DiffshegError(f"{bundle.source} carries no ONNX graphs: export them first "
                                f"(python -m diffsheg_core export-onnx {bundle.source})")
    if tuned.config != model.config:
        raise DiffshegError(f"{tuned.source} has another network than {model.source} (its configuration differs): a "
                            f"language's face is {model.source} fine-tuned on its face alone; train it with "
                            "init_from set to that file and trains = \"face\"")
    face = graph_weights({"expression": tuned.graphs["expression"]})
    outside = sorted(k for k in {*model.weights, *tuned.weights} - set(face)
                     if k not in model.weights or k not in tuned.weights
                     or not (np.array_equal(model.weights[k], tuned.weights[k]) or _counter(tuned.weights[k])))
    problem = (f"weights outside the face: {', '.join(outside[:3])}{' ...' if len(outside) > 3 else ''}" if outside
               else "its phonetic encoder" if not _same(model.phonetic_weights, tuned.phonetic_weights)
               else "its normalisation statistics" if not _same({"mean": model.mean, "std": model.std},
                                                                {"mean": tuned.mean, "std": tuned.std})
               else None)
    if problem:
        raise DiffshegError(f"{tuned.source} differs from {model.source} beyond the face ({problem}): a language's "
                            f"face is {model.source} fine-tuned on its face alone; train it with init_from and "
                            "phonetic set to that file and trains = \"face\", then add it")
    record = {"model_id": tuned.model_id, **{k: tuned.info[k] for k in ("trained_steps", "data", "datasets")
                                             if k in tuned.info}}
    graph = face_graph(model.config, {**model.weights, **{k: tuned.weights[k] for k in face}}, tuned.source)
    return replace(model, faces={**model.faces, language: Face(graph, graph_weights({"expression": graph}), record)})


def _same(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> bool:
    return a.keys() == b.keys() and all(np.array_equal(v, b[k]) for k, v in a.items())


def _counter(weight: np.ndarray) -> bool:
    """A batch norm's count of the batches it saw in training (`num_batches_tracked`): the only
    whole-number weights, which change in any fine-tune and nothing the network computes."""
    return weight.dtype.kind in "iu"


def remove_face(model: ModelBundle, language: str) -> ModelBundle:
    """`model` without `language`'s own face."""
    language = check_language(language)
    if language not in model.faces:
        raise DiffshegError(f"{model.source} has no face of its own for '{language}' (it has: "
                            f"{', '.join(sorted(model.faces)) or 'none'}): nothing to remove")
    return replace(model, faces={k: v for k, v in model.faces.items() if k != language})


def main(argv: list[str] | None = None) -> int:
    """Add a language's own face to a model file, or remove one."""
    parser = argparse.ArgumentParser(prog="python -m diffsheg_core add-face", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", help="this project's model file (.safetensors) to add the face to")
    parser.add_argument("tuned", nargs="?",
                        help="that model with its face fine-tuned on the language (trains = \"face\")")
    parser.add_argument("--language", help="the language's code (zh, pt-br): what a job names to run the face")
    parser.add_argument("--remove", metavar="LANGUAGE", help="take the language's own face out instead")
    parser.add_argument("--out", help="where to write the model (default: over MODEL, atomically)")
    args = parser.parse_args(argv)
    if (args.remove is None) == (args.tuned is None or args.language is None):
        parser.error("give TUNED and --language to add a face, or --remove LANGUAGE alone")
    model = load_model(args.model)
    if not model.source.endswith(".safetensors"):
        raise DiffshegError(f"{args.model}: only this project's .safetensors model files carry languages' faces")
    if args.remove is not None:
        model = remove_face(model, args.remove)
    else:
        model = add_face(model, load_model(args.tuned), args.language)
    path = save_checkpoint(model, args.out or args.model)
    print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB); its languages' own faces: "
          f"{', '.join(sorted(model.faces)) or 'none'}")
    return 0
