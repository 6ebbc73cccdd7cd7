"""The loop-closure kernels on the simulated CUDA device of ``../shared/tools/cuda_sim``: kernels,
host syncs and device mismatches per kernel call.

Each loop kernel (``torch_frontend.loop``: FAST, BRIEF, Hamming, keyframe description and BRIEF
matching, vocabulary training / transform, the place database, P3P / PnP-RANSAC / refinement,
triangulation, the pose-graph optimisers with each linear solver, loop verification and a whole
``PoseGraph`` run) is called once on small realistic inputs: keyframes of the rendered revisiting
room of ``torch_frontend.testing.synthetic`` (2 laps of 8 keyframes, 160x120, 60 tracked points;
the second lap revisits the first). Every input tensor is labelled ``cuda:0``
(``simcuda.to_sim``: the data stays on the CPU, the library takes its GPU code path); the inputs are
built on the CPU before the measured call, only the call is counted. RANSAC and k-medians get a
seeded CPU generator (a CPU-only torch has no CUDA generator): their draws are uploaded.

Columns: ``kernels`` (non-view ops on device tensors: at least one CUDA launch each), ``syncs``
(host syncs of every kind: ``.item()``, ``nonzero``, blocking copies, ...; informational, the loop
kernels are not required to be sync-free), ``device mismatches`` (ops that mix a CPU tensor that is
not 0-dim with cuda tensors: a real CUDA run raises there; must be 0), ``host ops`` (ops on CPU
tensors only: host work inside the call, e.g. formatting results), ``= CPU`` (the outputs equal
those of the same call on the CPU bit for bit; the CUDA code path may differ) and ``errors`` (the
call raised, e.g. ``.numpy()`` of a cuda tensor: the row is incomplete).

Run from the project root:

    .venv/bin/python benchmarks/sim_cuda_loop.py [--json out.json] [--kernels fast,brief] [--sites]
        [--no-compare] [--sim-dir ../shared/tools/cuda_sim] [--device sim|cuda]

``--sites`` lists the mismatch and sync sites (``file:line function``) per kernel. ``--device cuda``
runs the same calls on a real GPU instead (no simulator; a mismatch raises there). Exit code 0
whatever the figures; 2 when the simulator is missing or unusable here (no C++ compiler for its
guard, a CUDA build of torch) or for an unknown kernel name.
"""

from __future__ import annotations

import argparse
import collections
import importlib
import json
import sys
import time
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import torch

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

#: where the simulator lives beside the repository
DEFAULT_SIM_DIR = REPO.parent / "shared" / "tools" / "cuda_sim"

_F64 = torch.float64


def load_simcuda(sim_dir: Optional[Path] = None):
    """Import ``simcuda`` from ``sim_dir`` (default :data:`DEFAULT_SIM_DIR`) and install its no-op
    CUDA guard (built once with the system C++ compiler). Raises FileNotFoundError when absent."""
    d = Path(sim_dir) if sim_dir is not None else DEFAULT_SIM_DIR
    if not (d / "simcuda.py").is_file():
        raise FileNotFoundError(f"simulated CUDA tool not found: {d / 'simcuda.py'}")
    if str(d) not in sys.path:
        sys.path.insert(0, str(d))
    simcuda = importlib.import_module("simcuda")
    simcuda.enable()
    simcuda.watch_package("torch_frontend")
    return simcuda


# ---------------------------------------------------------------------------------------- inputs

