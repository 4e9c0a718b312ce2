"""What runs a model: the onnxruntime and torch backends behind one interface (`backends`),
and what a stored ONNX graph declares, read without the onnx package (`graphs`)."""
