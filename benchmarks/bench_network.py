"""Per-pair time of the network path at 256x832: onnxruntime (ours) vs PyTorch eager.

(a) ours: ``OnnxFlow`` (forward + backward flow in one call), ``OnnxDepthNet`` (depth once
    per frame: one depth inference per pair in a sequence), masks M_s / M_o with
    numpy (``vo.flow.masks.flow_scores``). (An earlier variant also timed the masks as an
    ONNX graph; it was slower and the graph option is gone, see NETWORK.md.)
(b) research-style PyTorch eager: autograd on, flow 1->2 and 2->1 as two calls,
    masks in torch (this file's ``_masks_torch``), depth for both frames of every pair.

Both use the same architectures (paper sizes, random weights: timing does not depend
on the weights) and the same thread count. Medians per stage are printed as a table
and written as JSON (``--json``) and as a markdown section (``--md``).

    python benchmarks/bench_network.py --pairs 8 --threads 2

``--split``: the run path's variants side by side, interleaved pair by pair: ``single``
(flow.onnx as one graph), ``split`` (encoder in ``prepare``, once per frame; decoder per
pair), ``split-int8`` (``export --quantize int8``: int8 decoder and depth); per stage ms,
peak RSS of a fresh process per variant, onnxruntime settings on the split graphs, and
int8 against fp32 on real frames (flow end-point error, depth relative error):

    python benchmarks/bench_network.py --split --pairs 8 --threads 2 --append-md

``--costvol``: the matrix-product cost volume (``models/pwc.py: cost_volume``) against the
reference formulation (``cost_volume_reference``: 81 slice/multiply/mean per level), with the
same seed-0 weights: the cost volume alone per pyramid level in onnxruntime, the split fp32
and int8 paths interleaved pair by pair (``split-ref``, ``split-new``, ``int8-ref``,
``int8-new``), new - reference flow, int8 against its own fp32, and one torch training step
(forward + backward, batch 2) per formulation in a fresh process (time, peak RSS):

    python benchmarks/bench_network.py --costvol --pairs 8 --threads 2 --models M --int8-models Q --append-md

(``--models`` / ``--int8-models``: exports made with the reference cost volume; default:
exported here with it. ``--new-models`` / ``--new-int8-models``: the same with the current
code; default: exported here.)
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time
import warnings
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import cv2  # noqa: E402
import numpy as np  # noqa: E402


def _load_frames(seq: Path, n: int, size: tuple[int, int]) -> list[np.ndarray]:
    folder = seq / "image_0" if (seq / "image_0").is_dir() else seq
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))[:n]
    if len(files) < n:
        raise SystemExit(f"{folder}: need {n} images, found {len(files)}")
    h, w = size
    return [cv2.resize(cv2.imread(str(p), cv2.IMREAD_COLOR), (w, h), interpolation=cv2.INTER_AREA) for p in files]


def _timed(fn, *args):
    t = time.perf_counter()
    out = fn(*args)
    return out, time.perf_counter() - t


def _median_ms(values: list[float]) -> float:
    return 1000.0 * statistics.median(values)


def export_models(out_dir: Path, size, seed: int) -> dict:
    from trianflow_vo.models.checkpoint import checkpoint_from_dict, random_checkpoint
    from trianflow_vo.models.export import export_checkpoint

    ckpt = checkpoint_from_dict(random_checkpoint(seed, size))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        export_checkpoint(ckpt, out_dir, size, seed)
    return {"ckpt": ckpt}


def _masks_torch(flow_fw, flow_bw, range_threshold: float = 0.5):
    """The research-style baseline's masks, in torch: M_s = 1 / (0.1 + |f(x) + b(x + f(x))|)
    and M_o (range map of ``flow_bw`` by bilinear splatting above the threshold, forward
    flow landing inside the image). Batch size 1. Only the eager baseline uses it."""
    import torch
    import torch.nn.functional as F

    _, _, h, w = flow_fw.shape
    ys = torch.arange(h, dtype=flow_fw.dtype).view(h, 1).expand(h, w)
    xs = torch.arange(w, dtype=flow_fw.dtype).view(1, w).expand(h, w)
    grid = torch.stack(((xs + flow_fw[0, 0]) * (2.0 / (w - 1)) - 1.0,
                        (ys + flow_fw[0, 1]) * (2.0 / (h - 1)) - 1.0), dim=2)[None]
    d = flow_fw + F.grid_sample(flow_bw, grid, mode="bilinear", padding_mode="border", align_corners=True)
    m_s = 1.0 / (0.1 + torch.sqrt(d[:, :1] ** 2 + d[:, 1:] ** 2))
    x = (xs + flow_bw[0, 0]).reshape(-1)
    y = (ys + flow_bw[0, 1]).reshape(-1)
    x0, y0 = torch.floor(x), torch.floor(y)
    idx_all, wgt_all = [], []
    for dx in (0.0, 1.0):
        for dy in (0.0, 1.0):
            xi, yi = x0 + dx, y0 + dy
            wgt = (1.0 - torch.abs(x - xi)) * (1.0 - torch.abs(y - yi))
            ok = (xi >= 0) & (xi <= w - 1) & (yi >= 0) & (yi <= h - 1)
            idx_all.append((yi.clamp(0, h - 1) * w + xi.clamp(0, w - 1)).to(torch.int64))
            wgt_all.append(torch.where(ok, wgt, torch.zeros_like(wgt)))
    rng = torch.zeros(h * w, dtype=flow_bw.dtype).scatter_add(0, torch.cat(idx_all), torch.cat(wgt_all))
    xt, yt = xs + flow_fw[0, 0], ys + flow_fw[0, 1]
    inside = (xt >= 0) & (xt <= w - 1) & (yt >= 0) & (yt <= h - 1)
    m_o = ((rng.view(h, w) > range_threshold) & inside).to(flow_fw.dtype)[None, None]
    return m_s, m_o


def bench_ours(model_dir: Path, frames, threads: int) -> dict:
    from trianflow_vo.depth.onnx_depth import OnnxDepthNet
    from trianflow_vo.flow.masks import flow_scores
    from trianflow_vo.flow.onnx_flow import OnnxFlow

    flow = OnnxFlow(model_dir / "flow.onnx", threads=threads)
    depth = OnnxDepthNet(model_dir / "depth.onnx", threads=threads)
    # warm-up (first runs allocate)
    p0 = flow.prepare(frames[0])
    flow.flow_pair(p0, p0)
    depth.predict(frames[0])
    stages = {k: [] for k in ("prepare", "flow_fw_bw", "depth", "masks_numpy", "total")}
    prev, _ = _timed(flow.prepare, frames[0])
    depth.predict(frames[0])
    for i in range(1, len(frames)):
        cur, t_prep = _timed(flow.prepare, frames[i])
        (fw, bw), t_flow = _timed(flow.flow_pair, prev, cur)
        # depth once per frame: frame i-1's depth was computed for the previous pair
        _, t_depth = _timed(depth.predict, frames[i])
        _, t_mnp = _timed(flow_scores, fw, bw)
        stages["prepare"].append(t_prep)
        stages["flow_fw_bw"].append(t_flow)
        stages["depth"].append(t_depth)
        stages["masks_numpy"].append(t_mnp)
        stages["total"].append(t_prep + t_flow + t_depth + t_mnp)
        prev = cur
    if depth.n_inferences != len(frames) + 1:  # + the warm-up
        raise RuntimeError(f"depth ran {depth.n_inferences} times for {len(frames)} frames")
    return {k: _median_ms(v) for k, v in stages.items()}


def bench_torch_eager(ckpt, frames, threads: int) -> dict:
    import torch

    from trianflow_vo.models.export import DepthGraph, FlowGraph

    torch.set_num_threads(threads)
    flow_net = FlowGraph(ckpt.flow.net, ckpt.flow.normalisation).eval()
    depth_net = DepthGraph(ckpt.depth.net, ckpt.depth.normalisation).eval()
    pwc = flow_net.net

    def to_t(img):
        return torch.from_numpy(np.ascontiguousarray(img[:, :, ::-1].transpose(2, 0, 1), dtype=np.float32))[None]

    def flows(a, b):
        h, w = a.shape[2:]
        na, nb = flow_net.norm(a), flow_net.norm(b)
        fw = pwc.full_flow(pwc(na, nb)[0], (h, w))
        bw = pwc.full_flow(pwc(nb, na)[0], (h, w))
        return fw, bw

    def masks(fw, bw):
        return _masks_torch(fw, bw)

    def depths(a, b):
        return depth_net(a), depth_net(b)

    a = to_t(frames[0])
    flows(a, a)
    stages = {k: [] for k in ("prepare", "flow_fw_bw", "depth", "masks", "total")}
    for i in range(1, len(frames)):
        (ta, tb), t_prep = _timed(lambda: (to_t(frames[i - 1]), to_t(frames[i])))
        (fw, bw), t_flow = _timed(flows, ta, tb)
        _, t_mask = _timed(masks, fw, bw)
        _, t_depth = _timed(depths, ta, tb)
        stages["prepare"].append(t_prep)
        stages["flow_fw_bw"].append(t_flow)
        stages["masks"].append(t_mask)
        stages["depth"].append(t_depth)
        stages["total"].append(t_prep + t_flow + t_mask + t_depth)
    return {k: _median_ms(v) for k, v in stages.items()}


def bench_ort_settings(model_dir: Path, frames, threads: int, repeats: int) -> list[dict]:
    """Flow graph alone under onnxruntime optimisation levels, spinning and thread counts."""
    import onnxruntime as ort

    from trianflow_vo.flow.onnx_flow import OnnxFlow

    src = OnnxFlow(model_dir / "flow.onnx", threads=threads)
    feed = {"image1": src.prepare(frames[0]).tensor, "image2": src.prepare(frames[1]).tensor}
    levels = {"basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
              "extended": ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED,
              "all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL}
    rows = []
    variants = [("all", threads, True), ("extended", threads, True), ("basic", threads, True),
                ("all", threads, False), ("all", 1, True)]
    for level, n_threads, spin in variants:
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = n_threads
        opts.inter_op_num_threads = 1
        opts.graph_optimization_level = levels[level]
        opts.add_session_config_entry("session.intra_op.allow_spinning", "1" if spin else "0")
        sess = ort.InferenceSession(str(model_dir / "flow.onnx"), opts, providers=["CPUExecutionProvider"])
        sess.run(None, feed)
        times = [_timed(sess.run, None, feed)[1] for _ in range(repeats)]
        rows.append({"opt_level": level, "threads": n_threads, "spinning": spin, "flow_fw_bw_ms": _median_ms(times)})
    return rows


def bench_flow_levels(ckpt, size, threads: int) -> list[dict]:
    """Where the flow time goes: torch profile of one forward+backward call, per module group."""
    import torch

    torch.set_num_threads(threads)
    net = ckpt.flow.net
    h, w = size
    x = torch.rand(1, 3, h, w)
    groups = {"pyramid": net.pyramid, "context": net.context}
    for k, lvl in enumerate(net.levels):
        groups[f"estimator L{lvl}"] = net.estimators[k]
    spent = {name: 0.0 for name in groups}
    hooks = []
    starts = {}
    for name, mod in groups.items():
        hooks.append(mod.register_forward_pre_hook(lambda m, i, n=name: starts.__setitem__(n, time.perf_counter())))
        hooks.append(mod.register_forward_hook(
            lambda m, i, o, n=name: spent.__setitem__(n, spent[n] + time.perf_counter() - starts[n])))
    with torch.no_grad():
        net.forward_backward(x, x)
        for n in spent:
            spent[n] = 0.0
        t = time.perf_counter()
        net.forward_backward(x, x)
        total = time.perf_counter() - t
    for hk in hooks:
        hk.remove()
    rows = [{"part": n, "ms": 1000 * v} for n, v in spent.items()]
    rows.append({"part": "cost volumes, warping, upsampling (rest)", "ms": 1000 * (total - sum(spent.values()))})
    rows.append({"part": "total (torch no_grad)", "ms": 1000 * total})
    return rows


def _gflops(ckpt, size) -> dict:
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    h, w = size
    x = torch.rand(1, 3, h, w)
    with torch.no_grad():
        with FlopCounterMode(display=False) as fc:
            ckpt.flow.net.forward_backward(x, x)
        flow = fc.get_total_flops() / 1e9
        with FlopCounterMode(display=False) as fc:
            ckpt.depth.net.depth(x)
        depth = fc.get_total_flops() / 1e9
    return {"flow_fw_bw": flow, "depth": depth}


def _markdown(res: dict) -> str:
    o, t = res["ours_ms"], res["torch_eager_ms"]
    lines = [
        f"## Network path (flow + depth networks, {res['size_hw'][0]}x{res['size_hw'][1]})",
        "",
        f"`{res['command']}` on {res['machine']} ({res['cpu_count']} cores), {res['threads']} threads, "
        f"{res['pairs']} pairs of `{res['seq']}`, random weights, paper-size architectures "
        f"(PWC-Net fw+bw {res['gflop']['flow_fw_bw']:.0f} GFLOP, depth {res['gflop']['depth']:.0f} GFLOP per call). "
        f"Load average at start: {res['load_average']} (a shared machine: ratios measured in one run are more "
        "reliable than absolute times).",
        "",
        "| stage (median ms per pair) | ours: onnxruntime | PyTorch eager (research style) |",
        "|---|---:|---:|",
        f"| prepare (resize, convert) | {o['prepare']:.1f} | {t['prepare']:.1f} |",
        f"| flow forward + backward | {o['flow_fw_bw']:.1f} (one call, shared pyramid) | {t['flow_fw_bw']:.1f} (two calls) |",
        f"| depth | {o['depth']:.1f} (once per frame) | {t['depth']:.1f} (both frames) |",
        f"| masks M_s, M_o | {o['masks_numpy']:.1f} (numpy) | {t['masks']:.1f} (torch) |",
        f"| **total network path** | **{o['total']:.1f}** | **{t['total']:.1f}** |",
        "",
        f"Ratio eager / ours: **{res['ratio_eager_over_ours']:.2f}x**. Target <= 300 ms per pair: "
        f"{'met' if o['total'] <= 300 else 'NOT met'}. Geometry (sampling, essential matrix, triangulation/PnP) "
        "is not in these numbers: see the pipeline timing in `run.json` (`timing_ms_median`).",
        "",
        f"Masks: numpy (`vo.flow.masks.flow_scores`) {o['masks_numpy']:.1f} ms; `OnnxFlow` returns flows only and "
        "the pipeline computes the masks with numpy. (The in-graph masks variant was removed: it measured about "
        "twice as slow as numpy and the run path never used it.)",
        "",
        "Flow graph alone under onnxruntime settings:",
        "",
        "| optimisation level | threads | spinning | flow fw+bw ms |",
        "|---|---:|---|---:|",
    ]
    for r in res["ort_settings"]:
        lines.append(f"| {r['opt_level']} | {r['threads']} | {r['spinning']} | {r['flow_fw_bw_ms']:.1f} |")
    lines += ["", "Where the flow time goes (torch, no_grad, one fw+bw call):", "", "| part | ms |", "|---|---:|"]
    for r in res["flow_breakdown"]:
        lines.append(f"| {r['part']} | {r['ms']:.1f} |")
    g = res["gflop"]["flow_fw_bw"] + res["gflop"]["depth"]
    lines += [
        "",
        f"What bounds it: one pair costs {g:.0f} GFLOP of fp32 arithmetic (flow fw+bw "
        f"{res['gflop']['flow_fw_bw']:.0f}, depth {res['gflop']['depth']:.0f}); 300 ms needs {g / 0.3:.0f} GFLOP/s "
        f"sustained, against an fp32 peak of roughly 320-380 GFLOP/s for two AVX-512 cores (2 x 64 flop/cycle x "
        f"~2.5-3 GHz) of which convolutions reach about half: we sustain {g / (o['total'] / 1000.0):.0f} GFLOP/s. "
        "Most of the flow cost is at the finest decoded level (1/4 resolution): its estimator and the context "
        "network, then the cost volumes (memory-bound). onnxruntime settings change little (table above). "
        "What would meet it, none applied silently: int8 (VNNI/AMX) quantisation of the convolutions, a lower "
        "working size, or a lighter flow decoder; each changes accuracy and needs trained weights to judge.",
        "",
    ]
    return "\n".join(lines)


# ---------------------------------------------------------------------------
# split flow graphs (encoder per frame, decoder per pair), int8, onnxruntime settings


def _rss_mb() -> dict:
    """Current and peak resident memory of this process (MB)."""
    out = {}
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(("VmRSS:", "VmHWM:")):
            out["rss" if line.startswith("VmRSS") else "peak"] = int(line.split()[1]) / 1024
    return out


def _make_variant(name: str, dirs: dict, threads: int):
    from trianflow_vo.depth.onnx_depth import OnnxDepthNet
    from trianflow_vo.flow.onnx_flow import OnnxFlow

    d = dirs.get(name) or (dirs["int8"] if name == "split-int8" else dirs["fp32"])  # a variant's own dir first
    flow = OnnxFlow(d / "flow.onnx", threads=threads, split=(name != "single"))
    return flow, OnnxDepthNet(d / "depth.onnx", threads=threads)


def bench_variants(dirs: dict, frames, threads: int, names: list[str]) -> dict:
    """Per pair, every variant in turn (order rotated each pair): prepare (+ encoder when
    split), flow (single graph or decoder), depth (once per frame), masks (numpy)."""
    from trianflow_vo.flow.masks import flow_scores

    models = {n: _make_variant(n, dirs, threads) for n in names}
    prev = {}
    for n, (flow, depth) in models.items():  # warm-up, and frame 0
        p0 = flow.prepare(frames[0])
        flow.flow_pair(p0, p0)
        depth.predict(frames[0])
        prev[n] = flow.prepare(frames[0])
    st = {n: {k: [] for k in ("prepare_encoder", "flow", "depth", "masks", "total")} for n in names}
    for i in range(1, len(frames)):
        order = names[i % len(names):] + names[:i % len(names)]
        for n in order:
            flow, depth = models[n]
            cur, t_prep = _timed(flow.prepare, frames[i])
            (fw, bw), t_flow = _timed(flow.flow_pair, prev[n], cur)
            _, t_depth = _timed(depth.predict, frames[i])
            _, t_masks = _timed(flow_scores, fw, bw)
            for k, v in (("prepare_encoder", t_prep), ("flow", t_flow), ("depth", t_depth), ("masks", t_masks),
                         ("total", t_prep + t_flow + t_depth + t_masks)):
                st[n][k].append(v)
            prev[n] = cur
    return {n: {k: _median_ms(v) for k, v in d.items()} for n, d in st.items()}


def peak_rss(variant: str, dirs: dict, seq: Path, size, threads: int, pairs: int = 3) -> dict:
    """Peak RSS of a fresh process that opens one variant and runs ``pairs`` pairs."""
    import subprocess

    code = (f"import sys; sys.argv=['x']; sys.path.insert(0, {str(REPO)!r});"
            "from benchmarks.bench_network import _rss_worker; "
            f"_rss_worker({variant!r}, {str(dirs['fp32'])!r}, {str(dirs.get('int8') or dirs['fp32'])!r}, "
            f"{str(seq)!r}, {list(size)!r}, {threads}, {pairs})")
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def _rss_worker(variant, fp32, int8, seq, size, threads, pairs):
    frames = _load_frames(Path(seq), pairs + 1, tuple(size))
    base = _rss_mb()["rss"]
    flow, depth = _make_variant(variant, {"fp32": Path(fp32), "int8": Path(int8)}, threads)
    loaded = _rss_mb()["rss"]
    prev = flow.prepare(frames[0])
    for f in frames[1:]:
        cur = flow.prepare(f)
        flow.flow_pair(prev, cur)
        depth.predict(f)
        prev = cur
    print(json.dumps({"base_mb": base, "after_open_mb": loaded, "peak_mb": _rss_mb()["peak"]}))


def bench_ort_split_settings(model_dir: Path, frames, threads: int, repeats: int) -> list[dict]:
    """Encoder + decoder (split fp32 graphs) per pair under onnxruntime settings, interleaved."""
    import onnxruntime as ort

    from trianflow_vo.flow.onnx_flow import OnnxFlow

    src = OnnxFlow(model_dir / "flow.onnx", threads=threads)
    enc_in = src.prepare(frames[0]).tensor
    pa, pb = src.prepare(frames[0]).features, src.prepare(frames[1]).features
    dec_feed = dict(zip(src.decoder.info.input_names, [*pa, *pb]))
    levels = {"basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
              "extended": ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED,
              "all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL}
    variants = [("all", threads, False, "sequential"), ("all", threads, True, "sequential"),
                ("extended", threads, False, "sequential"), ("basic", threads, False, "sequential"),
                ("all", threads, False, "parallel"), ("all", 1, False, "sequential")]
    sessions = []
    for level, n_threads, spin, mode in variants:
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = n_threads
        opts.inter_op_num_threads = 1
        opts.graph_optimization_level = levels[level]
        opts.execution_mode = (ort.ExecutionMode.ORT_PARALLEL if mode == "parallel"
                               else ort.ExecutionMode.ORT_SEQUENTIAL)
        opts.log_severity_level = 3
        opts.add_session_config_entry("session.intra_op.allow_spinning", "1" if spin else "0")
        enc = ort.InferenceSession(str(src.encoder.info.path), opts, providers=["CPUExecutionProvider"])
        dec = ort.InferenceSession(str(src.decoder.info.path), opts, providers=["CPUExecutionProvider"])
        enc.run(None, {"image": enc_in})
        dec.run(None, dec_feed)
        sessions.append((enc, dec, {"encoder": [], "decoder": []}))
    for _ in range(repeats):  # interleaved
        for enc, dec, t in sessions:
            t["encoder"].append(_timed(enc.run, None, {"image": enc_in})[1])
            t["decoder"].append(_timed(dec.run, None, dec_feed)[1])
    rows = []
    for (level, n_threads, spin, mode), (_, _, t) in zip(variants, sessions):
        e, d = _median_ms(t["encoder"]), _median_ms(t["decoder"])
        rows.append({"opt_level": level, "threads": n_threads, "spinning": spin, "execution_mode": mode,
                     "encoder_ms": e, "decoder_ms": d, "per_pair_ms": e + d})
    return rows


def int8_accuracy(dirs: dict, seqs: list[Path], size, threads: int, n: int) -> list[dict]:
    """Flow end-point error (working pixels) and depth relative error of int8 against fp32."""
    from trianflow_vo.depth.onnx_depth import OnnxDepthNet
    from trianflow_vo.flow.onnx_flow import OnnxFlow

    f32 = OnnxFlow(dirs["fp32"] / "flow.onnx", threads=threads)
    f8 = OnnxFlow(dirs["int8"] / "flow.onnx", threads=threads)
    d32 = OnnxDepthNet(dirs["fp32"] / "depth.onnx", threads=threads)
    d8 = OnnxDepthNet(dirs["int8"] / "depth.onnx", threads=threads)
    rows = []
    for seq in seqs:
        frames = _load_frames(seq, n + 1, size)
        epe, mag, rel = [], [], []
        for a, b in zip(frames[:-1], frames[1:]):
            ref, _ = f32.flow_pair(f32.prepare(a), f32.prepare(b))
            got, _ = f8.flow_pair(f8.prepare(a), f8.prepare(b))
            epe.append(np.linalg.norm(got - ref, axis=2).ravel())
            mag.append(np.linalg.norm(ref, axis=2).ravel())
            r32, r8 = d32.predict(b), d8.predict(b)
            rel.append((np.abs(r8 - r32) / r32).ravel())
        epe, mag, rel = np.concatenate(epe), np.concatenate(mag), np.concatenate(rel)
        rows.append({"seq": str(seq.relative_to(REPO)) if seq.is_relative_to(REPO) else str(seq), "pairs": n,
                     "flow_epe_median_px": float(np.median(epe)), "flow_epe_mean_px": float(epe.mean()),
                     "flow_epe_p99_px": float(np.percentile(epe, 99)),
                     "fp32_flow_median_magnitude_px": float(np.median(mag)),
                     "depth_rel_err_median": float(np.median(rel)), "depth_rel_err_mean": float(rel.mean())})
    return rows


def _markdown_split(res: dict) -> str:
    v = res["variants_ms"]
    names = list(v)
    lines = [
        f"## Split flow graphs, int8, onnxruntime settings ({res['date']}, {res['size_hw'][0]}x{res['size_hw'][1]})",
        "",
        f"`{res['command']}` on {res['machine']} ({res['cpu_count']} cores, {res['cpu_flags']}), "
        f"{res['threads']} threads, {res['pairs']} pairs of `{res['seq']}`, random weights, variants run "
        f"interleaved pair by pair, medians. onnxruntime {res['versions']['onnxruntime']}. Load average at "
        f"start / end: {res['load_average']} / {res['load_average_end']} (other jobs shared the 2 cores: "
        "absolute times are inflated; compare columns of this table, not with the older sections).",
        "",
        "| stage (median ms per pair) | " + " | ".join(names) + " |",
        "|---|" + "---:|" * len(names),
    ]
    labels = {"prepare_encoder": "prepare (resize, convert; + encoder when split)",
              "flow": "flow fw+bw (single graph / decoder)", "depth": "depth (once per frame)",
              "masks": "masks M_s, M_o (numpy)", "total": "**total per pair**"}
    for k, label in labels.items():
        cells = [f"{v[n][k]:.1f}" for n in names]
        if k == "total":
            cells = [f"**{c}**" for c in cells]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    if res.get("rss"):
        lines.append("| peak RSS MB (fresh process, 3 pairs) | " + " | ".join(
            f"{res['rss'][n]['peak_mb']:.0f}" for n in names) + " |")
    lines += ["", "Split graphs (encoder + decoder, fp32) under onnxruntime settings, interleaved:", "",
              "| optimisation | threads | spinning | execution mode | encoder ms | decoder ms | per pair ms |",
              "|---|---:|---|---|---:|---:|---:|"]
    for r in res["ort_split_settings"]:
        lines.append(f"| {r['opt_level']} | {r['threads']} | {r['spinning']} | {r['execution_mode']} | "
                     f"{r['encoder_ms']:.1f} | {r['decoder_ms']:.1f} | {r['per_pair_ms']:.1f} |")
    if res.get("int8_accuracy"):
        lines += ["", "int8 (static QDQ, calibrated on the first 8 frames of sample/kitti00) against fp32, "
                  "working pixels. **Random weights**: the fp32 flows are a fraction of a pixel and the depth "
                  "near constant, so these errors say little about trained networks; they need re-measuring "
                  "with the authors' weights.", "",
                  "| sequence | pairs | flow EPE median px | EPE mean | EPE p99 | fp32 flow median px | "
                  "depth rel. err. median | mean |", "|---|---:|---:|---:|---:|---:|---:|---:|"]
        for r in res["int8_accuracy"]:
            lines.append(f"| `{r['seq']}` | {r['pairs']} | {r['flow_epe_median_px']:.4f} | "
                         f"{r['flow_epe_mean_px']:.4f} | {r['flow_epe_p99_px']:.4f} | "
                         f"{r['fp32_flow_median_magnitude_px']:.3f} | {r['depth_rel_err_median']:.4f} | "
                         f"{r['depth_rel_err_mean']:.4f} |")
    lines += ["", res.get("notes", ""), ""]
    return "\n".join(lines)


def main_split(args, size, frames) -> int:
    """``--split``: fp32 single vs fp32 split vs int8 split, ORT settings, RSS, int8 accuracy."""
    import datetime
    import subprocess

    import onnxruntime

    with tempfile.TemporaryDirectory() as tmp:
        dirs = {"fp32": args.models or Path(tmp) / "fp32"}
        if args.models is None:
            print(f"exporting random-init models at {size[0]}x{size[1]} ...", flush=True)
            export_models(dirs["fp32"], size, 0)
        names = ["single", "split"]
        if args.int8_models is not None or not args.no_int8:
            dirs["int8"] = args.int8_models or Path(tmp) / "int8"
            if args.int8_models is None:
                print("exporting int8 models ...", flush=True)
                subprocess.run([sys.executable, "-m", "trianflow_vo.cli.main", "export", "--random-init",
                                "--size", args.size, "--out-dir", str(dirs["int8"]), "--quantize", "int8",
                                "--calibration", str(REPO / "sample" / "kitti00")], check=True)
            names.append("split-int8")
        load = os.getloadavg()
        print("variants, interleaved ...", flush=True)
        variants = bench_variants(dirs, frames, args.threads, names)
        print("peak RSS ...", flush=True)
        rss = {n: peak_rss(n, dirs, args.seq, size, args.threads) for n in names}
        print("onnxruntime settings (split graphs) ...", flush=True)
        settings = bench_ort_split_settings(dirs["fp32"], frames, args.threads, repeats=max(3, args.pairs // 2))
        acc = []
        if "int8" in dirs:
            print("int8 accuracy ...", flush=True)
            seqs = [args.seq] + [p for p in (REPO.parent / "shared" / "data" / "kitti00-f0000-0150",) if p.is_dir()]
            acc = int8_accuracy(dirs, seqs, size, args.threads, args.pairs)
        load_end = os.getloadavg()
    flags = Path("/proc/cpuinfo").read_text().split("flags", 1)[-1].split("\n", 1)[0].split()
    simd = ", ".join(f for f in ("avx2", "avx512f", "avx512_vnni", "avx_vnni", "amx_int8") if f in flags)
    res = {
        "date": datetime.date.today().isoformat(),
        "command": "python benchmarks/bench_network.py " + " ".join(args.argv),
        "machine": platform.processor() or platform.machine(), "cpu_count": os.cpu_count(), "cpu_flags": simd,
        "load_average": [round(v, 2) for v in load], "load_average_end": [round(v, 2) for v in load_end],
        "threads": args.threads, "pairs": args.pairs,
        "seq": str(args.seq.relative_to(REPO)) if args.seq.is_relative_to(REPO) else str(args.seq),
        "size_hw": list(size), "versions": {"onnxruntime": onnxruntime.__version__},
        "variants_ms": variants, "rss": rss, "ort_split_settings": settings, "int8_accuracy": acc,
        "target_ms": 300.0,
    }
    for n, v in variants.items():
        print(f"{n:12s} " + "  ".join(f"{k} {x:.1f}" for k, x in v.items()) + f"  peak RSS {rss[n]['peak_mb']:.0f} MB")
    for r in settings:
        print(f"ORT opt={r['opt_level']:9s} threads={r['threads']} spin={r['spinning']!s:5s} "
              f"mode={r['execution_mode']:10s} enc {r['encoder_ms']:.1f} dec {r['decoder_ms']:.1f} ms")
    for r in acc:
        print(json.dumps(r))
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(res, indent=2))
    if args.append_md:
        with open(args.md, "a") as fh:
            fh.write("\n" + _markdown_split(res))
        print(f"wrote {args.json}, appended to {args.md}")
    else:
        print(f"wrote {args.json}")
    return 0


# ---------------------------------------------------------------------------
# --costvol: the matrix-product cost volume against the reference formulation

COSTVOL_VARIANTS = ("split-ref", "split-new", "int8-ref", "int8-new")


def _export_with(cost_fn_name: str, out_dir: Path, size, quantize: bool, calibration) -> None:
    """Seed-0 random-init export into ``out_dir`` with ``pwc.<cost_fn_name>`` as the cost volume."""
    from unittest import mock

    from trianflow_vo.models import pwc
    from trianflow_vo.models.checkpoint import checkpoint_from_dict, random_checkpoint
    from trianflow_vo.models.export import export_checkpoint

    ckpt = checkpoint_from_dict(random_checkpoint(0, size), "<random-init>")
    with mock.patch.object(pwc, "cost_volume", getattr(pwc, cost_fn_name)), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        export_checkpoint(ckpt, out_dir, size, 0, quantize="int8" if quantize else None,
                          calibration=calibration if quantize else None)


def _calibration(seq: Path, n: int = 8) -> list[np.ndarray]:
    """What ``export --calibration SEQ`` reads: the first ``n`` frames, BGR, original size."""
    folder = seq / "image_0" if (seq / "image_0").is_dir() else seq
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))[:n]
    return [cv2.imread(str(p), cv2.IMREAD_COLOR) for p in files]


def _decoder_ops(model_dir: Path) -> dict:
    """Node counts of the cost-volume ops in ``model_dir``'s flow decoder (which formulation it is)."""
    import onnx

    ops = [n.op_type for n in onnx.load(str(model_dir / "flow_decoder.onnx"), load_external_data=False).graph.node]
    return {op: ops.count(op) for op in ("MatMul", "ReduceMean", "Slice", "Mul", "GridSample")} | {"nodes": len(ops)}


