"""Seconds per training iteration and peak memory of each stage, on this machine.

Each (stage, size, batch) runs in a fresh process (so peak RSS is that configuration's):
networks at the authors' sizes, Adam, the stage's loss weights of the kitti preset, a
frame pair of the KITTI sample (resized; the same pair repeated: this is a cost
measurement, not training), ``--warmup`` iterations not timed, then ``--iters`` timed.

    python benchmarks/bench_train.py --sizes 256x832,128x384 --batches 8,2 --iters 3 --json out.json

With random weights the flow is near zero, the pose of stages depth and joint often fails and
their depth terms are then zeroed, which skips most of the depth backward pass and makes the
iteration look cheaper than it is. ``--init CKPT`` starts from a checkpoint's networks (e.g. a
short flow stage's ``checkpoint.pt``) so that the pose succeeds; every row reports
``depth_failed`` (items whose pose or triangulation failed, over the timed iterations) so a
row measured on zeroed terms shows it. ``--depth-failure item`` keeps the other items' depth
terms when one fails (the kitti preset, as the authors, zeroes the whole batch's).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def one(stage: str, size: tuple[int, int], batch: int, iters: int, warmup: int, threads: int,
        init: str | None = None, depth_failure: str | None = None) -> dict:
    import cv2
    import numpy as np
    import resource
    import torch

    from trianflow_vo.models.depth_net import DepthNet
    from trianflow_vo.models.pwc import PWCNet
    from trianflow_vo.train.config import load_train_config
    from trianflow_vo.train.loop import loss_weights
    from trianflow_vo.train.objective import compute_losses

    torch.set_num_threads(threads)
    cv2.setNumThreads(threads)
    h, w = size
    frames = sorted((REPO / "sample" / "kitti00").glob("image_*/*.jpg"))[:2] or \
        sorted((REPO / "sample" / "kitti00").rglob("*.jpg"))[:2]
    ims = []
    for f in frames:
        im = cv2.imread(str(f))
        H, W = im.shape[:2]
        ims.append(torch.from_numpy(cv2.resize(im, (w, h)).transpose(2, 0, 1).astype(np.float32) / 255.0))
    K0 = np.array([[718.856, 0, 607.1928], [0, 718.856, 185.2157], [0, 0, 1.0]])
    K = K0.copy()
    K[0] *= w / W
    K[1] *= h / H
    Kt = torch.tensor(K, dtype=torch.float32).expand(batch, 3, 3).contiguous()
    Ki = torch.linalg.inv(Kt)
    img1 = ims[0].expand(batch, -1, -1, -1).contiguous()
    img2 = ims[1].expand(batch, -1, -1, -1).contiguous()
    cfg = load_train_config("kitti", stage)
    weights = loss_weights(cfg)
    if depth_failure:
        import dataclasses

        weights = dataclasses.replace(weights, depth_failure=depth_failure)
    torch.manual_seed(0)
    flow = PWCNet()
    depth = DepthNet() if stage != "flow" else None
    if init:
        from trianflow_vo.models.checkpoint import load_checkpoint

        ck = load_checkpoint(init)
        if ck.flow is not None:
            flow.load_state_dict(ck.flow.net.state_dict())
        if ck.depth is not None and depth is not None:
            depth.load_state_dict(ck.depth.net.state_dict())
    if stage == "depth":
        flow.eval()
        for p in flow.parameters():
            p.requires_grad_(False)
    params = [p for n in (flow, depth) if n is not None for p in n.parameters() if p.requires_grad]
    opt = torch.optim.Adam(params, lr=1e-4)
    times = []
    failed = zeroed = 0
    load0 = os.getloadavg()
    for i in range(warmup + iters):
        t0 = time.perf_counter()
        cv2.setRNGSeed(i)
        out = compute_losses(stage, img1, img2, Kt, Ki, weights, flow_net=flow, depth_net=depth,
                             generator=torch.Generator().manual_seed(i))
        opt.zero_grad()
        out.total.backward()
        opt.step()
        if i >= warmup:
            times.append(time.perf_counter() - t0)
            failed += int(out.depth_failed)
            zeroed += int(out.depth_zeroed and weights.depth_failure == "batch")
    return {"stage": stage, "size": f"{h}x{w}", "batch": batch, "threads": threads, "init": init,
            "depth_failure": weights.depth_failure, "batches_zeroed": zeroed,
            "s_per_iter_median": float(np.median(times)), "s_per_iter_all": times,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
            "depth_failed": failed, "load_average_start": load0, "load_average_end": os.getloadavg()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stages", default="flow,depth,joint")
    ap.add_argument("--sizes", default="256x832,128x384")
    ap.add_argument("--batches", default="8,2", help="one per size")
    ap.add_argument("--iters", type=int, default=3)
    ap.add_argument("--warmup", type=int, default=1)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", default=None)
    ap.add_argument("--init", default=None, help="checkpoint whose networks to start from (see above)")
    ap.add_argument("--depth-failure", choices=["batch", "item"], default=None,
                    help="losses.depth_failure (default: the preset's, batch)")
    ap.add_argument("--one", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.one:
        stage, size, batch = a.one.split(":")
        h, w = (int(v) for v in size.split("x"))
        print(json.dumps(one(stage, (h, w), int(batch), a.iters, a.warmup, a.threads, a.init, a.depth_failure)))
        return
    rows = []
    load0 = os.getloadavg()
    for size, batch in zip(a.sizes.split(","), a.batches.split(",")):
        for stage in a.stages.split(","):
            res = subprocess.run([sys.executable, __file__, "--one", f"{stage}:{size}:{batch}", "--iters",
                                  str(a.iters), "--warmup", str(a.warmup), "--threads", str(a.threads),
                                  *(["--init", a.init] if a.init else []),
                                  *(["--depth-failure", a.depth_failure] if a.depth_failure else [])],
                                 capture_output=True, text=True)
            if res.returncode:
                row = {"stage": stage, "size": size, "batch": int(batch), "error": res.stderr.strip()[-300:]}
            else:
                row = json.loads(res.stdout.strip().splitlines()[-1])
            rows.append(row)
            print(json.dumps(row), flush=True)
    doc = {"load_average_start": load0, "load_average_end": os.getloadavg(), "rows": rows}
    if a.json:
        Path(a.json).write_text(json.dumps(doc, indent=2))


if __name__ == "__main__":
    main()