def make_inputs(laps: int = 2, keyframes_per_lap: int = 8, width: int = 160, height: int = 120,
                max_points: int = 60) -> Dict[str, Any]:
    """CPU inputs of every kernel: the synthetic room's keyframes and what is derived from them."""
    from torch_frontend.geometry import R_to_quat, R_to_ypr
    from torch_frontend.loop.features import brief, default_brief_pattern, fast
    from torch_frontend.loop.keyframe import match_brief
    from torch_frontend.loop.optimize import measurements_4dof, measurements_6dof, sequential_edges
    from torch_frontend.loop.vocabulary import Vocabulary
    from torch_frontend.testing.synthetic import make_keyframes, render_loop_sequence

    seq = render_loop_sequence(laps=laps, keyframes_per_lap=keyframes_per_lap, width=width, height=height)
    kfs = make_keyframes(seq, max_points=max_points, min_dist=10)
    K = len(kfs)
    half = keyframes_per_lap
    imgs = seq.images[seq.keyframe_frames][:, None].contiguous()  # (K, 1, H, W) uint8
    pattern = default_brief_pattern()
    pts, _, valid = fast(imgs[:4])
    desc = brief(imgs[:4], pts, valid, pattern)
    # window points of the keyframes (tracked features), padded
    n_win = max(k.num_points for k in kfs)
    uv = torch.zeros(K, n_win, 2, dtype=torch.float32)
    uv_valid = torch.zeros(K, n_win, dtype=torch.bool)
    for b, k in enumerate(kfs):
        uv[b, :k.num_points] = k.point_2d_uv
        uv_valid[b, :k.num_points] = True
    # revisits: keyframe b + half (second lap) against keyframe b (first lap)
    pairs = [(b + half, b) for b in range(min(4, K - half))]
    curs = [kfs[c] for c, _ in pairs]
    olds = [kfs[o] for _, o in pairs]
    n_old = max(o.num_keypoints for o in olds)
    odesc = torch.zeros(len(pairs), n_old, 4, dtype=torch.int64)
    ovalid = torch.zeros(len(pairs), n_old, dtype=torch.bool)
    onorm = torch.zeros(len(pairs), n_old, 2, dtype=_F64)
    for b, o in enumerate(olds):
        odesc[b, :o.num_keypoints] = o.brief
        ovalid[b, :o.num_keypoints] = True
        onorm[b, :o.num_keypoints] = o.keypoints_norm
    wdesc = torch.zeros(len(pairs), n_win, 4, dtype=torch.int64)
    wvalid = torch.zeros(len(pairs), n_win, dtype=torch.bool)
    p3 = torch.zeros(len(pairs), n_win, 3, dtype=_F64)
    for b, c in enumerate(curs):
        wdesc[b, :c.num_points] = c.window_brief
        wvalid[b, :c.num_points] = True
        p3[b, :c.num_points] = c.point_3d
    midx, _, matched = match_brief(wdesc, odesc, wvalid, ovalid)
    pn = onorm.gather(1, midx.clamp_min(0)[..., None].expand(-1, -1, 2))
    # vocabulary: trained on the keyframes' descriptors (small: k = 4, L = 3)
    kd = torch.zeros(K, max(k.num_keypoints for k in kfs), 4, dtype=torch.int64)
    kv = torch.zeros(kd.shape[:2], dtype=torch.bool)
    for b, k in enumerate(kfs):
        kd[b, :k.num_keypoints] = k.brief
        kv[b, :k.num_keypoints] = True
    voc = Vocabulary.train(kd, kv, k=4, L=3, generator=torch.Generator().manual_seed(0))
    bows = voc.transform(kd, kv)
    # triangulation: the first keyframe's window points seen in the next 3 keyframes
    F_ = 4
    kf_fr = seq.keyframe_frames[:F_]
    R_wc = seq.R_gt[kf_fr] @ seq.R_ic
    t_wc = seq.T_gt[kf_fr] + (seq.R_gt[kf_fr] @ seq.t_ic[:, None])[..., 0]
    Xw = seq.points_3d(int(kf_fr[0]), kfs[0].point_2d_uv.double())  # exact world points
    Xc = torch.einsum("fji,fpj->pfi", R_wc, Xw[None] - t_wc[:, None])  # (P, F, 3) camera frame
    obs = Xc[..., :2] / Xc[..., 2:3]
    mask = Xc[..., 2] > 0.1
    # pose graph: the vio poses of all keyframes, sequential edges + one loop edge
    T = seq.T_vio[seq.keyframe_frames].clone()
    R = seq.R_vio[seq.keyframe_frames].clone()
    sq = torch.ones(K, dtype=torch.int64)
    si, sj = sequential_edges(sq, 4)
    t_meas_s, yaw_meas_s = measurements_4dof(T, R, si, sj)
    q = R_to_quat(R)
    t_meas6, q_meas6 = measurements_6dof(T, q, si, sj)
    # one loop edge: keyframe half -> 0 with the true relative pose
    li, lj = torch.tensor([0]), torch.tensor([half])
    Rg, Tg = seq.R_gt[seq.keyframe_frames], seq.T_gt[seq.keyframe_frames]
    lt = (Rg[0].T @ (Tg[half] - Tg[0]))[None]
    ypr_g = R_to_ypr(Rg)
    lyaw = (ypr_g[half, 0] - ypr_g[0, 0])[None]
    lq = R_to_quat(Rg[0].T @ Rg[half])[None]
    ypr = R_to_ypr(R)
    fixed = torch.zeros(K, dtype=torch.bool)
    fixed[0] = True
    return dict(
        seq=seq, kfs=kfs, imgs=imgs, pattern=pattern, pts=pts, valid=valid, desc=desc, uv=uv, uv_valid=uv_valid,
        camera=seq.camera, pairs=pairs, wdesc=wdesc, wvalid=wvalid, odesc=odesc, ovalid=ovalid, p3=p3, pn=pn,
        matched=matched, voc=voc, kd=kd, kv=kv, bows=bows, R_wc=R_wc, t_wc=t_wc, obs=obs, mask=mask,
        T=T, R=R, q=q, ypr=ypr, i=torch.cat([si, li]), j=torch.cat([sj, lj]),
        t_meas=torch.cat([t_meas_s, lt]), yaw_meas=torch.cat([yaw_meas_s, lyaw]),
        t_meas6=torch.cat([t_meas6, lt]), q_meas6=torch.cat([q_meas6, lq]),
        is_loop=torch.cat([torch.zeros(si.shape[0], dtype=torch.bool), torch.ones(1, dtype=torch.bool)]),
        fixed=fixed, seq_ids=sq, R_ic=seq.R_ic, t_ic=seq.t_ic,
        R0=torch.eye(3, dtype=_F64).expand(len(pairs), 3, 3).clone(), t0=torch.zeros(len(pairs), 3, dtype=_F64),
    )