def bench_costvol_levels(size, threads: int, repeats: int, tmp: Path) -> list[dict]:
    """Cost volume alone (fp32 ONNX graph, batch 2 as in the decoder) per pyramid level: median ms."""
    import onnxruntime as ort
    import torch

    from trianflow_vo.models.export import OPSET
    from trianflow_vo.models.pwc import PWCConfig, cost_volume, cost_volume_reference

    class _CV(torch.nn.Module):
        def __init__(self, fn, d):
            super().__init__()
            self.fn, self.d = fn, d

        def forward(self, a, b):
            return self.fn(a, b, self.d)

    cfg = PWCConfig()
    h, w = size
    rng = np.random.default_rng(0)
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")  # the run path's settings
    rows = []
    for lvl in range(len(cfg.pyramid_channels), cfg.output_level - 1, -1):
        shape = (2, cfg.pyramid_channels[lvl - 1], h >> lvl, w >> lvl)
        feed = {"a": rng.standard_normal(shape).astype(np.float32), "b": rng.standard_normal(shape).astype(np.float32)}
        sessions, ref_out = {}, None
        for name, fn in (("ref", cost_volume_reference), ("new", cost_volume)):
            path = tmp / f"cv_{name}_L{lvl}.onnx"
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                torch.onnx.export(_CV(fn, cfg.search_range), tuple(torch.from_numpy(v) for v in feed.values()),
                                  str(path), input_names=["a", "b"], output_names=["cost"], opset_version=OPSET,
                                  dynamo=False)
            sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
            out = sess.run(None, feed)[0]
            ref_out = out if ref_out is None else ref_out
            sessions[name] = (sess, [], float(np.abs(out - ref_out).max()))
        for _ in range(repeats):
            for sess, t, _ in sessions.values():
                t.append(_timed(sess.run, None, feed)[1])
        r, n = _median_ms(sessions["ref"][1]), _median_ms(sessions["new"][1])
        rows.append({"level": lvl, "shape": list(shape), "ref_ms": r, "new_ms": n, "ratio_new_over_ref": n / r,
                     "max_abs_diff": sessions["new"][2]})
    return rows


