"""What runs a model: the onnxruntime and torch backends behind one interface (`backends`)."""
