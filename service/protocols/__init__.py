"""The Open Inference Protocol (KServe V2) beside the service's own API: its tensors from a JSON header and binary
data (``open_inference``) and its JSON tensors read without a Python object per number (``json_tensors``)."""
