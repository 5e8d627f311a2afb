"""Segment a simulated cube through the service's Open Inference Protocol (KServe V2) routes with Triton's client.

    .venv/bin/python docs/open_inference_example.py --url 127.0.0.1:8000 [--model small] [--json]
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import tritonclient.http as triton

from radar.simulate import simulate_sequence


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--url", default="127.0.0.1:8000", help="host:port of the service")
    parser.add_argument("--model", default="small", help="a served model (GET /v1/models)")
    parser.add_argument("--json", action="store_true", help="send and receive JSON tensors instead of binary ones")
    args = parser.parse_args()
    client = triton.InferenceServerClient(args.url, network_timeout=600)  # a first, unwarmed inference is slow
    assert client.is_server_ready() and client.is_model_ready(args.model)
    metadata = client.get_model_metadata(args.model)
    print("inputs:", {i["name"]: i["shape"] for i in metadata["inputs"]})

    cube = next(simulate_sequence("small", 1, seed=2)).cube  # complex64 (R, A, D)
    tensor = np.stack([cube.real, cube.imag], axis=-1).astype(np.float32)  # complex as a trailing axis of 2
    cube_input = triton.InferInput("complex", list(tensor.shape), "FP32")
    cube_input.set_data_from_numpy(tensor, binary_data=not args.json)
    outputs = [triton.InferRequestedOutput(name, binary_data=not args.json)
               for name in ("ra_mask", "rd_mask", "objects", "compute")]
    result = client.infer(args.model, [cube_input], outputs=outputs)

    columns = result.get_output("objects")["parameters"]["columns"].split(",")
    for row in result.as_numpy("objects"):
        print(dict(zip(columns, row.round(2).tolist(), strict=True)))
    print("RA mask:", result.as_numpy("ra_mask").shape, "labelled cells:", int((result.as_numpy("ra_mask") > 0).sum()))
    compute = json.loads(result.as_numpy("compute")[0])
    print("MACs:", compute["compute"]["macs"]["total"], "request:", compute["request_id"])


if __name__ == "__main__":
    main()
