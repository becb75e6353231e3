"""The driving policy, in one place: its network (`net.py`: CNN + LSTM, the ONNX export module), a trained run's
policy files loaded to act (`run_folder.py`), and an exported ONNX graph on onnxruntime (`onnx_runtime.py`).
Train, eval and export use these; none of them imports another stage's run module for it."""
