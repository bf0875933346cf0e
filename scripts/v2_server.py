#!/usr/bin/env python3
"""Serve LeanGate ONNX models on a KServe V2 / Open Inference Protocol server (NVIDIA Triton
Inference Server through PyTriton; CPU, onnxruntime in Python), on loopback by default.

Used by the remote-scoring tests and benchmark (tests/remote.rs, benches/remote.rs) and handy
for trying `leangate server=...` without a Triton installation:

    .venv-triton/bin/python scripts/v2_server.py models/leangate-s-encoder.onnx \
        models/leangate-s-head.onnx models/leangate-s.onnx --http-port 8000

Each model is served under its file name without `.onnx` (or NAME=path.onnx), with dynamic
batching (max batch 8). The venv comes from `scripts/setup.sh` (`.venv-triton`, built from
Debian's /usr/bin/python3: the Python backend bundled in PyTriton needs that libpython).
SIGINT/SIGTERM stop it cleanly, and it stops by itself when its parent process goes away.
"""

import argparse
import json
import os
import shutil
import signal
import sys
import tempfile
import threading
import time

import numpy as np

# Microsoft's onnxruntime wheels write a device id and queued usage events under
# ~/.cache/Microsoft as soon as the module loads, unless this is set first (a user's own value is
# kept), as the element does for its library (src/runtime.rs).
os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")
import onnxruntime as ort  # noqa: E402
from pytriton.decorators import batch
from pytriton.model_config import DynamicBatcher, ModelConfig, Tensor
from pytriton.triton import Triton, TritonConfig

MAX_BATCH = 8


class Knobs:
    """Test hooks: rows served per model (written to --counts as JSON after each call) and an
    artificial delay per call read from --delay-file (milliseconds; absent or empty = none)."""

    def __init__(self, counts_path, delay_path):
        self.counts_path, self.delay_path = counts_path, delay_path
        self.counts = {}
        self.lock = threading.Lock()

    def delay(self):
        if not self.delay_path:
            return
        try:
            with open(self.delay_path) as f:
                ms = float(f.read().strip() or 0)
        except (OSError, ValueError):
            return
        if ms > 0:
            time.sleep(ms / 1000)

    def count(self, name, rows):
        if not self.counts_path:
            return
        with self.lock:
            self.counts[name] = self.counts.get(name, 0) + rows
            tmp = self.counts_path + ".tmp"
            with open(tmp, "w") as f:
                json.dump(self.counts, f)
            os.replace(tmp, self.counts_path)


def model_fn(model_name, session, knobs):
    outputs = [o.name for o in session.get_outputs()]

    @batch
    def infer(**inputs):
        knobs.delay()
        feed = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in inputs.items()}
        got = session.run(outputs, feed)
        result = {}
        for out_name, value in zip(outputs, got):
            value = np.asarray(value, dtype=np.float32)
            n = next(iter(feed.values())).shape[0]
            if value.ndim == 1:  # [N] -> [N, 1]: Triton's batch dimension plus one
                value = value.reshape(n, 1)
            result[out_name] = value
        knobs.count(model_name, next(iter(feed.values())).shape[0])
        return result

    return infer


def tensor_specs(args):
    specs = []
    for a in args:
        dims = [d if isinstance(d, int) and d > 0 else -1 for d in a.shape[1:]]
        if not dims:
            dims = [1]
        specs.append(Tensor(name=a.name, dtype=np.float32, shape=tuple(dims)))
    return specs


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("models", nargs="+", help="model.onnx or NAME=model.onnx")
    p.add_argument("--address", default="127.0.0.1")
    p.add_argument("--http-port", type=int, default=8000)
    p.add_argument("--grpc-port", type=int, default=8001)
    p.add_argument("--metrics-port", type=int, default=8002)
    p.add_argument("--threads", type=int, default=1, help="onnxruntime intra-op threads")
    p.add_argument("--counts", help="write the rows served per model here (JSON), for tests")
    p.add_argument("--delay-file", help="a file holding a delay per call in ms, for tests")
    p.add_argument("--workspace", help="PyTriton's workspace (sockets, model store); default: a "
                   "temporary one in $TMPDIR, removed at exit (PyTriton's own default is under "
                   "~/.cache/pytriton, which it leaves behind)")
    args = p.parse_args()
    if args.workspace is not None:
        return serve(args, args.workspace)
    tmp = tempfile.mkdtemp(prefix="leangate-v2-server-")
    try:
        return serve(args, os.path.join(tmp, "workspace"))  # PyTriton makes the folder itself
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def serve(args, workspace):

    config = TritonConfig(
        http_address=args.address,
        http_port=args.http_port,
        grpc_address=args.address,
        grpc_port=args.grpc_port,
        metrics_address=args.address,
        metrics_port=args.metrics_port,
        allow_metrics=False,
        exit_timeout_secs=5,
    )
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    parent = os.getppid()

    knobs = Knobs(args.counts, args.delay_file)
    so = ort.SessionOptions()
    so.intra_op_num_threads = args.threads
    so.inter_op_num_threads = 1
    with Triton(config=config, workspace=workspace) as triton:
        for spec in args.models:
            name, _, path = spec.rpartition("=")
            if not name:
                name = os.path.basename(path)[: -len(".onnx")] if path.endswith(".onnx") else path
            session = ort.InferenceSession(path, so, providers=["CPUExecutionProvider"])
            triton.bind(
                model_name=name,
                infer_func=model_fn(name, session, knobs),
                inputs=tensor_specs(session.get_inputs()),
                outputs=tensor_specs(session.get_outputs()),
                config=ModelConfig(
                    max_batch_size=MAX_BATCH,
                    batcher=DynamicBatcher(max_queue_delay_microseconds=500),
                ),
                strict=False,
            )
            print(f"v2_server: model {name} from {path}", flush=True)
        triton.run()
        print(f"v2_server: serving on http://{args.address}:{args.http_port}", flush=True)
        while not stop.wait(0.2):
            if os.getppid() != parent:  # orphaned: the test or benchmark died
                break
    print("v2_server: stopped", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
