"""Model files: the bundled default, our own checkpoints, and the official DiffSHEG ones.

A `ModelBundle` is everything generation needs besides audio: the network's weights and
its ONNX graphs, its normalisation statistics, its default sampling settings and where it
came from. It holds numpy arrays and bytes only; `runtime.backends` runs it.

Our format is a safetensors file (no pickle): tensors `model.*` (the network, for the
torch backend), `norm.mean`, `norm.std`, `onnx.*` (the exported graphs as bytes, for the
onnxruntime backend), optionally `phonetic.*` (the phonetic encoder) and `prior.*` (the
gesture prior), and JSON metadata (config, sampling, guidance scales, model id, model
card). A weight a graph holds under its own name (graphs exported without constant folding
hold them all) is stored there only: `model.*` keeps the rest, and loading reads the network's
weights back from both. A model may carry a distilled student (`ModelBundle.student`, see
`training.distill`): its graphs are `onnx.student.*`, its weights outside them `student.*`,
and the metadata's `student` says what it was distilled from. `onnx.live.*` are the network's
graphs with their products in int8, which live sessions run (`ModelBundle.live_graphs`): they
hold no weights, each made from the network's when they are opened. A model may carry faces of
their own for some languages (`ModelBundle.faces`, `faces.py`): each its expression branch
fine-tuned on that language's captured faces, stored as the graph `onnx.face.<language>.expression`
(its weights outside it `face.<language>.*`), named in the metadata's `faces`. Reading it needs numpy and
safetensors only. Official checkpoints are torch pickles holding the state dict under
`encoder`; they need torch, are read with `weights_only=True` (in `torch_layer.official`) and
loaded strictly by `official_checkpoints`, which knows their format, configuration and
normalisation statistics; `load_model` tells the two apart.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Optional

import numpy as np

from .config import ModelConfig
from .errors import CheckpointError
from .files import atomic_write
from .foppas import FoppasConfig
from .official_checkpoints import OFFICIAL, STATS_ENV, STYLE_KEY, load_official, official_shapes
from .phonetic import PhoneticConfig
from .prior import GesturePrior
from .rigs import Layout, get_layout
from .runtime.graphs import check_supplied, left_out, named_weights, read_graph
from .style import style_names_fit

FORMAT = "diffsheg-core/1"
WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
DEFAULT_WEIGHTS = WEIGHTS_DIR / "default.safetensors"
MODEL_PREFIX, PHONETIC_PREFIX, GRAPH_PREFIX, STUDENT_PREFIX, LIVE_PREFIX = "model.", "phonetic.", "onnx.", "student.", "live."
FACE_PREFIX = "face."  # a language's own face: its graph onnx.face.<language>.expression, its other weights face.<language>.*
NETWORK_GRAPHS = ("expression", "gesture")  # the graphs that hold the network's weights (export names them model.*)
TORCH_HOW_TO = ("install torch: in Blender, Edit > Preferences > Add-ons > DiffSHEG > Install GPU "
                "support; elsewhere `pip install torch==2.13.0` (README, GPU)")


@dataclass
class Face:
    """A language's own face (issue 42): the model's expression branch fine-tuned on that
    language's captured faces (`trains = "face"`), which takes the shared branch's place when
    a job asks for the language (`ModelBundle.for_language`). The body is the model's own."""

    graph: bytes                     # its ONNX expression graph, products by weights in int8 (export.face_graph)
    weights: dict[str, np.ndarray]   # the expression branch's weights: what its graph holds (dequantised), and any it does not
    record: dict                     # what it is: model_id of the run it came from, and what that trained on


