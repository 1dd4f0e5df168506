"""The real-side loop: camera frames in, an exported policy, MAVLink MANUAL_CONTROL out to ArduSub (`swimm pilot`).

It needs onnxruntime, OpenCV and pymavlink, never torch or stable-baselines3: a topside computer or the rover's
companion runs it from the one ONNX file `swimm export` writes.
"""