# --------------------------------------------------------------------------------------- kernels

def keyframe_to(kf, convert):
    """A copy of a ``KeyFrame`` with every tensor field cloned and passed through ``convert``."""
    import dataclasses

    return dataclasses.replace(kf, **{f.name: convert(getattr(kf, f.name).clone()) for f in dataclasses.fields(kf)
                                      if isinstance(getattr(kf, f.name), torch.Tensor)})


def _gen() -> torch.Generator:
    """A fresh seeded CPU generator per call: RANSAC and k-medians draw on it and upload the draws
    (a CPU-only torch has no CUDA generator; on a GPU a CUDA one would avoid the upload)."""
    return torch.Generator().manual_seed(0)


def kernel_calls(inp: Dict[str, Any], to_dev: Callable, device) -> List[Tuple[str, Callable[[], Any]]]:
    """``(name, call)`` of every loop kernel; ``to_dev`` moves an input tensor to the device under
    test (``simcuda.to_sim``, or ``torch.clone`` on the CPU) before the call is measured. Each call
    returns its outputs (see :func:`flatten`)."""
    import copy

    from torch_frontend.loop import database as db_mod
    from torch_frontend.loop import features, keyframe, optimize, pnp, pose_graph, triangulate, vocabulary

    def conv(v):
        if isinstance(v, torch.Tensor):
            return to_dev(v)
        if isinstance(v, tuple) and hasattr(v, "_fields") and all(isinstance(x, torch.Tensor) for x in v):
            return type(v)(*(to_dev(x) for x in v))  # a BowVector
        return v

    d = {k: conv(v) for k, v in inp.items() if k not in ("seq", "kfs", "voc", "camera")}
    cam = copy.deepcopy(inp["camera"]).to(device=device)  # (Module.to moves in place: a copy first)
    voc = copy.copy(inp["voc"]).to(device)  # (Vocabulary.to moves in place: a shallow copy first)
    bows = d["bows"]
    calls: List[Tuple[str, Callable[[], Any]]] = []

    def add(name, fn):
        calls.append((name, fn))

    add("fast", lambda: features.fast(d["imgs"][:4]))
    add("fast max_points", lambda: features.fast(d["imgs"][:4], max_points=200, return_count=True))
    add("gaussian_blur_u8", lambda: features.gaussian_blur_u8(d["imgs"][:4]))
    add("brief", lambda: features.brief(d["imgs"][:4], d["pts"], d["valid"], d["pattern"]))
    add("brief default pattern", lambda: features.brief(d["imgs"][:4], d["pts"], d["valid"]))
    add("hamming", lambda: features.hamming(d["desc"][:, :60], d["desc"]))
    add("describe_keyframes", lambda: keyframe.describe_keyframes(d["imgs"][:4], cam, d["uv"][:4], d["uv_valid"][:4]))
    add("match_brief", lambda: keyframe.match_brief(d["wdesc"], d["odesc"], d["wvalid"], d["ovalid"]))
    k0 = keyframe_to(inp["kfs"][0], to_dev)
    add("KeyFrame.create", lambda: keyframe.KeyFrame.create(
        k0.time, d["imgs"][0, 0], k0.origin_vio_T, k0.origin_vio_R, k0.point_3d, k0.point_2d_uv, k0.point_id, cam))
    add("Vocabulary.train", lambda: _voc_tensors(vocabulary.Vocabulary.train(d["kd"], d["kv"], k=4, L=3,
                                                                             generator=_gen())))
    add("Vocabulary.transform", lambda: voc.transform(d["kd"], d["kv"]))
    add("bow_to_dense", lambda: vocabulary.bow_to_dense(bows, voc.num_words))

    def database():
        db = db_mod.PlaceDatabase(voc, num_streams=2, device=device)
        ids = db.add_many(type(bows)(bows.words[:8], bows.weights[:8]), streams=[0, 0, 0, 0, 1, 1, 1, 1])
        q = db.query_many(type(bows)(bows.words[8:10], bows.weights[8:10]), 4, -1, [0, 1])
        det = db.detect_loop_many(type(bows)(bows.words[10:12], bows.weights[10:12]), [4, 4], [0, 1], min_gap=2,
                                  return_scores=True)
        return ids, q, det
    add("PlaceDatabase add/query/detect", database)
    add("p3p", lambda: pnp.p3p(d["p3"][:, :3], torch.cat([d["pn"][:, :3], torch.ones_like(d["pn"][:, :3, :1])], -1)))
    add("pnp_ransac", lambda: pnp.pnp_ransac(d["p3"], d["pn"], d["matched"], generator=_gen()))
    add("pnp_ransac with guess", lambda: pnp.pnp_ransac(d["p3"], d["pn"], d["matched"], d["R0"], d["t0"],
                                                         generator=_gen()))
    add("refine_pnp", lambda: pnp.refine_pnp(d["p3"], d["pn"], d["matched"], d["R0"], d["t0"], 3))
    add("camera_poses", lambda: triangulate.camera_poses(d["R"], d["T"], d["R_ic"], d["t_ic"]))
    add("triangulate_points", lambda: triangulate.triangulate_points(d["R_wc"], d["t_wc"], d["obs"], d["mask"]))
    add("sequential_edges", lambda: optimize.sequential_edges(d["seq_ids"], 4))
    add("measurements_4dof", lambda: optimize.measurements_4dof(d["T"], d["R"], d["i"], d["j"]))
    add("measurements_6dof", lambda: optimize.measurements_6dof(d["T"], d["q"], d["i"], d["j"]))

    def opt4(solver="auto"):
        return lambda: optimize.optimize_4dof(d["T"], d["ypr"][:, 0], d["ypr"][:, 1], d["ypr"][:, 2], d["i"], d["j"],
                                              d["t_meas"], d["yaw_meas"], d["is_loop"], d["fixed"], solver=solver)
    add("optimize_4dof", opt4())
    for solver in ("banded", "lapack_banded", "splu"):
        add(f"optimize_4dof solver={solver}", opt4(solver))
    add("optimize_6dof", lambda: optimize.optimize_6dof(d["T"], d["q"], d["i"], d["j"], d["t_meas6"], d["q_meas6"],
                                                        d["is_loop"], d["fixed"]))
    curs = [keyframe_to(inp["kfs"][c], to_dev) for c, _ in inp["pairs"]]
    olds = [keyframe_to(inp["kfs"][o], to_dev) for _, o in inp["pairs"]]
    add("verify_loops", lambda: pose_graph.verify_loops(curs, olds, d["R_ic"], d["t_ic"], generator=_gen()))

    def graph(mode):
        def go():
            kfs = [keyframe_to(k, to_dev) for k in inp["kfs"]]
            for k in kfs[len(kfs) // 2:]:  # the second lap as a second sequence: its first loop merges it
                k.sequence = 2
            g = pose_graph.PoseGraph(cam, voc, mode=mode, R_ic=d["R_ic"], t_ic=d["t_ic"], generator=_gen(),
                                     min_loop_gap=7)
            for k in kfs:
                g.add_keyframe(k)
            # the graph took its device from R_ic, and holds its keyframes there
            assert g.device.type == device.type and all(k.device == g.device for k in g.keyframes), g.device
            return g.poses(), g.correct(d["T"][-1], d["R"][-1]), g.loops, g.csv_text()
        return go
    # (the keyframes are copied onto the device inside the call: the row includes those copies.)
    # 16 keyframes: 8 loop candidates verified, 1 accepted (it merges the two sequences), 1 optimisation
    add("PoseGraph 4dof (16 keyframes)", graph("4dof"))
    add("PoseGraph 6dof (16 keyframes)", graph("6dof"))
    return calls


def _voc_tensors(voc):
    return [voc.parent, voc.node_desc, voc.node_weight, voc.node_word, voc.children]


def flatten(obj) -> List[Any]:
    """The tensors (as CPU tensors), arrays and plain values of a kernel's output, in order."""
    import dataclasses

    import numpy as np

    if isinstance(obj, torch.Tensor):
        return [obj.detach().cpu()]
    if isinstance(obj, np.ndarray) or obj is None or isinstance(obj, (bool, int, float, str)):
        return [obj]
    if isinstance(obj, dict):
        return [x for k in sorted(obj) for x in flatten(obj[k])]
    if isinstance(obj, (list, tuple)):
        return [x for v in obj for x in flatten(v)]
    if dataclasses.is_dataclass(obj):
        return [x for f in dataclasses.fields(obj) for x in flatten(getattr(obj, f.name))]
    raise TypeError(f"flatten: unexpected output type {type(obj).__name__}")


def same(a: List[Any], b: List[Any]) -> bool:
    """Bit-for-bit equality of two :func:`flatten` results (NaN equals NaN)."""
    import numpy as np

    if len(a) != len(b):
        return False
    for x, y in zip(a, b):
        if isinstance(x, torch.Tensor) or isinstance(y, torch.Tensor):
            if not (isinstance(x, torch.Tensor) and isinstance(y, torch.Tensor)) or x.shape != y.shape \
                    or x.dtype != y.dtype:
                return False
            if x.is_floating_point():
                if not (torch.equal(x.isnan(), y.isnan()) and torch.equal(x.nan_to_num(0.0), y.nan_to_num(0.0))):
                    return False
            elif not torch.equal(x, y):
                return False
        elif isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            if not np.array_equal(np.asarray(x), np.asarray(y), equal_nan=np.asarray(x).dtype.kind == "f"):
                return False
        elif x != y and not (isinstance(x, float) and x != x and y != y):
            return False
    return True


# ------------------------------------------------------------------------------------- measuring

def measure(simcuda, fn: Callable[[], Any]) -> Tuple[Dict[str, Any], Any]:
    """Counts of one call of ``fn`` inside ``SimCudaMode`` (simcuda's LOG), and its output (None
    if it raised)."""
    LOG = simcuda.LOG
    LOG.reset()
    err, out = None, None
    with simcuda.SimCudaMode():
        LOG.enabled = True
        try:
            out = fn()
        except Exception as e:  # noqa: BLE001 - reported in the table
            err = f"{type(e).__name__}: {str(e).splitlines()[0][:160] if str(e) else ''}"
        finally:
            LOG.enabled = False
    cats: collections.Counter = collections.Counter()
    for (_st, _g, cat), n in LOG.ops.items():
        cats[cat] += n
    sync_sites: collections.Counter = collections.Counter()
    for (_st, _g, kind, site), n in LOG.syncs.items():
        sync_sites[f"{site} [{kind}]"] += n
    mism: collections.Counter = collections.Counter()
    for (op, site, detail), n in LOG.mismatch.items():
        mism[f"{site} {op} {detail}"] += n
    errors = [f"{what} at {site}" for what, site in LOG.errors]
    if err is not None:
        errors.append(err)
    row = {"kernels": cats["kernel"], "views": cats["view"], "host_ops": cats["host"], "h2d": cats["h2d"],
           "d2h": cats["d2h"], "syncs": sum(sync_sites.values()), "mismatches": sum(mism.values()),
           "mismatch_sites": dict(mism), "sync_sites": dict(sync_sites.most_common()), "errors": errors}
    return row, out


def run(sim_dir: Optional[Path] = None, only: Optional[Sequence[str]] = None, compare: bool = True,
        inputs: Optional[Dict[str, Any]] = None) -> List[Dict[str, Any]]:
    """One measured call of every loop kernel (or of those named in ``only``) on the simulated
    device: a row per kernel. With ``compare``, ``same_as_cpu`` says whether the outputs equal
    those of the same call on the CPU bit for bit (the CUDA code path may differ, e.g. the
    pose-graph solver)."""
    simcuda = load_simcuda(sim_dir)
    inp = make_inputs() if inputs is None else inputs
    with simcuda.SimCudaMode():
        calls = kernel_calls(inp, simcuda.to_sim, torch.device("cuda"))
    names = [n for n, _ in calls]
    if only:
        unknown = sorted(set(only) - set(names))
        if unknown:
            raise ValueError(f"unknown kernel(s) {unknown}; known: {names}")
    cpu = dict(kernel_calls(inp, torch.clone, torch.device("cpu"))) if compare else {}
    rows = []
    for name, fn in calls:
        if only and name not in only:
            continue
        t0 = time.perf_counter()
        row, out = measure(simcuda, fn)
        row["sim_seconds"] = round(time.perf_counter() - t0, 3)  # host time of the simulated call
        if compare:
            row["same_as_cpu"] = None if row["errors"] else same(flatten(out), flatten(cpu[name]()))
        rows.append({"kernel": name, **row})
    return rows


def run_real(device, only: Optional[Sequence[str]] = None,
             inputs: Optional[Dict[str, Any]] = None) -> List[Dict[str, Any]]:
    """The same calls on a real device (e.g. ``"cuda"`` when a GPU is at hand), no simulator: a
    device mismatch raises there (``errors``). ``kernels``/``syncs`` are ``OpCounter``'s counts
    (``torch_frontend.testing.dispatch_count``); ``same_as_cpu`` as in :func:`run`."""
    from torch_frontend.testing.dispatch_count import OpCounter

    device = torch.device(device)
    inp = make_inputs() if inputs is None else inputs
    calls = kernel_calls(inp, lambda t: t.to(device), device)
    cpu = dict(kernel_calls(inp, torch.clone, torch.device("cpu")))
    rows = []
    for name, fn in calls:
        if only and name not in only:
            continue
        errors, out = [], None
        with OpCounter() as c:
            try:
                out = fn()
            except Exception as e:  # noqa: BLE001 - reported in the table
                errors.append(f"{type(e).__name__}: {str(e).splitlines()[0][:160] if str(e) else ''}")
        rows.append({"kernel": name, "kernels": c.kernels, "syncs": c.syncs, "mismatches": 0, "host_ops": 0,
                     "mismatch_sites": {}, "sync_sites": {f"{site} [{kind}]": n for (kind, site), n in c.sites.items()},
                     "errors": errors, "same_as_cpu": None if errors else same(flatten(out), flatten(cpu[name]()))})
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", help="write every figure (sites included) to this file")
    ap.add_argument("--kernels", help="comma-separated kernel names (default: all)")
    ap.add_argument("--sites", action="store_true", help="print the sync and mismatch sites of each kernel")
    ap.add_argument("--no-compare", action="store_true", help="skip the comparison with the CPU outputs")
    ap.add_argument("--sim-dir", default=str(DEFAULT_SIM_DIR))
    ap.add_argument("--device", default="sim",
                    help="'sim' (default): the simulated CUDA device; else a real device such as 'cuda', "
                         "where a device mismatch raises (listed under errors; counts from OpCounter)")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    only = args.kernels.split(",") if args.kernels else None
    try:
        if args.device == "sim":
            rows = run(Path(args.sim_dir), only, not args.no_compare)
        else:
            rows = run_real(args.device, only)
    except FileNotFoundError as e:
        print(e, file=sys.stderr)
        return 2
    except RuntimeError as e:  # cudaguard.BuildError: no compiler, or a CUDA build of torch
        if type(e).__name__ != "BuildError":
            raise
        print(e, file=sys.stderr)
        return 2
    except ValueError as e:
        print(f"--kernels: {e}", file=sys.stderr)
        return 2
    where = "the simulated CUDA device" if args.device == "sim" else f"device {args.device} (no simulator)"
    print(f"\nLoop-closure kernels on {where}, one call each (inputs: the synthetic room, "
          "2 laps x 8 keyframes, 160x120)\n")
    print("| kernel | kernels | syncs | device mismatches | host ops | = CPU | errors |")
    print("|---|---:|---:|---:|---:|:---:|---|")
    for r in rows:
        eq = {True: "yes", False: "no", None: "-"}[r.get("same_as_cpu")]
        print(f"| {r['kernel']} | {r['kernels']} | {r['syncs']} | {r['mismatches']} | {r['host_ops']} | {eq} | "
              f"{'; '.join(r['errors'])} |")
    tot = sum(r["mismatches"] for r in rows)
    print(f"\ntotal device mismatches: {tot}; calls that raised: {sum(bool(r['errors']) for r in rows)}")
    if args.sites:
        for r in rows:
            if r["mismatch_sites"] or r["sync_sites"]:
                print(f"\n{r['kernel']}:")
                for s, n in r["mismatch_sites"].items():
                    print(f"  MISMATCH {n} x {s}")
                for s, n in r["sync_sites"].items():
                    print(f"  sync {n} x {s}")
    if args.json:
        meta = {"torch": torch.__version__, "inputs": "synthetic room, 2 laps x 8 keyframes, 160x120, 60 points",
                "device": args.device, "simulator": str(Path(args.sim_dir).resolve()) if args.device == "sim" else None}
        Path(args.json).write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