@dataclass
class ModelBundle:
    config: ModelConfig
    weights: dict[str, np.ndarray]   # the network's state dict (torch backend, re-export)
    mean: np.ndarray                 # (D,) normalisation, gesture then expression
    std: np.ndarray
    sampling: FoppasConfig
    guidance: Optional[float] = None  # default classifier-free scale (None: unguided)
    skip_guidance: Optional[float] = None  # default gesture skip-guidance scale (None: off; see guidance.py)
    model_id: str = "unnamed"
    trained: bool = True
    info: dict = field(default_factory=dict)
    phonetic: Optional[PhoneticConfig] = None  # the speech encoder of models with speech_encoder "phonetic"
    phonetic_weights: dict[str, np.ndarray] = field(default_factory=dict)
    prior: Optional[GesturePrior] = None  # where later FOPPAS windows start from (see prior.py)
    graphs: dict[str, bytes] = field(default_factory=dict)  # ONNX: expression, gesture[, phonetic]
    source: str = "model"            # how messages name it (its file)
    # a few-step student distilled from this model's guided sampling: a bundle of its own that
    # shares this one's config, statistics, prior and phonetic encoder, unguided, with what it was
    # distilled at in its info["distilled"] (see pipeline.make_plan for when it samples)
    student: Optional["ModelBundle"] = None
    # ONNX: expression and gesture with their products by weights in int8, which live sessions
    # run on onnxruntime (runtime.backends.live_network); they hold no weights of their own: each
    # is made from `weights` when they are opened (runtime.graphs.supplied_weights)
    live_graphs: dict[str, bytes] = field(default_factory=dict)
    faces: dict[str, Face] = field(default_factory=dict)  # {language code: its own face} (see Face)
    networks: dict = field(default_factory=dict, init=False, repr=False, compare=False)  # opened backends (runtime)
    languages: dict = field(default_factory=dict, init=False, repr=False, compare=False)  # for_language's bundles

    @property
    def layout(self) -> Layout:
        return get_layout(self.config.layout)

    @property
    def rig_layout(self) -> Layout:
        """The layout of the rig its motion is on, whose joints the model makes above the hips
        (a whole-body model's `beat_body`: `beat`); what live frames and rig mappings are laid out in."""
        return get_layout(self.layout.rig)

    @property
    def style_names(self) -> list[str]:
        """Names of the style classes (models trained with named styles; else none)."""
        return list(self.info.get("style_names", []))

    @property
    def default_style(self) -> "int | str":
        """The style generation uses when none is asked for (`default_style` of the training)."""
        return self.info.get("default_style", 0)

    @property
    def null_style(self) -> bool:
        """The model learned the null style (all zeros), which style guidance needs."""
        return bool(self.info.get("null_style", False))

    def for_language(self, language: Optional[str]) -> "ModelBundle":
        """The model a job in `language` runs: this one with that language's own face in place
        of the shared one (`faces`; made once, and its opened networks kept with it), or this
        one for None. Its fast sampling runs its own guided steps: the distilled student learnt
        the shared face."""
        if language is None:
            return self
        face = self.faces.get(language)
        if face is None:
            held = ", ".join(sorted(self.faces)) or "none"
            raise CheckpointError(f"{self.source} has no face of its own for language '{language}' (it has: "
                                  f"{held}): leave the language unset for the model's shared face, which serves "
                                  "every language")
        if language not in self.languages:
            self.languages[language] = replace(
                self, weights={**self.weights, **face.weights}, graphs={**self.graphs, "expression": face.graph},
                student=None, faces={}, source=f"{self.source} ({language} face)")
        return self.languages[language]

    @property
    def has_graphs(self) -> bool:
        """The file carries every ONNX graph sampling needs (the onnxruntime backend can run it)."""
        needed = {"expression", "gesture"} | ({"phonetic"} if self.config.phonetic_input else set())
        return needed <= set(self.graphs)

    @property
    def centre(self) -> np.ndarray:
        """(D,) the motion the network's zero stands for: the normalisation mean, its arms moved by
        the model's calibrated arm posture (info["arm_posture"], in normalised units; see
        training.calibrate), so that every sampling's arms sit on average where its training
        data's do. Without one, the mean."""
        arms = self.info.get("arm_posture")
        if arms is None:
            return self.mean
        centre = self.mean.copy()
        centre[: len(arms)] += self.std[: len(arms)] * np.asarray(arms, np.float32)
        return centre

    def normalise(self, motion: np.ndarray) -> np.ndarray:
        return (motion - self.centre) / self.std

    def denormalise(self, motion: np.ndarray) -> np.ndarray:
        out = motion * self.std
        out += self.centre  # in place: one array the size of the motion, not two
        return out


# ---------------------------------------------------------------- our format

