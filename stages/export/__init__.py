"""`drivesim export onnx`: the policy as one ONNX graph, checked with onnxruntime."""
