"""Device hygiene: the loop-closure kernels run on a CUDA device without mixing in
CPU tensors, checked without a GPU in two ways.

* On the simulated CUDA device of ``../shared/tools/cuda_sim`` (tensors labelled ``cuda:0``, data on
  the CPU, every op logged): ``benchmarks/sim_cuda_loop.py`` calls every loop kernel once on the
  synthetic room's keyframes, in a subprocess (the simulator changes process-wide torch settings),
  and each kernel must show 0 device mismatches (a non-0-dim CPU tensor in an op with cuda tensors:
  a real CUDA run raises there) and raise nothing.
* Under ``FakeTensorMode(allow_non_fake_inputs=False)`` with tensors made with ``device="cuda"``
  inside the mode: shapes, dtypes and the device propagate through the kernels that have no
  data-dependent shapes or host reads (a CPU constant built without ``device=`` meets the cuda
  tensors there and FakeTensor's device propagation raises). Smoke tests of
  ``pyramid.build_pyramid`` and the camera models' ``lift``/``project`` too (to be extended).
  A CPU-only torch needs the simulator's no-op CUDA device guard for that (``cudaguard``, built
  once with the system C++ compiler); a CUDA build of torch needs nothing.

Both skip, naming the path, when ``../shared/tools/cuda_sim`` is absent.
"""

from __future__ import annotations

import importlib.util
import json
import multiprocessing
import os
import subprocess
import sys
import traceback
from typing import Callable, Dict, List, Tuple

import pytest
import torch

from .conftest import REPO, SHARED

SIM_DIR = SHARED / "tools" / "cuda_sim"
SCRIPT = REPO / "benchmarks" / "sim_cuda_loop.py"
_CUDA_BUILD = bool(torch.version.cuda or getattr(torch.version, "hip", None))

# every kernel call of benchmarks/sim_cuda_loop.py (a kernel that drops out of the script fails here)
SIM_KERNELS = (
    "fast", "fast max_points", "gaussian_blur_u8", "brief", "brief default pattern", "hamming",
    "describe_keyframes", "match_brief", "KeyFrame.create", "Vocabulary.train", "Vocabulary.transform",
    "bow_to_dense", "PlaceDatabase add/query/detect", "p3p", "pnp_ransac", "pnp_ransac with guess", "refine_pnp",
    "camera_poses", "triangulate_points", "sequential_edges", "measurements_4dof", "measurements_6dof",
    "optimize_4dof", "optimize_4dof solver=banded", "optimize_4dof solver=lapack_banded",
    "optimize_4dof solver=splu", "optimize_6dof", "verify_loops", "PoseGraph 4dof (16 keyframes)",
    "PoseGraph 6dof (16 keyframes)",
)


FAKE_CHILD_TIMEOUT = 300  # s: every fake-cuda case in the forked child (~5 s)


def _sim_dir_or_skip():
    if not (SIM_DIR / "simcuda.py").is_file():
        pytest.skip(f"../shared/tools/cuda_sim not found beside the repo (looked for {SIM_DIR / 'simcuda.py'}); "
                    "the simulated CUDA device comes from there")


# ------------------------------------------------------------------------ simulated CUDA device
@pytest.fixture(scope="module")
def sim_rows(tmp_path_factory):
    _sim_dir_or_skip()
    if _CUDA_BUILD:
        pytest.skip("torch is a CUDA build: the simulator needs a CPU-only torch (the CUDA tests run instead)")
    out = tmp_path_factory.mktemp("sim") / "sim_cuda_loop.json"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    r = subprocess.run([sys.executable, str(SCRIPT), "--json", str(out), "--no-compare", "--sim-dir", str(SIM_DIR)],
                       capture_output=True, text=True, timeout=600, cwd=str(REPO), env=env)
    if r.returncode == 2:  # the tool is there but unusable here (e.g. no C++ compiler for its guard)
        pytest.skip(f"simulated CUDA device unavailable: {r.stderr.strip()[-500:]}")
    assert r.returncode == 0, f"{SCRIPT.name} failed:\n{r.stdout[-2000:]}\n{r.stderr[-4000:]}"
    return {row["kernel"]: row for row in json.loads(out.read_text())["rows"]}


def test_sim_runs_every_loop_kernel(sim_rows):
    assert tuple(sim_rows) == SIM_KERNELS
    for name, row in sim_rows.items():
        assert row["kernels"] > 0, f"{name}: no op ran on the (simulated) device"


@pytest.mark.parametrize("name", SIM_KERNELS)
def test_sim_no_device_mismatch(sim_rows, name):
    row = sim_rows[name]
    assert row["errors"] == [], f"{name} raised on the simulated CUDA device: {row['errors']}"
    assert row["mismatches"] == 0, (f"{name}: {row['mismatches']} device mismatches (CPU tensors mixed with cuda "
                                    f"ones; a real CUDA run raises there):\n" +
                                    "\n".join(f"  {n} x {s}" for s, n in row["mismatch_sites"].items()))