def write_safetensors(tensors: dict[str, np.ndarray], meta: dict[str, str], path: str | Path) -> Path:
    """Write atomically: a run killed mid-write leaves the previous file, not a broken one."""
    from safetensors.numpy import save

    path = Path(path)
    data = save({k: np.require(v, requirements="C") for k, v in tensors.items()}, metadata=meta)
    with atomic_write(path) as fh:
        fh.write(data)
    return path


def read_safetensors(path: Path, fix: str) -> tuple[dict[str, str], dict[str, np.ndarray]]:
    """Metadata and tensors (numpy) of a safetensors file; a damaged file raises
    CheckpointError ending in `fix`."""
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="numpy") as fh:
            return fh.metadata() or {}, {k: fh.get_tensor(k) for k in fh.keys()}
    except Exception as exc:  # safetensors raises several types for damaged files
        raise CheckpointError(f"{path}: cannot read this safetensors file ({exc}); {fix}") from exc


MAX_WEIGHT = 1e6  # trained weights stay within a few hundred; past this a file is damaged


def check_weights(tensors: dict[str, np.ndarray], source: str) -> None:
    """Refuse NaN, infinite or exploding floating-point values, naming the tensors."""
    bad = []
    for name, value in tensors.items():
        if value.dtype.kind != "f" or value.size == 0:
            continue
        values = value.astype(np.float32, copy=False)
        if not np.isfinite(values).all():
            bad.append(f"{name} (NaN or infinite)")
        elif float(np.abs(values).max()) > MAX_WEIGHT:
            bad.append(f"{name} (values up to {float(np.abs(values).max()):.3g})")
    if bad:
        shown = ", ".join(bad[:5]) + (f" and {len(bad) - 5} more" if len(bad) > 5 else "")
        raise CheckpointError(f"{source}: damaged weights in {shown}: the file is corrupt or its "
                              "training diverged; download or export it again")


def _json(meta: dict[str, str], key: str, default: Optional[str], path: Path):
    """The JSON value of metadata `key` (`default` if absent; None: required, KeyError)."""
    try:
        return json.loads(meta[key] if default is None else meta.get(key, default))
    except ValueError as exc:
        raise CheckpointError(f"{path}: its metadata '{key}' is not valid JSON ({exc}); the file is "
                              "damaged: download or export it again") from None


def _prefixed(tensors: dict[str, np.ndarray], prefix: str) -> dict[str, np.ndarray]:
    return {k[len(prefix):]: v for k, v in tensors.items() if k.startswith(prefix)}


def graph_weights(graphs: dict[str, bytes]) -> dict[str, np.ndarray]:
    """The network weights the graphs hold under their own names."""
    held: dict[str, np.ndarray] = {}
    for name in NETWORK_GRAPHS:
        if name in graphs:
            held.update(named_weights(graphs[name], MODEL_PREFIX))
    return held


def _stored_apart(weights: dict[str, np.ndarray], graphs: dict[str, bytes]) -> dict[str, np.ndarray]:
    """The weights the graphs do not hold exactly (same name, type and values)."""
    held = graph_weights(graphs)
    return {k: np.asarray(v) for k, v in weights.items()
            if not (k in held and held[k].dtype == np.asarray(v).dtype and np.array_equal(held[k], v))}


