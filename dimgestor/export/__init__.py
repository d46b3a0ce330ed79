"""Export: the streaming step as one ONNX graph with explicit state (`onnx_export`, `dimgestor export-onnx`),
driven as a stream (`onnx_stream`) or many streams a call (`onnx_batch`, `serve --backend onnxruntime`), kept in
a per-user cache (`onnx_cache`), and a Triton model repository (`onnx_triton`). Needs the `onnx` extra; nothing
is imported here, so the package imports without it."""
