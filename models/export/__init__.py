"""ERASE-Net in ONNX: export both stages with standard operators, and run them in onnxruntime.

``kernel_maps_numpy`` (numpy only) computes the segmenter graph's kernel-map inputs; ``sparse_graph`` is the
MinkUNet's export form; ``onnx_export`` writes and validates the graphs and their manifest; ``onnx_engine``
runs them behind :class:`models.erasenet.model.EraseNet`'s ``segment`` contract.
"""
