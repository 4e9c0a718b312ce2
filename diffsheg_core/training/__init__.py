"""Tooling around the runtime: the trainer, datasets, the synthetic corpus builder, metrics,
evaluation, the motion autoencoder and the phonetic encoder's training. Needs torch (and
scipy, librosa, onnx: `pip install -e ".[train]"`); the runtime never imports it, and the
Blender add-on leaves it out."""