def save_checkpoint(bundle: ModelBundle, path: str | Path) -> Path:
    tensors = {f"{MODEL_PREFIX}{k}": v for k, v in _stored_apart(bundle.weights, bundle.graphs).items()}
    tensors["norm.mean"] = np.asarray(bundle.mean, dtype=np.float32)
    tensors["norm.std"] = np.asarray(bundle.std, dtype=np.float32)
    tensors.update({f"{PHONETIC_PREFIX}{k}": np.asarray(v) for k, v in bundle.phonetic_weights.items()})
    tensors.update({f"{GRAPH_PREFIX}{k}": np.frombuffer(v, np.uint8) for k, v in bundle.graphs.items()})
    if bundle.prior is not None:
        tensors.update(bundle.prior.tensors())
    meta = {
        "format": FORMAT,
        "config": json.dumps(bundle.config.to_dict()),
        "sampling": json.dumps(asdict(bundle.sampling)),
        "guidance": json.dumps(bundle.guidance),
        "skip_guidance": json.dumps(bundle.skip_guidance),
        "model_id": bundle.model_id,
        "trained": json.dumps(bundle.trained),
        "info": json.dumps(bundle.info, default=str),
        **({"phonetic": bundle.phonetic.metadata()} if bundle.phonetic is not None else {}),
    }
    tensors.update({f"{GRAPH_PREFIX}{LIVE_PREFIX}{k}": np.frombuffer(v, np.uint8) for k, v in bundle.live_graphs.items()})
    student = bundle.student
    if student is not None:
        tensors.update({f"{STUDENT_PREFIX}{k}": v for k, v in _stored_apart(student.weights, student.graphs).items()})
        tensors.update({f"{GRAPH_PREFIX}{STUDENT_PREFIX}{k}": np.frombuffer(student.graphs[k], np.uint8)
                        for k in NETWORK_GRAPHS})
        meta["student"] = json.dumps({"model_id": student.model_id, "info": student.info}, default=str)
    for language, face in bundle.faces.items():
        prefix = f"{FACE_PREFIX}{language}."
        tensors[f"{GRAPH_PREFIX}{prefix}expression"] = np.frombuffer(face.graph, np.uint8)
        tensors.update({prefix + k: v for k, v in _stored_apart(face.weights, {"expression": face.graph}).items()})
    if bundle.faces:
        meta["faces"] = json.dumps({language: face.record for language, face in bundle.faces.items()}, default=str)
    return write_safetensors(tensors, meta, path)


def _network_weights(stored: dict[str, np.ndarray], graphs: dict[str, bytes], path: Path, what: str
                     ) -> dict[str, np.ndarray]:
    """A network's weights: those stored apart and those its graphs hold."""
    try:
        weights = {**graph_weights(graphs), **stored}
    except ValueError as exc:
        raise CheckpointError(f"{path}: the ONNX graphs of its {what} are damaged ({exc}); download or export "
                              "the model again") from None
    if not weights:
        raise CheckpointError(f"{path}: the file holds no weights of its {what} ({MODEL_PREFIX}* or in its graphs); "
                              "export it again")
    check_weights(weights, f"{path} ({what})")
    return weights


def _stored_student(teacher: ModelBundle, meta: dict, tensors: dict, graphs: dict, path: Path
                    ) -> Optional[ModelBundle]:
    """The distilled student a file carries (None: none)."""
    own = {k[len(STUDENT_PREFIX):]: v for k, v in graphs.items() if k.startswith(STUDENT_PREFIX)}
    if "student" not in meta and not own:
        return None
    record = _json(meta, "student", "null", path)
    if not isinstance(record, dict) or set(own) != set(NETWORK_GRAPHS) \
            or not isinstance(record.get("info", {}).get("distilled"), dict):
        raise CheckpointError(f"{path}: its distilled student is incomplete (it needs the graphs "
                              f"{', '.join(GRAPH_PREFIX + STUDENT_PREFIX + g for g in NETWORK_GRAPHS)} and the "
                              "metadata 'student' saying what it was distilled at); export it again")
    for key, what in (("posture", "posture"), ("first_posture", "first window's posture")):
        _check_posture(record["info"].get(key), teacher.config.gesture_dim, path, f"its distilled student's {what}")
    weights = _network_weights(_prefixed(tensors, STUDENT_PREFIX), own, path, "distilled student")
    if "phonetic" in teacher.graphs:  # the student hears through the teacher's encoder
        own["phonetic"] = teacher.graphs["phonetic"]
    return replace(teacher, weights=weights, graphs=own, live_graphs={}, guidance=None, skip_guidance=None,
                   model_id=str(record.get("model_id", f"{teacher.model_id}-student")), info=record["info"],
                   student=None, source=f"{path} (distilled student)")