def flow_difference(dir_a: Path, dir_b: Path, frames, threads: int) -> dict:
    """Max and median |flow_b - flow_a| (working pixels, both directions) over consecutive pairs."""
    from trianflow_vo.flow.onnx_flow import OnnxFlow

    fa, fb = OnnxFlow(dir_a / "flow.onnx", threads=threads), OnnxFlow(dir_b / "flow.onnx", threads=threads)
    diffs = []
    for a, b in zip(frames[:-1], frames[1:]):
        ra = fa.flow_pair(fa.prepare(a), fa.prepare(b))
        rb = fb.flow_pair(fb.prepare(a), fb.prepare(b))
        diffs += [np.abs(y - x).ravel() for x, y in zip(ra, rb)]
    d = np.concatenate(diffs)
    return {"max_px": float(d.max()), "median_px": float(np.median(d))}


def _train_step_worker(cost_fn_name: str, size, batch: int, threads: int, steps: int) -> None:
    """One process: PWCNet (paper sizes) forward of ``batch`` pairs + backward of a loss on all
    decoded levels, ``steps`` times; prints JSON (median s per step, peak RSS MB)."""
    from unittest import mock

    import torch

    from trianflow_vo.models import pwc

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    net = pwc.PWCNet().train()
    h, w = size
    img1, img2 = torch.rand(batch, 3, h, w), torch.rand(batch, 3, h, w)
    base = _rss_mb()["rss"]
    times = []
    with mock.patch.object(pwc, "cost_volume", getattr(pwc, cost_fn_name)):
        for _ in range(steps):
            t = time.perf_counter()
            flows = net(img1, img2)
            loss = sum(f.abs().mean() for f in flows)
            loss.backward()
            times.append(time.perf_counter() - t)
            net.zero_grad(set_to_none=True)
            del flows, loss
    print(json.dumps({"step_ms": _median_ms(times), "first_step_ms": 1000 * times[0], "base_rss_mb": base,
                      "peak_rss_mb": _rss_mb()["peak"]}))


