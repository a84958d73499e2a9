"""Run a `flowmimic export` graph in ONNX Runtime and check it against flowmimic's own outputs.

    flowmimic export pretrained/models/fm -o fm.onnx --check fm.check.safetensors \
        --rollout runs/demo/joystick.rollout.safetensors
    python3 examples/onnx_check.py fm.onnx fm.check.safetensors runs/demo/joystick.rollout.safetensors

Needs numpy and onnxruntime (`pip install numpy onnxruntime`), nothing else. For a trajectory
model it compares the network's output, then samples with the objective's sampler written out
here (`sample`: Flow Matching's Euler steps, MeanFlow's jumps, DDPM's ancestral steps, each
reading a velocity, clean-sample or noise prediction as the metadata says) against flowmimic's
samples from the same noise; given the rollout, it also builds the conditioning from the
rollout's states and actions as flowmimic's controller does (states re-expressed in the current
character frame, normalised with the statistics in the graph's metadata) and samples from it.
For an expert it compares the actions. It then times ONNX Runtime's forward pass at batch 1 and
64. Exits non-zero when a comparison fails.
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
    """A safetensors file's F32 tensors as numpy arrays, and its metadata (a JSON header, then
    the bytes)."""
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
        if info["dtype"] == "F32":
            out[name] = np.frombuffer(body[start:end], dtype="<f4").reshape(info["shape"])
    return out, header.get("__metadata__", {})


def quat_mul(a, b):
    """Hamilton product of (w, x, y, z) quaternions."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw])


def yaw_quat(yaw):
    return np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])


def rotate(q, v):
    return quat_mul(quat_mul(q, np.concatenate([[0.0], v])), q * np.array([1, -1, -1, -1]))[1:]


def from_rotvec(v):
    angle = np.linalg.norm(v)
    if angle < 1e-12:
        q = np.concatenate([[1.0], 0.5 * v])
        return q / np.linalg.norm(q)
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * v / angle])


def rotvec(q):
    q = -q if q[0] < 0 else q
    s = np.linalg.norm(q[1:])
    return 2.0 * q[1:] if s < 1e-12 else q[1:] * (2.0 * np.arctan2(s, q[0]) / s)


def reexpress(state, pose_k, pose_t):
    """A state (in its own character frame) in the frame of step t: root position, velocity and
    rotation vector are the only entries that depend on the frame (state offsets 0, 3 and 6)."""
    out = state.astype(np.float64).copy()
    turn, back = yaw_quat(float(np.float32(pose_k[2] - pose_t[2]))), yaw_quat(-float(pose_t[2]))
    d = rotate(back, np.array([float(np.float32(pose_k[0] - pose_t[0])), float(np.float32(pose_k[1] - pose_t[1])), 0.0]))
    out[0:2] = d[:2]
    out[3:6] = rotate(turn, out[3:6])
    out[6:9] = rotvec(quat_mul(turn, from_rotvec(out[6:9])))
    return out.astype(np.float32)


def rollout_conditioning(rollout, layout, t):
    """The controller's conditioning at step t of the rollout's first environment: the last
    N + 1 states (the oldest repeated before there are N + 1) and the N actions between them."""
    n, sd = layout["spec"]["history"], layout["state_dim"]
    qpos, states, actions = rollout["qpos"][0], rollout["state"][0], rollout["action"][0]
    w, x, y, z = (qpos[:, i].astype(np.float64) for i in range(3, 7))
    heading = np.arctan2(2 * (x * y + w * z), 1 - 2 * (y * y + z * z)).astype(np.float32)
    pose = lambda k: (qpos[k, 0], qpos[k, 1], heading[k])
    ks = [max(t - n + j, 0) for j in range(n + 1)]
    parts = []
    for j, k in enumerate(ks):
        parts.append(reexpress(states[k, :sd], pose(k), pose(t)))
        if j < n:
            parts.append(actions[k] if k < t else np.zeros(layout["action_dim"], dtype=np.float32))
    # A model with task labels takes them after s_t; the check gives none (all zeros).
    parts.append(np.zeros(layout.get("labels", 0), dtype=np.float32))
    return np.concatenate(parts)[None, :]


def normaliser(meta):
    """Per-entry mean and std of a window, from the graph's metadata (a task label, after s_t,
    is taken as it is)."""
    stats, layout = json.loads(meta["stats"]), json.loads(meta["layout"])
    sd, ad = layout["state_dim"], layout["action_dim"]
    slots = len(stats["state_mean"]) // sd
    at, labels = layout["spec"]["history"] * (sd + ad) + sd, layout.get("labels", 0)
    interleave = lambda s, a, fill: np.insert(
        np.concatenate([np.concatenate([s[k * sd:(k + 1) * sd], a[k * ad:(k + 1) * ad]]) for k in range(slots)]),
        at,
        np.full(labels, fill),
    ).astype(np.float32)
    return (
        interleave(stats["state_mean"], stats["action_mean"], 0.0),
        interleave(stats["state_std"], stats["action_std"], 1.0),
    )