# ------------------------------------------------------------------ FakeTensorMode, fake cuda
def _fake_mode_here():
    """A ``FakeTensorMode`` factory in this process; on a CPU-only torch the simulator's no-op CUDA
    device guard is installed first (torch's Python bindings open a CUDA guard for a cuda tensor,
    fake or not). Raises ``pytest.skip.Exception`` when the guard cannot be built."""
    if not _CUDA_BUILD:
        spec = importlib.util.spec_from_file_location("cudaguard", SIM_DIR / "cudaguard.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        try:
            mod.install()
        except mod.BuildError as e:
            pytest.skip(f"no CUDA device guard for fake cuda tensors: {str(e)[:300]}")
    from torch._subclasses.fake_tensor import FakeTensorMode

    return lambda: FakeTensorMode(allow_non_fake_inputs=False)


def _in_a_forked_child(cases: Dict[str, Callable[[Callable], None]]) -> Dict[str, Tuple[str, str]]:
    """Every ``case(fake_mode_factory)`` in one forked child process: ``name -> (kind, text)``, kind
    ``"ok"``, ``"skip"`` or ``"fail"`` (with the traceback). The guard is process-wide and cannot be
    removed: registered in the test process, it would make autograd start device threads at the
    next backward, after which a forked process (the distributed tests' ranks) cannot run autograd."""
    ctx = multiprocessing.get_context("fork")
    recv, send = ctx.Pipe(duplex=False)

    def child():
        out = {}
        try:
            mode = _fake_mode_here()
        except pytest.skip.Exception as e:
            send.send({n: ("skip", str(e)) for n in cases})
            return
        for name, case in cases.items():
            try:
                case(mode)
                out[name] = ("ok", "")
            except BaseException:  # reported to the parent, which fails that test with it
                out[name] = ("fail", traceback.format_exc())
        send.send(out)

    proc = ctx.Process(target=child)
    proc.start()
    got = recv.recv() if recv.poll(FAKE_CHILD_TIMEOUT) else {}
    proc.join(FAKE_CHILD_TIMEOUT)
    return {n: got.get(n, ("fail", "the forked child sent nothing for this case")) for n in cases}


@pytest.fixture(scope="module")
def fake_cuda():
    """Every fake-cuda case's outcome (``name -> (kind, text)``), run once in a forked child."""
    if not _CUDA_BUILD:
        _sim_dir_or_skip()
    cases = {f"shapes: {n}": (lambda mode, case=c: _check_fake(mode, case)) for n, c in FAKE_CASES.items()}
    cases.update({"vocabulary transform": _vocabulary_transform, "cpu constant": _cpu_constant_raises})
    return _in_a_forked_child(cases)


def _outcome(fake_cuda, name: str) -> None:
    kind, text = fake_cuda[name]
    if kind == "skip":
        pytest.skip(text)
    assert kind == "ok", f"{name}, in the forked child:\n{text}"


def _tensors(obj) -> List[torch.Tensor]:
    if isinstance(obj, torch.Tensor):
        return [obj]
    if isinstance(obj, dict):
        return [t for k in sorted(obj) for t in _tensors(obj[k])]
    if isinstance(obj, (list, tuple)):
        return [t for v in obj for t in _tensors(v)]
    raise TypeError(f"unexpected output {type(obj).__name__}")


def _image(B, H, W, dev):
    """A deterministic textured uint8 image batch ``(B, 1, H, W)`` (values matter only on the CPU)."""
    i = torch.arange(B * H * W, device=dev).reshape(B, 1, H, W)
    return ((i * 37 + (i // W) * 11) % 251).to(torch.uint8)


def _points(B, N, W, H, dev):
    s = torch.linspace(0.1, 0.9, N, dtype=torch.float32, device=dev)
    return torch.stack([s * (W - 1), s.flip(0) * (H - 1)], -1).expand(B, N, 2).contiguous()


def _desc(B, K, dev, salt=0):
    i = torch.arange(B * K * 4, dtype=torch.int64, device=dev).reshape(B, K, 4)
    return (i + salt) * 0x9E3779B97F4A7C15


def _case_brief(dev, pattern: bool):
    from torch_frontend.loop.features import brief, make_brief_pattern

    pat = torch.as_tensor(make_brief_pattern(), device=dev) if pattern else None
    return brief(_image(2, 48, 64, dev), _points(2, 10, 64, 48, dev), None, pat)


def _case_describe_window(dev):
    # describe_keyframes without FAST (data-dependent): BRIEF of window points + their lift
    from torch_frontend.camera import PinholeCamera
    from torch_frontend.loop.features import brief
    from torch_frontend.loop.keyframe import _lift_norm

    cam = PinholeCamera(0.0, 0.0, 0.0, 0.0, 50.0, 50.0, 31.5, 23.5, width=64, height=48, device=dev)
    pts = _points(2, 10, 64, 48, dev)
    valid = torch.ones(2, 10, dtype=torch.bool, device=dev)
    return brief(_image(2, 48, 64, dev), pts, valid), _lift_norm(cam, pts, valid)


def _case_match(dev):
    from torch_frontend.loop.keyframe import match_brief

    return match_brief(_desc(3, 12, dev), _desc(3, 20, dev, salt=5), None,
                       torch.arange(20, device=dev).expand(3, 20) < 17)


def _case_hamming(dev):
    from torch_frontend.loop.features import hamming

    return hamming(_desc(2, 7, dev), _desc(2, 9, dev, salt=3))


def _case_blur(dev):
    from torch_frontend.loop.features import gaussian_blur_u8

    return gaussian_blur_u8(_image(2, 48, 64, dev))


def _scene(dev, F=4, P=6):
    from torch_frontend.geometry import ypr_to_R

    a = torch.linspace(-10.0, 10.0, F, dtype=torch.float64, device=dev)
    R_wc = ypr_to_R(torch.stack([a, 0.3 * a, -0.2 * a], -1))
    t_wc = torch.stack([a / 10, torch.zeros_like(a), torch.zeros_like(a)], -1)
    s = torch.linspace(-0.3, 0.3, P, dtype=torch.float64, device=dev)
    obs = torch.stack([s[:, None].expand(P, F), s.flip(0)[:, None].expand(P, F)], -1).contiguous()
    mask = torch.ones(P, F, dtype=torch.bool, device=dev)
    return R_wc, t_wc, obs, mask


def _case_triangulate(dev):
    from torch_frontend.loop.triangulate import triangulate_points

    R_wc, t_wc, obs, mask = _scene(dev)
    return triangulate_points(R_wc[None], t_wc[None], obs[None], mask[None])


def _case_camera_poses(dev):
    from torch_frontend.loop.triangulate import camera_poses

    R_wc, t_wc, _, _ = _scene(dev)
    return camera_poses(R_wc, t_wc, R_wc[0], t_wc[1])


def _case_refine(dev):
    from torch_frontend.loop.pnp import refine_pnp

    B, N = 2, 12
    s = torch.linspace(-1.0, 1.0, N, dtype=torch.float64, device=dev)
    X = torch.stack([s, s.flip(0), 4.0 + s * s], -1).expand(B, N, 3).contiguous()
    p = X[..., :2] / X[..., 2:]
    w = torch.ones(B, N, dtype=torch.float64, device=dev)
    R = torch.eye(3, dtype=torch.float64, device=dev).expand(B, 3, 3)
    return refine_pnp(X, p + 0.01, w, R, torch.zeros(B, 3, dtype=torch.float64, device=dev), 2)


def _case_bow_to_dense(dev):
    from torch_frontend.loop.vocabulary import BowVector, bow_to_dense

    words = torch.tensor([[0, 3, 5, -1], [1, 2, -1, -1]], device=dev)
    return bow_to_dense(BowVector(words, (words >= 0).to(torch.float64) * 0.25), 8)


def _case_pyramid(dev):
    from torch_frontend.pyramid import build_pyramid

    p = build_pyramid(_image(2, 48, 64, dev), 2)
    return list(p.levels) + list(p.grads)


def _cameras(dev):
    from torch_frontend.camera import KannalaBrandtCamera, MeiCamera, PinholeCamera

    return [
        PinholeCamera(-0.28, 0.07, 2e-4, 2e-5, 458.7, 457.3, 367.2, 248.4, width=752, height=480, device=dev),
        MeiCamera(1.2, -0.1, 0.02, 1e-4, -2e-4, 800.0, 790.0, 376.0, 240.0, width=752, height=480, device=dev),
        KannalaBrandtCamera(-0.01, 0.002, -1e-3, 1e-4, 380.0, 380.0, 376.0, 240.0, width=752, height=480,
                            device=dev),
    ]


def _case_cameras(dev):
    uv = _points(2, 5, 752, 480, dev).to(torch.float64)
    out = []
    for cam in _cameras(dev):
        P = cam.lift(uv)
        out += [P, cam.project(P)]
    return out


FAKE_CASES = {
    "loop.gaussian_blur_u8": _case_blur,
    "loop.brief": lambda dev: _case_brief(dev, True),
    "loop.brief default pattern": lambda dev: _case_brief(dev, False),
    "loop.hamming": _case_hamming,
    "loop.match_brief": _case_match,
    "loop.keyframe window BRIEF + lift": _case_describe_window,
    "loop.refine_pnp": _case_refine,
    "loop.camera_poses": _case_camera_poses,
    "loop.triangulate_points": _case_triangulate,
    "loop.bow_to_dense": _case_bow_to_dense,
    "pyramid.build_pyramid": _case_pyramid,
    "camera lift/project": _case_cameras,
}


def _check_fake(fake_mode, case: Callable):
    from torch._subclasses.fake_tensor import FakeTensor

    ref = _tensors(case(torch.device("cpu")))
    with fake_mode():
        out = _tensors(case(torch.device("cuda")))
    assert len(out) == len(ref) > 0
    for k, (o, r) in enumerate(zip(out, ref)):
        assert isinstance(o, FakeTensor), f"output {k} is not a fake tensor"
        assert o.device.type == "cuda", f"output {k} on {o.device}"
        assert (tuple(o.shape), o.dtype) == (tuple(r.shape), r.dtype), f"output {k}"


@pytest.mark.parametrize("name", sorted(FAKE_CASES))
def test_fake_cuda_shapes_and_devices(fake_cuda, name):
    _outcome(fake_cuda, f"shapes: {name}")


def test_fake_cuda_vocabulary_transform(fake_cuda):
    _outcome(fake_cuda, "vocabulary transform")


def _vocabulary_transform(fake_mode):
    """``Vocabulary.transform`` with the tree's tensors as fake cuda tensors."""
    from torch._subclasses.fake_tensor import FakeTensor

    from torch_frontend.loop.vocabulary import Vocabulary

    D, K = 6, 30
    desc = _desc(D, K, "cpu")
    voc = Vocabulary.train(desc, k=3, L=2, generator=torch.Generator().manual_seed(0))
    ref = voc.transform(desc)
    names = ("parent", "node_desc", "node_weight", "node_word", "word_node", "children", "is_leaf")
    with fake_mode() as mode:
        for n in names:  # what Vocabulary.to("cuda") does, on fakes of the CPU tree
            setattr(voc, n, mode.from_tensor(getattr(voc, n)).to("cuda"))
        voc.device = torch.device("cuda")
        out = voc.transform(_desc(D, K, "cuda"))
    for o, r in zip(out, ref):
        assert isinstance(o, FakeTensor) and o.device.type == "cuda"
        assert (o.shape, o.dtype) == (r.shape, r.dtype)


def test_fake_cuda_catches_a_cpu_constant(fake_cuda):
    _outcome(fake_cuda, "cpu constant")


def _cpu_constant_raises(fake_mode):
    """The check above can fail: a CPU constant (no ``device=``) mixed with cuda tensors raises."""
    with fake_mode(), pytest.raises(Exception, match="(?i)device"):
        x = torch.zeros(2, 3, device="cuda")
        x + torch.ones(3)


# ------------------------------------------------------------- devices of keyframes and graphs
def _tiny_keyframe():
    from torch_frontend.loop.keyframe import KeyFrame

    return KeyFrame.loaded(0, 1.0, torch.zeros(3), torch.eye(3), torch.zeros(2, 2), torch.zeros(2, 2),
                           torch.zeros(2, 4, dtype=torch.int64))


def test_keyframe_to_moves_every_tensor_field():
    import dataclasses

    kf = _tiny_keyframe()
    assert kf.device.type == "cpu"
    assert kf.to("meta") is kf and kf.device.type == "meta"
    for f in dataclasses.fields(kf):
        v = getattr(kf, f.name)
        if isinstance(v, torch.Tensor):
            assert v.device.type == "meta", f.name
    kf.update_pose(torch.zeros(3), torch.eye(3))  # new poses follow the keyframe's device
    assert kf.T_w_i.device.type == "meta" and kf.R_w_i.device.type == "meta"


def test_pose_graph_device():
    from torch_frontend.loop.pose_graph import PoseGraph

    assert PoseGraph().device == torch.device("cpu")
    g = PoseGraph(R_ic=torch.eye(3, dtype=torch.float64, device="meta"))  # default: R_ic's device
    assert g.device.type == "meta" and g.R_ic.device.type == "meta" and g.t_ic.device.type == "meta"
    g = PoseGraph(R_ic=torch.eye(3), device="meta")
    assert g.R_ic.device.type == "meta" and g.w_r_vio.device.type == "meta"
    c_T, c_R = g.correct(torch.zeros(3), torch.eye(3))  # host input, answer on the graph's device
    assert c_T.device.type == "meta" and c_R.device.type == "meta"
    kf = _tiny_keyframe()
    g.add_keyframe(kf, detect_loop=False)  # a keyframe on another device is moved onto the graph's
    assert g.keyframes[0] is kf and kf.device.type == "meta" and kf.T_w_i.device.type == "meta"