def _load_ours(path: Path) -> ModelBundle:
    meta, tensors = read_safetensors(path, "it may be truncated: download or export it again")
    if meta.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not a diffsheg-core checkpoint (format tag "
                              f"{meta.get('format')!r}, expected {FORMAT!r})")
    try:
        cfg = ModelConfig.from_dict(_json(meta, "config", None, path))
        sampling = FoppasConfig(**_json(meta, "sampling", None, path))
        mean, std = tensors.pop("norm.mean"), tensors.pop("norm.std")
    except (KeyError, ValueError, TypeError) as exc:
        raise CheckpointError(f"{path}: checkpoint metadata is incomplete ({exc}); export it again") from None
    check_weights({"norm.mean": mean, "norm.std": std, **tensors}, str(path))
    if not (std > 0).all():
        raise CheckpointError(f"{path}: its normalisation std holds zero or negative values; export it again")
    phonetic = _stored_phonetic(cfg, meta, tensors, path)
    graphs = {k: v.tobytes() for k, v in _prefixed(tensors, GRAPH_PREFIX).items()}
    _check_graphs(graphs, cfg, phonetic.get("phonetic"), path)
    weights = _network_weights(_prefixed(tensors, MODEL_PREFIX), graphs, path, "network")
    info = _json(meta, "info", "{}", path)
    if not isinstance(info, dict):
        raise CheckpointError(f"{path}: its metadata 'info' is a JSON {type(info).__name__}, not an object: "
                              f"the file was edited or damaged; export it again from its training run")
    _check_styles(info, cfg.style_dim, path)
    for key, what in (("live_posture", "live posture"), ("arm_posture", "arm posture")):
        _check_posture(info.get(key), cfg.gesture_dim, path, f"its {what}")
    bundle = ModelBundle(
        config=cfg, weights=weights, mean=mean, std=std, sampling=sampling,
        guidance=_json(meta, "guidance", "null", path),
        skip_guidance=_json(meta, "skip_guidance", "null", path), model_id=meta.get("model_id", path.stem),
        trained=_json(meta, "trained", "true", path), info=info,
        **phonetic, prior=_stored_prior(cfg, tensors, path),
        graphs={k: v for k, v in graphs.items() if not k.startswith((STUDENT_PREFIX, LIVE_PREFIX, FACE_PREFIX))},
        live_graphs=_stored_live(graphs, weights, path), source=str(path))
    bundle.student = _stored_student(bundle, meta, tensors, graphs, path)
    bundle.faces = _stored_faces(bundle, meta, tensors, graphs, path)
    return bundle


def _stored_faces(bundle: ModelBundle, meta: dict, tensors: dict, graphs: dict, path: Path) -> dict[str, Face]:
    """The languages' own faces a file carries ({}: none), each checked to be the model's
    expression branch: the same weights by name and shape."""
    records = _json(meta, "faces", "{}", path)
    own = {k[len(FACE_PREFIX):]: v for k, v in graphs.items() if k.startswith(FACE_PREFIX)}
    if not isinstance(records, dict) or not all(isinstance(r, dict) for r in records.values()) \
            or set(own) != {f"{language}.expression" for language in records}:
        raise CheckpointError(f"{path}: its languages' own faces are incomplete (each language the metadata "
                              f"'faces' names needs the graph {GRAPH_PREFIX}{FACE_PREFIX}<language>.expression, "
                              "and only that); export it again")
    shared = graph_weights({"expression": bundle.graphs["expression"]}) if "expression" in bundle.graphs else {}
    faces = {}
    for language, record in records.items():
        graph = own[f"{language}.expression"]
        apart = _prefixed(tensors, f"{FACE_PREFIX}{language}.")
        weights = _network_weights(apart, {"expression": graph}, path, f"{language} face")
        held = set(weights) - set(apart)
        wrong = sorted(set(held) ^ set(shared)) + sorted(
            k for k, v in weights.items() if k not in bundle.weights or v.shape != bundle.weights[k].shape)
        if wrong:
            raise CheckpointError(f"{path}: refused: its {language} face is not this model's expression branch "
                                  f"({', '.join(wrong[:3])} differ{'s' if len(wrong) == 1 else ''} in name or "
                                  "shape): the file was edited or mixes two models; add the face again "
                                  "(python -m diffsheg_core add-face)")
        faces[language] = Face(graph=graph, weights=weights, record=record)
    return faces