MIN_REMAINING = 0.05  # the smallest 1 - s a clean-sample flow network's velocity divides by


def cosine_alpha_bar(steps):
    """DDPM's cosine schedule, cumulative products of 1 - beta (float64, as flowmimic)."""
    f = lambda k: np.cos(((k / steps) + 0.008) / 1.008 * np.pi / 2) ** 2
    alpha_bar = [1.0]
    for k in range(1, steps + 1):
        alpha_bar.append(alpha_bar[-1] * (1.0 - min(1.0 - f(k) / f(k - 1), 0.999)))
    return alpha_bar


def sample(run, objective, noise, cond, nfe, ancestral_noise=None):
    """flowmimic's sampler of `objective` at `nfe` network calls from `noise` (normalised units).
    `run(x, t, cond)` is the network."""
    (kind, o), = objective.items()
    x, n = noise.copy(), len(noise)
    f32 = np.float32
    if kind in ("fm", "meanflow"):
        assert o.get("solver", "Euler") == "Euler", "Heun's method is not written out here"
        h = f32(1.0 / nfe)
        for step in range(nfe):
            s = f32(step) * h
            # Flow Matching's network takes the time s; MeanFlow's the interval (s, h) it jumps.
            t = np.full(n, s, dtype=f32) if kind == "fm" else np.tile(np.array([s, h], dtype=f32), (n, 1))
            y = run(x, t, cond)
            # A clean-sample network's velocity is (x_hat - x) / (1 - s).
            v = (y - x) / f32(max(1.0 - s, MIN_REMAINING)) if o.get("prediction") == "sample" else y
            x = x + h * v
        return x
    # DDPM: respaced ancestral sampling on the cosine schedule, clean estimates clipped.
    steps, clip = o["steps"], f32(o["clip"])
    alpha_bar = cosine_alpha_bar(steps)
    m = min(max(nfe, 1), steps)
    ks = [int(np.floor(i * steps / m + 0.5)) for i in range(1, m + 1)]
    prev, betas = 1.0, []
    for k in ks:
        betas.append(1.0 - alpha_bar[k] / prev)
        prev = alpha_bar[k]
    for i in reversed(range(len(ks))):
        k, beta, ab = ks[i], betas[i], alpha_bar[ks[i]]
        ab_prev = 1.0 if i == 0 else alpha_bar[ks[i - 1]]
        sa, s1a = f32(np.sqrt(ab)), f32(np.sqrt(1.0 - ab))
        a, b = (f32(1.0) / sa, -s1a / sa) if o["prediction"] == "epsilon" else (f32(0.0), f32(1.0))
        out = run(x, np.full(n, f32(k) / f32(steps), dtype=f32), cond)
        x0 = np.clip(a * x + b * out, -clip, clip)
        if i == 0:
            return x0
        c0 = f32(np.sqrt(ab_prev) * beta / (1.0 - ab))
        ck = f32(np.sqrt(1.0 - beta) * (1.0 - ab_prev) / (1.0 - ab))
        sd = f32(np.sqrt(beta * (1.0 - ab_prev) / (1.0 - ab)))
        x = c0 * x0 + ck * x + sd * ancestral_noise[len(ks) - 1 - i]


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
    if len(sys.argv) not in (3, 4):
        sys.exit(__doc__)
    graph, check = sys.argv[1], sys.argv[2]
    options = ort.SessionOptions()
    options.intra_op_num_threads = os.cpu_count()  # as flowmimic, which uses every core
    options.inter_op_num_threads = 1
    session = ort.InferenceSession(graph, options, providers=["CPUExecutionProvider"])
    meta = session.get_modelmeta().custom_metadata_map
    assert meta.get("format") == "flowmimic-onnx/1", f"{graph} is not a flowmimic export: {meta.get('format')}"
    data, check_meta = read_safetensors(check)
    errors = {}
    if meta["kind"] == "trajectory-model":
        run = lambda x, t, cond: session.run(["y"], {"x": x, "t": t, "cond": cond})[0]
        objective, nfe = json.loads(meta["objective"]), int(check_meta["nfe"])
        errors["network output"] = relative_error(run(data["x"], data["t"], data["cond"]), data["y"])
        got = sample(run, objective, data["noise"], data["cond"], nfe, data.get("ancestral_noise"))
        errors[f"samples, NFE {nfe}"] = relative_error(got, data["samples"])
        if len(sys.argv) == 4:
            rollout, _ = read_safetensors(sys.argv[3])
            layout = json.loads(meta["layout"])
            cond = rollout_conditioning(rollout, layout, int(check_meta["rollout_step"]))
            errors["conditioning from the rollout"] = relative_error(cond, data["rollout_cond"])
            mean, std = normaliser(meta)
            c = cond.shape[1]
            cond = ((cond - mean[:c]) / std[:c]).astype(np.float32)
            got = sample(run, objective, data["rollout_noise"], cond, nfe, data.get("rollout_ancestral_noise"))
            errors["samples from the rollout's conditioning"] = relative_error(got, data["rollout_samples"])
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
