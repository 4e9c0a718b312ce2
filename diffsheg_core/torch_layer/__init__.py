"""Everything of diffsheg_core that imports torch (the training tooling aside): the rest of the
package runs on numpy and onnxruntime, and reaches these modules only when torch is asked for.

- `model`: the UniEG denoiser and the phonetic encoder as torch modules;
- `backend`: `TorchNetwork`, the torch backend of `runtime.backends` (official checkpoints,
  CUDA GPUs);
- `devices`: which torch device work runs on;
- `hubert`: HuBERT speech features (with the `transformers` package);
- `official`: reading official DiffSHEG checkpoints (torch pickles);
- `export`: ONNX export of a model's networks (tooling, with the `onnx` package; the
  Blender add-on ships the other modules, not this one).

Nothing outside this folder and `training/` imports torch (tests/test_imports.py checks).
This file imports nothing, so naming the package costs nothing.
"""