def train_step(cost_fn_name: str, size, batch: int, threads: int, steps: int) -> dict:
    import subprocess

    code = (f"import sys; sys.argv=['x']; sys.path.insert(0, {str(REPO)!r});"
            "from benchmarks.bench_network import _train_step_worker; "
            f"_train_step_worker({cost_fn_name!r}, {list(size)!r}, {batch}, {threads}, {steps})")
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def _markdown_costvol(res: dict) -> str:
    v = res["variants_ms"]
    names = list(v)
    lines = [
        f"## Cheaper cost volume ({res['date']}, {res['size_hw'][0]}x{res['size_hw'][1]})",
        "",
        f"`{res['command']}` on {res['machine']} ({res['cpu_count']} cores, {res['cpu_flags']}), "
        f"{res['threads']} threads, {res['pairs']} pairs of `{res['seq']}`, random seed-0 weights (the same in "
        f"every column), onnxruntime {res['versions']['onnxruntime']}, torch {res['versions']['torch']}. "
        f"Load average at start / end: {res['load_average']} / {res['load_average_end']}.",
        "",
        "`models/pwc.py: cost_volume` is now computed with matrix products: per `dy` one batched MatMul of "
        "8-pixel tiles of `f1` (8 x C) with the `f2` columns their shifts reach (C x 16), the 9 wanted dot "
        "products taken from the band by a pad + reshape; the old formulation (81 slice + multiply + channel "
        "mean per level) is kept as `cost_volume_reference`. Same function (max difference below).",
        "",
        "Cost volume alone (fp32 ONNX graph, batch 2 = both directions, the run path's session settings), "
        "interleaved, median ms per call:",
        "",
        "| level | f1, f2 shape | reference | new | new / ref | max abs diff |",
        "|---|---|---:|---:|---:|---:|",
    ]
    tr = tn = 0.0
    for r in res["costvol_levels"]:
        tr, tn = tr + r["ref_ms"], tn + r["new_ms"]
        lines.append(f"| {r['level']} | {'x'.join(map(str, r['shape']))} | {r['ref_ms']:.2f} | {r['new_ms']:.2f} | "
                     f"{r['ratio_new_over_ref']:.2f} | {r['max_abs_diff']:.1e} |")
    lines += [f"| **all levels** | | **{tr:.1f}** | **{tn:.1f}** | **{tn / tr:.2f}** | |", "",
              "Network path per pair, variants interleaved pair by pair (`ref` = exported with the reference "
              "cost volume, `new` = with the current code; int8 = `export --quantize int8 --calibration "
              "sample/kitti00`), median ms:", "",
              "| stage (median ms per pair) | " + " | ".join(names) + " |", "|---|" + "---:|" * len(names)]
    labels = {"prepare_encoder": "prepare + encoder", "flow": "flow decoder (fw+bw)", "depth": "depth",
              "masks": "masks (numpy)", "total": "**total per pair**"}
    for k, label in labels.items():
        cells = [f"{v[n][k]:.1f}" for n in names]
        if k == "total":
            cells = [f"**{c}**" for c in cells]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    ops = res["decoder_ops"]
    lines.append("| decoder nodes (MatMul / ReduceMean / Slice / Mul) | " + " | ".join(
        f"{ops[n]['nodes']} ({ops[n]['MatMul']} / {ops[n]['ReduceMean']} / {ops[n]['Slice']} / {ops[n]['Mul']})"
        for n in names) + " |")
    rt = res["ratios"]
    lines += ["", f"Ratios in this run: fp32 decoder new / ref **{rt['fp32_decoder']:.2f}**, fp32 total "
              f"{rt['fp32_total']:.2f}; int8 decoder new / ref **{rt['int8_decoder']:.2f}**, int8 total per pair "
              f"**{rt['int8_total']:.2f}** ({v['int8-new']['total']:.1f} vs {v['int8-ref']['total']:.1f} ms).", ""]
    fd = res["flow_new_minus_ref"]
    lines += [f"Flow new - reference (fp32 split graphs, same weights, {res['pairs']} pairs, both directions): "
              f"max {fd['max_px']:.1e} px, median {fd['median_px']:.1e} px.", ""]
    if res.get("int8_accuracy"):
        lines += ["int8 against its own fp32 (working pixels; random weights, see the caveat above):", "",
                  "| cost volume | sequence | flow EPE median px | EPE mean | EPE p99 | depth rel. err. median |",
                  "|---|---|---:|---:|---:|---:|"]
        for name, rows in res["int8_accuracy"].items():
            for r in rows:
                lines.append(f"| {name} | `{r['seq']}` | {r['flow_epe_median_px']:.4f} | {r['flow_epe_mean_px']:.4f} "
                             f"| {r['flow_epe_p99_px']:.4f} | {r['depth_rel_err_median']:.4f} |")
        lines.append("")
    t = res["train_step"]
    lines += [f"Training step in torch (PWCNet paper sizes, `train()`, batch {t['batch']} at "
              f"{res['size_hw'][0]}x{res['size_hw'][1]}: forward of all levels + backward of a loss on them, "
              f"{t['steps']} steps, each formulation in a fresh process, {res['threads']} threads):", "",
              "| cost volume | step ms (median) | peak RSS MB | RSS before the step MB |", "|---|---:|---:|---:|"]
    for name in ("reference", "new"):
        r = t[name]
        lines.append(f"| {name} | {r['step_ms']:.0f} | {r['peak_rss_mb']:.0f} | {r['base_rss_mb']:.0f} |")
    lines += ["", res.get("notes", ""), ""]
    return "\n".join(lines)


