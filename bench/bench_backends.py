"""Benchmark: the bundled model on onnxruntime against torch, with 1 and 2 CPU threads, idle
and while another process keeps one core busy; and the model's compute against the machine's
matrix-multiply rate. One run prints every figure side by side, measured on this machine:

    python bench/bench_backends.py [--seconds 60] [--repeats 2]

Each configuration runs in a fresh process (thread settings are per process), generates
from the first --seconds of real speech once to warm up on 2 s, then times whole
generations (features + sampling) and keeps the best of --repeats. The busy core is a
separate Python process spinning in a loop, as Blender's UI or another job would.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SPEECH = REPO.parent / "shared" / "data" / "audio" / "2_scott_0_3_3.wav"

RUN = """
import json, sys, time
import numpy as np, soundfile as sf
import diffsheg_core
from diffsheg_core.checkpoints import load_model
samples, rate = sf.read({speech!r}, dtype="float32")
bundle = load_model()
diffsheg_core.generate(samples[: 2 * rate], rate, model=bundle, backend={backend!r}, device="cpu",
                       threads={threads})
times, steps = [], []
for _ in range({repeats}):
    steps.clear()
    t = time.perf_counter()
    motion = diffsheg_core.generate(samples[: int({seconds} * rate)], rate, model=bundle, seed=0,
                                    backend={backend!r}, device="cpu", threads={threads},
                                    progress=steps.append)
    times.append(time.perf_counter() - t)
print(json.dumps({{"best": min(times), "frames": motion.n_frames, "steps": len(steps)}}))
"""


def spin() -> None:
    while True:
        pass


def measure(backend: str, threads: int, busy: bool, seconds: float, repeats: int) -> dict:
    hog = multiprocessing.Process(target=spin, daemon=True) if busy else None
    if hog is not None:
        hog.start()
    try:
        code = RUN.format(speech=str(SPEECH), backend=backend, threads=threads, seconds=seconds,
                          repeats=repeats)
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                             cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)})
    finally:
        if hog is not None:
            hog.terminate()
            hog.join()
    return json.loads(out.stdout.strip().splitlines()[-1])


def flops_per_call() -> tuple[float, int]:
    """Multiply-adds x 2 of one sampling step of the bundled model as generation runs it
    (guided: two passes per branch, one 34-frame window), counted on the torch modules, and
    the number of network calls per step."""
    import torch

    from diffsheg_core.checkpoints import load_model
    from diffsheg_core.diffusion import Schedule
    from diffsheg_core.guidance import Guidance, step_eps
    from diffsheg_core.style import style_vector, style_weights
    from diffsheg_core.torch_layer.backend import TorchNetwork

    bundle = load_model()
    net = TorchNetwork(bundle, "cpu", "fp32")
    total = [0.0]

    def count(module, inputs, output):
        rows = output.numel() / output.shape[-1 if isinstance(module, torch.nn.Linear) else 1]
        if isinstance(module, torch.nn.Linear):
            total[0] += 2.0 * rows * module.in_features * module.out_features
        else:  # Conv1d over (B, C, T)
            total[0] += 2.0 * output.numel() * module.in_channels * module.kernel_size[0]

    for module in net.model.modules():
        if isinstance(module, (torch.nn.Linear, torch.nn.Conv1d)):
            module.register_forward_hook(count)
    cfg, sched = bundle.config, Schedule.linear().respaced(25)
    x = np.zeros((1, cfg.clip_len, cfg.dim), np.float32)
    cond = np.zeros((1, cfg.clip_len, cfg.speech_dim), np.float32)
    i = np.array([10])
    step_eps(net, cfg.gesture_dim, x, sched.model_timesteps(i), np.zeros((1, cfg.clip_len, 128), np.float32),
             cond, style_vector(bundle, style_weights(bundle, None)), sched.x0_coefs(i, x),
             Guidance(bundle.guidance, bundle.skip_guidance))
    return total[0], 2


def matmul_rate(threads: int) -> dict[str, float]:
    """GFLOP/s of float32 matrix products: one the size of the model's (68 x 192 @ 192 x 384)
    and a large one (1024^3), in a process with `threads` BLAS threads."""
    code = """
import json, time, numpy as np
def rate(m, k, n, reps):
    a, b = np.random.rand(m, k).astype(np.float32), np.random.rand(k, n).astype(np.float32)
    a @ b
    t = time.perf_counter()
    for _ in range(reps):
        a @ b
    return 2.0 * m * k * n * reps / (time.perf_counter() - t) / 1e9
print(json.dumps({"model-sized": rate(68, 192, 384, 3000), "large": rate(1024, 1024, 1024, 20)}))
"""
    env = {**os.environ, "OPENBLAS_NUM_THREADS": str(threads), "OMP_NUM_THREADS": str(threads)}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env)
    return json.loads(out.stdout)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; "
          f"{args.seconds:g} s of {SPEECH.name}, best of {args.repeats}")
    results = {}
    print(f"{'backend':<8}{'threads':>8}{'idle s':>10}{'busy s':>10}{'busy/idle':>11}{'x real time':>13}")
    for backend in ("onnx", "torch"):
        for threads in (1, 2):
            run = measure(backend, threads, False, args.seconds, args.repeats)
            idle, steps = run["best"], run["steps"]
            busy = measure(backend, threads, True, args.seconds, args.repeats)["best"]
            results[backend, threads] = (idle, busy)
            print(f"{backend:<8}{threads:>8}{idle:>10.2f}{busy:>10.2f}{busy / idle:>11.2f}"
                  f"{args.seconds / idle:>13.1f}")
    for threads in (1, 2):
        for i, load in enumerate(("idle", "busy")):
            ratio = results["torch", threads][i] / results["onnx", threads][i]
            print(f"torch / onnx, {threads} thread(s), {load}: {ratio:.2f}x")
    flops, calls = flops_per_call()
    print(f"compute: {flops / 1e6:.1f} MFLOP per sampling step ({calls} network calls); "
          f"{steps} steps for {args.seconds:g} s -> {flops * steps / 1e9:.1f} GFLOP")
    for threads in (1, 2):
        rates = matmul_rate(threads)
        idle = results["onnx", threads][0]
        achieved = flops * steps / idle / 1e9
        print(f"{threads} thread(s): matmul {rates['model-sized']:.1f} GFLOP/s at the model's sizes, "
              f"{rates['large']:.1f} large; onnx achieves {achieved:.1f} GFLOP/s over the whole run "
              f"({100 * achieved / rates['model-sized']:.0f}% of the model-sized rate)")


if __name__ == "__main__":
    main()
