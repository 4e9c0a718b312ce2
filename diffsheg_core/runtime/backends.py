"""The backends that run a model's networks, behind the two calls of `guidance.Network`
(plus the phonetic encoder's posteriors): numpy in, numpy out.

- onnx: onnxruntime on the CPU, from the ONNX graphs stored in the model file. Needs no
  torch: this is what the Blender add-on runs.
- torch: the UniEG module built from the file's weights, on the CPU or a CUDA GPU; the
  backend of official DiffSHEG checkpoints (which carry no graphs) and of training. It is
  `torch_layer.backend.TorchNetwork`, imported only when this backend is chosen.

`backend="auto"` picks onnx where the model has its graphs and no GPU is asked for or
found, torch otherwise. Both backends get the same inputs from the same numpy sampler,
so a seed gives the same motion on either (within float32 rounding).
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import importlib.util
import os
import sys
from typing import Iterator, Optional

import numpy as np

from ..checkpoints import MODEL_PREFIX, TORCH_HOW_TO, ModelBundle
from ..errors import DiffshegError
from ..validate import BACKENDS, DEVICES, PRECISIONS, THREADS, check_number, parse_whole
from .graphs import left_out, supplied_weights

THREADS_ENV = "DIFFSHEG_THREADS"


def default_threads() -> int:
    """CPU threads per generation: $DIFFSHEG_THREADS, else 1.

    The bundled model's products are small (68 x 192 rows by columns): one thread runs them
    at the machine's matrix-multiply rate, a second adds more overhead than speed (onnx on 2
    cores: 3.7 s for 60 s of speech with 1 thread, 4.2 s with 2), and a second thread that
    must share a core with Blender's UI or another job collapses (torch: 6.9 s idle, 23.0 s
    with one core busy; 1 thread: 8.3 / 8.4 s). See bench/bench_backends.py. onnxruntime's
    threads are also told not to spin when more are asked for."""
    value = os.environ.get(THREADS_ENV)
    if not value:
        return 1
    threads = parse_whole(value)
    return check_number(f"${THREADS_ENV}", value if threads is None else threads, THREADS, whole=True)


def resolve_threads(threads: Optional[int]) -> int:
    """A generation's CPU threads: `threads` checked, or `default_threads()` for None."""
    return default_threads() if threads is None else check_number("threads", threads, THREADS, whole=True)


@contextlib.contextmanager
def cpu_threads(threads: Optional[int] = None) -> Iterator[None]:
    """numpy's BLAS (OpenBLAS, MKL; through threadpoolctl) held to a generation's CPU threads
    while it runs, as the network's are. The sampler's numpy work is small (the gesture
    prior's solves, the legs): on more threads than it has cores to itself it collapses. With
    the other core of a 2-core machine busy, the prior's solve for a new overlap took 0.06-1.4 s
    on OpenBLAS's 2 threads and 3-5 ms on one, and a live session fell 1.5 s behind from it."""
    threads = resolve_threads(threads)
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        raise DiffshegError("generation needs the threadpoolctl package: `pip install threadpoolctl` (the "
                            "Blender add-on bundles it; the legacy add-on's Install dependencies installs it)") from None
    with threadpool_limits(limits=threads, user_api="blas"):
        yield