def _stored_live(graphs: dict[str, bytes], weights: dict[str, np.ndarray], path: Path) -> dict[str, bytes]:
    """The live graphs a file carries ({} none), each weight they leave out one the network's
    weights make (so onnxruntime reads no file for it)."""
    live = {k[len(LIVE_PREFIX):]: v for k, v in graphs.items() if k.startswith(LIVE_PREFIX)}
    if live and set(live) != set(NETWORK_GRAPHS):
        raise CheckpointError(f"{path}: its live graphs are incomplete (it needs "
                              f"{', '.join(GRAPH_PREFIX + LIVE_PREFIX + g for g in NETWORK_GRAPHS)}); export it again")
    for name, graph in live.items():
        try:
            check_supplied(left_out(graph), weights, MODEL_PREFIX)
        except ValueError as exc:
            raise CheckpointError(f"{path}: refused: its live ONNX graph '{name}' leaves out what the model's "
                                  f"weights do not make ({exc}): the file was edited or mixes two models; export "
                                  "it again") from None
    return live


def _check_posture(posture: object, gesture_dim: int, path: Path, what: str) -> None:
    """A calibrated posture (training.calibrate) is None or one finite number per gesture channel."""
    if posture is not None and (not isinstance(posture, list) or len(posture) != gesture_dim or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in posture)):
        raise CheckpointError(f"{path}: {what} must be {gesture_dim} finite numbers, one per gesture channel: the "
                              "file was edited or damaged; take it again from its training run and calibrate that "
                              "(python -m diffsheg_core.training.calibrate)")


def _check_styles(info: dict, style_dim: int, path: Path) -> None:
    """The style names and default style in `info` fit the model's `style_dim` styles."""
    names, default = info.get("style_names", []), info.get("default_style", 0)
    if not style_names_fit(names, style_dim):
        raise CheckpointError(f"{path}: its style names {names!r} are not {style_dim} different names "
                              "(text), one per style of the model: the file was edited or damaged; export "
                              "it again from its training run")
    if not (default in names if isinstance(default, str) else
            isinstance(default, int) and not isinstance(default, bool) and 0 <= default < style_dim):
        raise CheckpointError(f"{path}: its default style {default!r} is not one of its styles "
                              f"({', '.join(names) or f'indices 0 to {style_dim - 1}'}): the file was edited "
                              "or damaged; export it again from its training run")


def _graph_inputs(cfg: ModelConfig, phonetic: Optional[PhoneticConfig]) -> dict[str, dict[str, tuple]]:
    """{graph: {input: (element type, shape)}} as export.py writes them; None: an axis that varies."""
    frames = (None, None)  # batch, frames
    speech = {"speech": ("float32", (*frames, cfg.speech_dim))} if cfg.has_speech_input else {}
    null = {"null": ("bool", (None,))} if cfg.classifier_free else {}
    common = {"timesteps": ("int64", (None,)), **speech, "style": ("float32", (None, cfg.style_dim)), **null}
    graphs = {"expression": {"expression": ("float32", (*frames, cfg.expression_dim)),
                             "mel": ("float32", (*frames, cfg.mel_dim)), **common},
              "gesture": {"gesture": ("float32", (*frames, cfg.gesture_dim)),
                          "audio": ("float32", (*frames, 2 * cfg.mel_dim)),
                          "expression_x0": ("float32", (*frames, cfg.expression_dim)), **common,
                          "attend": ("bool", (None,))}}
    graphs.update({prefix + name: graphs[name] for name in NETWORK_GRAPHS  # a distilled student's, live's
                   for prefix in (STUDENT_PREFIX, LIVE_PREFIX)})
    if phonetic is not None:
        graphs["phonetic"] = {"mel": ("float32", (1, phonetic.n_mels, None))}
    return graphs


def _fits(found: tuple, wanted: tuple) -> bool:
    """An input the graph declares as `found` (element type, shape) takes `wanted`."""
    (found_type, found_shape), (wanted_type, wanted_shape) = found, wanted
    return found_type == wanted_type and len(found_shape) == len(wanted_shape) and all(
        w is None or not isinstance(f, int) or f == w for f, w in zip(found_shape, wanted_shape))


