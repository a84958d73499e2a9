"""Run a `flowmimic export` graph in ONNX Runtime and check it against flowmimic's own outputs.

    flowmimic export pretrained/models/fm -o fm.onnx --check fm.check.safetensors
    python3 examples/onnx_check.py fm.onnx fm.check.safetensors

Needs numpy and onnxruntime (`pip install numpy onnxruntime`), nothing else. For a trajectory
model it compares the network's output and, for Flow Matching, an Euler sampler at NFE 5 written
here against flowmimic's samples from the same noise; for an expert, the actions. It then times
ONNX Runtime's forward pass at batch 1 and 64. Exits non-zero when a comparison fails.
"""

import json
import os
import struct
import sys
import time

import numpy as np
import onnxruntime as ort

TOLERANCE = 1e-4  # largest error relative to the largest magnitude of flowmimic's output


def read_safetensors(path):
    """A safetensors file's F32 tensors as numpy arrays (the format is a JSON header + bytes)."""
    with open(path, "rb") as f:
        data = f.read()
    (size,) = struct.unpack("<Q", data[:8])
    header = json.loads(data[8 : 8 + size])
    body = data[8 + size :]
    out = {}
    for name, info in header.items():
        if name == "__metadata__":
            continue
        start, end = info["data_offsets"]
        assert info["dtype"] == "F32", f"{name}: {info['dtype']}"
        out[name] = np.frombuffer(body[start:end], dtype="<f4").reshape(info["shape"])
    return out


def relative_error(got, expected):
    return float(np.max(np.abs(got - expected)) / max(np.max(np.abs(expected)), 1e-12))


def median_ms(run, repeats=50):
    run()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return 1000 * float(np.median(times))


def main():
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    graph, check = sys.argv[1], sys.argv[2]
    options = ort.SessionOptions()
    options.intra_op_num_threads = os.cpu_count()  # as flowmimic, which uses every core
    options.inter_op_num_threads = 1
    session = ort.InferenceSession(graph, options, providers=["CPUExecutionProvider"])
    meta = session.get_modelmeta().custom_metadata_map
    assert meta.get("format") == "flowmimic-onnx/1", f"{graph} is not a flowmimic export: {meta.get('format')}"
    data = read_safetensors(check)
    errors = {}
    if meta["kind"] == "trajectory-model":
        run = lambda x, t, cond: session.run(["y"], {"x": x, "t": t, "cond": cond})[0]
        errors["network output"] = relative_error(run(data["x"], data["t"], data["cond"]), data["y"])
        if "euler_nfe5" in data:
            x, nfe = data["noise"].copy(), 5
            for step in range(nfe):
                t = np.full(len(x), step / nfe, dtype=np.float32)
                x = x + (1.0 / nfe) * run(x, t, data["cond"])
            errors["Euler samples, NFE 5"] = relative_error(x, data["euler_nfe5"])
        for batch in (1, 64):
            rows = np.arange(batch) % len(data["x"])
            x, t, cond = data["x"][rows], data["t"][rows], data["cond"][rows]
            print(f"onnxruntime forward, batch {batch}: {median_ms(lambda: run(x, t, cond)):.3f} ms (median of 50)")
    else:
        run = lambda obs: session.run(["action"], {"obs": obs})[0]
        errors["actions"] = relative_error(run(data["obs"]), data["action"])
        for batch in (1, 64):
            obs = data["obs"][np.arange(batch) % len(data["obs"])]
            print(f"onnxruntime forward, batch {batch}: {median_ms(lambda: run(obs)):.3f} ms (median of 50)")
    failed = False
    for what, error in errors.items():
        ok = error <= TOLERANCE
        failed |= not ok
        print(f"{what}: largest relative error {error:.2e} ({'ok' if ok else 'FAILS'}; tolerance {TOLERANCE:.0e})")
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