class OnnxNetwork:
    """A model's ONNX graphs on onnxruntime (CPU): `graphs` (by default the model's own), the
    weights a graph leaves out made from the model's (`runtime.graphs.supplied_weights`)."""

    name = "onnx"

    def __init__(self, bundle: ModelBundle, threads: int, graphs: Optional[dict[str, bytes]] = None,
                 what: str = "ONNX graphs"):
        try:
            import onnxruntime as ort
        except ImportError:
            raise DiffshegError("the onnx backend needs the onnxruntime package: `pip install onnxruntime` "
                                "(the Blender add-on bundles it), or choose backend torch") from None
        self.sessions, self._supplied = {}, []
        try:
            for name, graph in (bundle.graphs if graphs is None else graphs).items():
                options = self._options(ort, threads)
                names = left_out(graph)  # none in a model's own graphs (checkpoints refuses them there)
                if names:
                    values = supplied_weights(names, bundle.weights, MODEL_PREFIX)
                    self._supplied.append([ort.OrtValue.ortvalue_from_numpy(values[n]) for n in names])
                    options.add_external_initializers(names, self._supplied[-1])
                self.sessions[name] = ort.InferenceSession(graph, options, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own types for damaged graphs
            raise DiffshegError(f"{bundle.source}: its {what} do not load ({exc}); export the model again "
                                "(python -m diffsheg_core export-onnx FILE), or choose backend torch") from None
        self.inputs = {name: {i.name for i in session.get_inputs()} for name, session in self.sessions.items()}
        self.device = "cpu"

    @staticmethod
    def _options(ort, threads: int):
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        options.log_severity_level = 3
        return options

    def _run(self, graph: str, feeds: dict) -> list[np.ndarray]:
        """Run `graph` on the feeds it takes (the `null` input exists only in models with a
        null condition); a row mask left as None means no row is nulled / every row attends."""
        if "timesteps" in feeds:
            rows = len(feeds["timesteps"])
            defaults = {"null": np.zeros(rows, bool), "attend": np.ones(rows, bool)}
            feeds = {k: defaults[k] if v is None and k in defaults else v for k, v in feeds.items()}
        return self.sessions[graph].run(None, {k: v for k, v in feeds.items() if k in self.inputs[graph]})

    def expression(self, expression, timesteps, mel, speech, style, null):
        eps, audio = self._run("expression", {
            "expression": expression, "timesteps": timesteps.astype(np.int64), "mel": mel,
            "speech": speech, "style": style, "null": null})
        return eps, audio

    def gesture(self, gesture, timesteps, audio, speech, expression_x0, style, null, attend):
        return self._run("gesture", {
            "gesture": gesture, "timesteps": timesteps.astype(np.int64), "audio": audio, "speech": speech,
            "expression_x0": expression_x0, "style": style, "null": null, "attend": attend})[0]

    def phone_posteriors(self, mel: np.ndarray) -> np.ndarray:
        return self._run("phonetic", {"mel": mel[None]})[0]


def _torch_sees_cuda() -> bool:
    """Whether an installed torch sees a CUDA GPU. A CPU build (version `+cpu`) or macOS
    cannot, and is not imported to find out: that would add most of a second to every run."""
    if importlib.util.find_spec("torch") is None or sys.platform == "darwin":
        return False
    try:
        if importlib.metadata.version("torch").endswith("+cpu"):
            return False
    except importlib.metadata.PackageNotFoundError:  # torch on sys.path without metadata
        pass
    from ..torch_layer.devices import resolve_device

    return resolve_device("auto").type == "cuda"


def choose_backend(bundle: ModelBundle, backend: str = "auto", device: str = "auto") -> str:
    """The backend that runs `bundle`: onnx or torch. Bad or impossible choices raise
    DiffshegError saying what to change."""
    if backend not in BACKENDS:
        raise DiffshegError(f"unknown backend '{backend}': use {', '.join(BACKENDS)}")
    if str(device) not in DEVICES and not str(device).startswith("cuda:"):
        raise DiffshegError(f"unknown device '{device}': use {', '.join(DEVICES)}")
    wants_gpu = str(device).startswith("cuda")
    if backend == "auto":
        gpu = wants_gpu or (device == "auto" and _torch_sees_cuda())
        backend = "onnx" if bundle.has_graphs and not gpu else "torch"
    if backend == "onnx":
        if not bundle.has_graphs:
            raise DiffshegError(f"{bundle.source} carries no ONNX graphs (official checkpoints and files "
                                "exported before 0.2 do not): choose backend torch, or export it again")
        if wants_gpu:
            raise DiffshegError("the onnx backend runs on the CPU: choose backend torch for a CUDA GPU")
    elif importlib.util.find_spec("torch") is None:
        raise DiffshegError(f"{bundle.source} needs the torch backend "
                            f"({'a CUDA GPU was asked for' if wants_gpu else 'it carries no ONNX graphs'}), "
                            f"and torch is not installed: {TORCH_HOW_TO}")
    return backend


def open_network(bundle: ModelBundle, backend: str = "auto", device: str = "auto",
                 precision: str = "fp32", threads: Optional[int] = None):
    """The network that runs `bundle` (cached on it): an OnnxNetwork or a TorchNetwork."""
    if precision not in PRECISIONS:
        raise DiffshegError(f"unknown precision '{precision}': use {', '.join(PRECISIONS)}")
    threads = default_threads() if threads is None else check_number("threads", threads, THREADS, whole=True)
    backend = choose_backend(bundle, backend, device)
    key = (backend, str(device), precision, threads)
    if key not in bundle.networks:
        if backend == "onnx":
            if precision != "fp32":
                raise DiffshegError(f"precision '{precision}' needs the torch backend on a CUDA GPU")
            bundle.networks[key] = OnnxNetwork(bundle, threads)
        else:
            from ..torch_layer.backend import TorchNetwork

            bundle.networks[key] = TorchNetwork(bundle, device, precision, threads)
    return bundle.networks[key]


def student_network(bundle: ModelBundle, network):
    """The network of `bundle`'s distilled student, opened as `network` (one `open_network`
    opened for `bundle`) is: same backend, device, precision and threads. None when `network`
    was not opened that way (a caller's own network runs the guided steps itself)."""
    key = _opened_as(bundle, network)
    if key is None or key[0] == "live" or bundle.student is None:
        return None
    return open_network(bundle.student, *key)


def _opened_as(bundle: ModelBundle, network) -> Optional[tuple]:
    """The key `open_network` cached `network` under on `bundle` (None: not opened that way)."""
    return next((k for k, v in bundle.networks.items() if v is network), None)


def live_network(bundle: ModelBundle, network):
    """The network a live session of `bundle` runs, given `network` (one `open_network` opened
    for `bundle`): on onnxruntime the model's live graphs when the file has them (its products
    by weights in int8: a window's calls take about 0.8x the time on one core, docs/live.md),
    else `network` itself (torch runs the model's float weights)."""
    key = _opened_as(bundle, network)
    if key is None or key[0] != "onnx" or not bundle.live_graphs:
        return network
    live_key = ("live", *key)
    if live_key not in bundle.networks:
        bundle.networks[live_key] = OnnxNetwork(bundle, key[3], {**bundle.graphs, **bundle.live_graphs},
                                                "live int8 graphs (offline generation does not use them)")
    return bundle.networks[live_key]