def _check_graphs(graphs: dict[str, bytes], cfg: ModelConfig, phonetic: Optional[PhoneticConfig],
                  path: Path) -> None:
    """Refuse ONNX graphs that refer to external data (onnxruntime would read those files
    relative to the working directory; a live graph's, made from the weights instead, are
    checked by `_stored_live`) or whose inputs disagree with the metadata, naming what
    disagrees. Read without the onnx package (runtime.graphs)."""
    expected = _graph_inputs(cfg, phonetic)
    for name, graph in graphs.items():
        try:
            found = read_graph(graph)
        except ValueError as exc:
            raise CheckpointError(f"{path}: its ONNX graph '{name}' is damaged ({exc}); download or export "
                                  "the model again") from None
        if found.external and not name.startswith(LIVE_PREFIX):  # a live graph's are checked by _stored_live
            raise CheckpointError(
                f"{path}: refused: its ONNX graph '{name}' refers to external data files (tensor "
                f"{', '.join(found.external[:3])}); our model files hold all their weights and never use "
                "external data, so this file was edited or is not one of ours: download or export it again")
        wanted = expected.get(name.rsplit(".", 1)[-1] if name.startswith(FACE_PREFIX) else name)  # a face: expression
        if wanted is None:
            raise CheckpointError(f"{path}: it holds an ONNX graph '{name}' that no model of ours has "
                                  f"(expected {', '.join(expected)}): the file was edited; export it again")
        problems = [f"missing inputs {', '.join(sorted(set(wanted) - set(found.inputs)))}"] \
            if set(wanted) - set(found.inputs) else []
        problems += [f"unexpected inputs {', '.join(sorted(set(found.inputs) - set(wanted)))}"] \
            if set(found.inputs) - set(wanted) else []
        problems += [f"input '{k}' is {_shown(found.inputs[k])} where the metadata's config gives {_shown(v)}"
                     for k, v in wanted.items() if k in found.inputs and not _fits(found.inputs[k], v)]
        if problems:
            raise CheckpointError(f"{path}: its metadata and its ONNX graph '{name}' disagree: "
                                  f"{'; '.join(problems)}; the file was edited or mixes two models: export it "
                                  "again from its training run")


def _shown(spec: tuple) -> str:
    kind, shape = spec
    return f"{kind} ({', '.join('?' if d is None else str(d) for d in shape)})"


def _stored_phonetic(cfg: ModelConfig, meta: dict, tensors: dict, path: Path) -> dict:
    if not cfg.phonetic_input:
        return {}
    weights = _prefixed(tensors, PHONETIC_PREFIX)
    if "phonetic" not in meta or not weights:
        raise CheckpointError(f"{path}: the model takes phonetic features but the file holds no phonetic "
                              "encoder; export it again from its training run")
    phonetic = PhoneticConfig.from_metadata(meta["phonetic"], f"{path} (phonetic encoder)")
    if phonetic.dim != cfg.speech_dim:
        raise CheckpointError(f"{path}: its phonetic encoder gives {phonetic.dim} features per frame but "
                              f"the network takes {cfg.speech_dim}; export it again")
    return {"phonetic": phonetic, "phonetic_weights": weights}


def _stored_prior(cfg: ModelConfig, tensors: dict, path: Path) -> Optional[GesturePrior]:
    prior = GesturePrior.from_tensors(tensors, str(path))
    if prior is not None and (prior.dims != cfg.gesture_dim or prior.max_len < cfg.clip_len):
        raise CheckpointError(f"{path}: its gesture prior covers {prior.dims} channels over "
                              f"{prior.max_len} frames, but the model has {cfg.gesture_dim} gesture "
                              f"channels in {cfg.clip_len}-frame windows; export it again")
    return prior


# ---------------------------------------------------------------- the default and entry point

def is_ours(path: Path) -> bool:
    """Whether `path` is in our safetensors format (by name, or by its JSON header), not an
    official DiffSHEG torch pickle."""
    if path.suffix == ".safetensors":
        return True
    with open(path, "rb") as fh:
        return fh.read(16)[8:9] == b"{"


def _model_file(source: str | Path | None) -> Path:
    return DEFAULT_WEIGHTS if source is None else Path(source).expanduser()


