class OnnxLineDetector:  # placeholder
    name = "onnx"