def main_costvol(args, size, frames) -> int:
    """``--costvol``: matrix-product cost volume vs the reference formulation (see the module docstring)."""
    import datetime

    import onnxruntime
    import torch

    with tempfile.TemporaryDirectory() as tmp_s:
        tmp = Path(tmp_s)
        calib = _calibration(REPO / "sample" / "kitti00")
        dirs = {"split-ref": args.models, "int8-ref": args.int8_models,
                "split-new": args.new_models, "int8-new": args.new_int8_models}
        for name, d in list(dirs.items()):
            if d is None:
                dirs[name] = tmp / name
                print(f"exporting {name} ...", flush=True)
                _export_with("cost_volume_reference" if name.endswith("-ref") else "cost_volume", dirs[name], size,
                             name.startswith("int8"), calib)
        ops = {n: _decoder_ops(d) for n, d in dirs.items()}
        for n, o in ops.items():  # the directories hold what their names say
            if (o["ReduceMean"] > 0) != n.endswith("-ref"):
                raise SystemExit(f"{dirs[n]}: its flow decoder does not use the {n.split('-')[1]} cost volume: {o}")
        load = os.getloadavg()
        print("cost volume alone, per level ...", flush=True)
        levels = bench_costvol_levels(size, args.threads, max(10, 3 * args.pairs), tmp)
        print("variants, interleaved ...", flush=True)
        variants = bench_variants(dirs, frames, args.threads, list(COSTVOL_VARIANTS))
        print("flow new - reference, int8 accuracy ...", flush=True)
        fdiff = flow_difference(dirs["split-ref"], dirs["split-new"], frames, args.threads)
        acc = {}
        for kind in ("ref", "new"):
            acc[kind] = int8_accuracy({"fp32": dirs[f"split-{kind}"], "int8": dirs[f"int8-{kind}"]}, [args.seq],
                                      size, args.threads, args.pairs)
        print("torch training step, fresh processes ...", flush=True)
        train = {"batch": args.train_batch, "steps": 3}
        for name, fn in (("reference", "cost_volume_reference"), ("new", "cost_volume")):
            train[name] = train_step(fn, size, args.train_batch, args.threads, 3)
        load_end = os.getloadavg()
    flags = Path("/proc/cpuinfo").read_text().split("flags", 1)[-1].split("\n", 1)[0].split()
    simd = ", ".join(f for f in ("avx2", "avx512f", "avx512_vnni", "avx_vnni", "amx_int8") if f in flags)
    v = variants
    res = {
        "date": datetime.date.today().isoformat(),
        "command": "python benchmarks/bench_network.py " + " ".join(args.argv),
        "machine": platform.processor() or platform.machine(), "cpu_count": os.cpu_count(), "cpu_flags": simd,
        "load_average": [round(x, 2) for x in load], "load_average_end": [round(x, 2) for x in load_end],
        "threads": args.threads, "pairs": args.pairs,
        "seq": str(args.seq.relative_to(REPO)) if args.seq.is_relative_to(REPO) else str(args.seq),
        "size_hw": list(size), "versions": {"onnxruntime": onnxruntime.__version__, "torch": torch.__version__},
        "model_dirs": {n: str(d) for n, d in dirs.items()}, "decoder_ops": ops,
        "costvol_levels": levels, "variants_ms": variants,
        "ratios": {"fp32_decoder": v["split-new"]["flow"] / v["split-ref"]["flow"],
                   "fp32_total": v["split-new"]["total"] / v["split-ref"]["total"],
                   "int8_decoder": v["int8-new"]["flow"] / v["int8-ref"]["flow"],
                   "int8_total": v["int8-new"]["total"] / v["int8-ref"]["total"]},
        "flow_new_minus_ref": fdiff, "int8_accuracy": acc, "train_step": train, "target_ms": 300.0,
    }
    for r in levels:
        print(f"L{r['level']} {r['shape']}: ref {r['ref_ms']:.2f} ms  new {r['new_ms']:.2f} ms  "
              f"ratio {r['ratio_new_over_ref']:.2f}  max diff {r['max_abs_diff']:.1e}")
    for n, x in v.items():
        print(f"{n:10s} " + "  ".join(f"{k} {y:.1f}" for k, y in x.items()))
    print("ratios new/ref: " + "  ".join(f"{k} {y:.3f}" for k, y in res["ratios"].items()))
    print(f"flow new - ref: {fdiff}")
    for k, rows in acc.items():
        for r in rows:
            print(f"int8 {k}: {json.dumps(r)}")
    for name in ("reference", "new"):
        print(f"train step {name}: {train[name]}")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(res, indent=2))
    if args.append_md:
        with open(args.md, "a") as fh:
            fh.write("\n" + _markdown_costvol(res))
        print(f"wrote {args.json}, appended to {args.md}")
    else:
        print(f"wrote {args.json}")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seq", type=Path, default=REPO / "sample" / "kitti00")
    ap.add_argument("--pairs", type=int, default=8)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--size", default="256x832")
    ap.add_argument("--models", type=Path, default=None,
                    help="directory with flow.onnx and depth.onnx (default: export random ones)")
    ap.add_argument("--json", type=Path, default=REPO / "benchmarks" / "out" / "network.json")
    ap.add_argument("--md", type=Path, default=REPO / "benchmarks" / "NETWORK.md")
    ap.add_argument("--render", type=Path, default=None, metavar="JSON",
                    help="only rewrite --md from an earlier --json result")
    ap.add_argument("--split", action="store_true",
                    help="single graph vs split encoder/decoder vs int8, ORT settings on the split graphs, "
                         "peak RSS, int8 accuracy (writes --json; --append-md appends a section to --md)")
    ap.add_argument("--int8-models", type=Path, default=None,
                    help="with --split: directory of an 'export --quantize int8' (default: export one)")
    ap.add_argument("--no-int8", action="store_true", help="with --split: skip the int8 variant")
    ap.add_argument("--append-md", action="store_true", help="with --split / --costvol: append the section to --md")
    ap.add_argument("--costvol", action="store_true",
                    help="matrix-product cost volume vs the reference formulation: per level, split fp32/int8 "
                         "paths interleaved, flow difference, torch training step (--models / --int8-models: "
                         "exports with the reference cost volume)")
    ap.add_argument("--new-models", type=Path, default=None,
                    help="with --costvol: fp32 export made with the current code (default: export one)")
    ap.add_argument("--new-int8-models", type=Path, default=None,
                    help="with --costvol: int8 export made with the current code (default: export one)")
    ap.add_argument("--train-batch", type=int, default=2, help="with --costvol: batch of the torch training step")
    args = ap.parse_args(argv)
    args.argv = list(argv if argv is not None else sys.argv[1:])
    if args.render is not None:
        args.md.write_text(_markdown(json.loads(args.render.read_text())))
        print(f"wrote {args.md}")
        return 0
    size = tuple(int(v) for v in args.size.split("x"))
    frames = _load_frames(args.seq, args.pairs + 1, size)
    cv2.setNumThreads(args.threads)
    if args.costvol:
        if args.json == REPO / "benchmarks" / "out" / "network.json":
            args.json = REPO / "benchmarks" / "out" / "network_costvol.json"
        return main_costvol(args, size, frames)
    if args.split:
        if args.json == REPO / "benchmarks" / "out" / "network.json":
            args.json = REPO / "benchmarks" / "out" / "network_split.json"
        return main_split(args, size, frames)

    from trianflow_vo.models.checkpoint import checkpoint_from_dict, random_checkpoint

    with tempfile.TemporaryDirectory() as tmp:
        model_dir = args.models or Path(tmp)
        if args.models is None:
            print(f"exporting random-init models at {size[0]}x{size[1]} ...", flush=True)
            export_models(model_dir, size, 0)
        ckpt = checkpoint_from_dict(random_checkpoint(0, size))
        load = os.getloadavg()
        print("onnxruntime path ...", flush=True)
        ours = bench_ours(model_dir, frames, args.threads)
        print("PyTorch eager ...", flush=True)
        eager = bench_torch_eager(ckpt, frames, args.threads)
        print("onnxruntime settings ...", flush=True)
        settings = bench_ort_settings(model_dir, frames, args.threads, repeats=3)
        breakdown = bench_flow_levels(ckpt, size, args.threads)
        gflop = _gflops(ckpt, size)
    import onnxruntime
    import torch

    res = {
        "command": "python benchmarks/bench_network.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "machine": platform.processor() or platform.machine(), "cpu_count": os.cpu_count(),
        "load_average": [round(v, 2) for v in load], "threads": args.threads, "pairs": args.pairs,
        "seq": str(args.seq.relative_to(REPO)) if args.seq.is_relative_to(REPO) else str(args.seq),
        "size_hw": list(size), "versions": {"onnxruntime": onnxruntime.__version__, "torch": torch.__version__},
        "ours_ms": ours, "torch_eager_ms": eager,
        "ratio_eager_over_ours": eager["total"] / ours["total"],
        "target_ms": 300.0, "ort_settings": settings, "flow_breakdown": breakdown, "gflop": gflop,
    }
    print()
    print(f"{'stage (median ms/pair)':28s} {'ours (ORT)':>12s} {'torch eager':>12s}")
    for k_ours, k_eager, label in (("prepare", "prepare", "prepare"), ("flow_fw_bw", "flow_fw_bw", "flow fw+bw"),
                                   ("depth", "depth", "depth"), (None, "masks", "masks"),
                                   ("total", "total", "total")):
        v = ours["masks_numpy"] if k_ours is None else ours[k_ours]
        print(f"{label:28s} {v:12.1f} {eager[k_eager]:12.1f}")
    print(f"ratio eager/ours {res['ratio_eager_over_ours']:.2f}x; target {res['target_ms']:.0f} ms "
          f"{'met' if ours['total'] <= 300 else 'NOT met'}")
    for r in settings:
        print(f"ORT opt={r['opt_level']:9s} threads={r['threads']} spin={r['spinning']!s:5s} flow {r['flow_fw_bw_ms']:.1f} ms")
    for r in breakdown:
        print(f"  {r['part']:42s} {r['ms']:8.1f} ms")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(res, indent=2))
    args.md.write_text(_markdown(res))
    print(f"wrote {args.json} and {args.md}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