def _stored_metadata(source: str | Path | None) -> Optional[dict]:
    """The metadata of one of our model files (None: the bundled default) without reading
    the weights; None for official checkpoints and files that cannot tell."""
    path = _model_file(source)
    if not path.is_file() or not is_ours(path):
        return None
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="numpy") as fh:
            return dict(fh.metadata() or {})
    except Exception:  # damaged files are reported when they load
        return None


def _stored_config(meta: Optional[dict]) -> Optional[ModelConfig]:
    """The network configuration in one of our files' metadata (None: none, or unreadable)."""
    try:
        return ModelConfig.from_dict(json.loads(meta["config"])) if meta else None
    except Exception:
        return None


def stored_rig(source: str | Path | None = None) -> Optional[str]:
    """The rig (its layout's skeleton: what presets map) of one of our model files from its
    metadata alone (None: official checkpoints, whose layout shows in their tensors, and
    files that cannot tell)."""
    cfg = _stored_config(_stored_metadata(source))
    return get_layout(cfg.layout).rig if cfg else None


def stored_style_names(source: str | Path | None = None) -> list[str]:
    """The style names of one of our model files from its metadata alone ([] when it has
    none, or names that do not fit its styles, which loading it reports)."""
    meta = _stored_metadata(source)
    cfg = _stored_config(meta)
    if cfg is None:
        return []
    try:
        names = json.loads(meta.get("info", "{}")).get("style_names", [])
    except Exception:
        return []
    return names if style_names_fit(names, cfg.style_dim) else []


def stored_face_languages(source: str | Path | None = None) -> list[str]:
    """The languages a model file carries a face of its own for (`ModelBundle.faces`), from its
    metadata alone ([] when it has none or cannot tell; loading it reports a damaged file)."""
    try:
        faces = json.loads((_stored_metadata(source) or {}).get("faces", "{}"))
    except ValueError:
        return []
    return sorted(faces) if isinstance(faces, dict) else []


def stored_style_count(source: str | Path | None = None) -> Optional[int]:
    """The number of style classes of a model file without reading its weights: from our
    files' metadata, from the shapes in an official checkpoint (no torch needed); None when
    the file cannot tell."""
    cfg = _stored_config(_stored_metadata(source))
    if cfg is not None:
        return cfg.style_dim
    shape = official_shapes(_model_file(source)).get(STYLE_KEY)
    return shape[1] if shape and len(shape) == 2 else None


def files_read(source: str | Path | None = None, stats_dir: str | Path | None = None,
               hubert: str | Path | None = None) -> list[Path]:
    """Every model file a run with `source` (None: the bundled model) may read, which no
    output of the run may overwrite: the model file; for an official checkpoint, the
    statistics it may take from `stats_dir`, $DIFFSHEG_OFFICIAL_STATS or its own folder;
    the files of the HuBERT folder `hubert`."""
    path = DEFAULT_WEIGHTS if source is None else Path(source).expanduser()
    files = [path]
    if path.is_file() and not is_ours(path):
        folders = [Path(f).expanduser() for f in (stats_dir, os.environ.get(STATS_ENV)) if f] + [path.parent]
        files += [folder / name for folder in folders for setup in OFFICIAL.values() for name in setup.stats_files]
    if hubert is not None:
        files += [f for f in Path(hubert).expanduser().rglob("*") if f.is_file()]
    return files


def load_model(source: str | Path | None = None, *, dataset: Optional[str] = None,
               stats_dir: str | Path | None = None) -> ModelBundle:
    """Load a model: None = the bundled default; else a checkpoint path (ours or official)."""
    if source is None:
        if not DEFAULT_WEIGHTS.is_file():
            raise CheckpointError(f"the bundled model {DEFAULT_WEIGHTS} is missing: reinstall the package "
                                  "or pass a checkpoint")
        return _load_ours(DEFAULT_WEIGHTS)
    path = Path(source).expanduser()
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    if dataset is not None and dataset not in OFFICIAL:
        raise CheckpointError(f"unknown configuration '{dataset}': choose beat or show")
    if is_ours(path):
        return _load_ours(path)
    return load_official(path, dataset, stats_dir)
