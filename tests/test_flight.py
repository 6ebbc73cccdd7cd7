"""``testing.flight``'s batched flights (``fly_over``) and degradations: the ground truth is right
(photometric consistency at the mapped points; LK on the clean flight tracks to sub-pixel error
against the homographies, on two real photos), the degradations do what they say, and everything
is deterministic given a ``torch.Generator``."""

from __future__ import annotations

import cv2
import pytest
import torch
import torch.nn.functional as F

from torch_frontend import good_features_to_track, track_lk
from torch_frontend.errors import ConfigError
from torch_frontend.learn import homography_targets
from torch_frontend.testing.flight import DEGRADATIONS, Degradation, Flight, degrade, fly_over

from .conftest import TEST_DATA, load_gray, sample_frames

SIZE = (96, 112)


@pytest.fixture(scope="module")
def photo():
    return load_gray(sample_frames("cam0")[0])


@pytest.fixture(scope="module")
def moto():
    return cv2.imread(str(TEST_DATA / "motorcycle" / "motorcycle_left.png"), cv2.IMREAD_GRAYSCALE)


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _bilinear(img: torch.Tensor, pts: torch.Tensor) -> torch.Tensor:
    """``img (B, 1, H, W)`` at ``pts (B, N, 2)`` pixels (centres at integers): ``(B, N)``."""
    H, W = img.shape[-2:]
    grid = torch.stack((pts[..., 0] * 2 / (W - 1) - 1, pts[..., 1] * 2 / (H - 1) - 1), -1).unsqueeze(1)
    return F.grid_sample(img, grid.to(img.dtype), align_corners=True)[:, 0, 0]


def test_fly_over_shapes_dtypes_and_pairs(photo, device, dtype):
    fl = fly_over(photo, 4, SIZE, batch=3, generator=_gen(0), dtype=dtype, device=device)
    assert isinstance(fl, Flight) and (fl.batch, fl.n_frames) == (3, 4)
    assert fl.frames.shape == (3, 4, 1) + SIZE and fl.frames.dtype == dtype
    assert fl.frames.device.type == torch.device(device).type
    assert fl.homographies.shape == (3, 4, 3, 3) and fl.homographies.dtype == torch.float64
    assert float(fl.frames.min()) >= 0 and float(fl.frames.max()) <= 255 and float(fl.frames.std()) > 10
    prev, nxt, rel = fl.pairs()
    assert prev.shape == nxt.shape == (9, 1) + SIZE and rel.shape == (9, 3, 3)
    # flight-major: pair 1 * (T - 1) + 2 is flight 1, frames 2 -> 3
    assert torch.equal(prev[5], fl.frames[1, 2]) and torch.equal(nxt[5], fl.frames[1, 3])
    torch.testing.assert_close(rel[5], fl.relative(2)[1])
    a, b, r = fl.pair(1)
    assert torch.equal(a, fl.frames[:, 1]) and torch.equal(b, fl.frames[:, 2])
    # relative homographies compose: 0 -> 2 = (1 -> 2)(0 -> 1)
    torch.testing.assert_close(fl.relative(0, 2), fl.relative(1) @ fl.relative(0), rtol=1e-9, atol=1e-9)
    # H_k (u, v, 1) has the depth as its third coordinate: positive for what the frames show
    corners = torch.tensor([[0.0, 0.0], [SIZE[1] - 1, 0], [0, SIZE[0] - 1], [SIZE[1] - 1, SIZE[0] - 1]],
                           dtype=torch.float64, device=device)
    for k in range(4):
        uv, ok = homography_targets(corners.expand(3, 4, 2), torch.linalg.inv(fl.homographies[:, k]))
        depth = (uv * fl.homographies[:, k, None, 2, :2]).sum(-1) + fl.homographies[:, k, None, 2, 2]
        assert bool(ok.all()) and bool((depth > 0).all())
    q = fly_over(photo, 2, SIZE, generator=_gen(0), quantize=True)
    assert torch.equal(q.frames, torch.round(q.frames))


def test_fly_over_deterministic_given_generator(photo):
    a = fly_over(photo, 3, SIZE, batch=2, generator=_gen(7))
    b = fly_over(torch.from_numpy(photo), 3, SIZE, batch=2, generator=_gen(7))
    assert torch.equal(a.frames, b.frames) and torch.equal(a.homographies, b.homographies)
    c = fly_over(photo, 3, SIZE, batch=2, generator=_gen(8))
    assert not torch.equal(a.homographies, c.homographies)
    # the flights move: a few px per frame, as asked
    flow = homography_targets(torch.tensor([[[55.5, 47.5]]], dtype=torch.float64).expand(2, 1, 2),
                              a.relative(0))[0] - torch.tensor([55.5, 47.5], dtype=torch.float64)
    assert (flow.norm(dim=-1) > 0.5).all() and (flow.norm(dim=-1) < 8).all()


def test_frames_are_the_photo_through_the_homographies(photo):
    """Photometric truth: frame k at ``H_k p`` equals the (smooth) photo at ``p``; half a pixel off
    (a wrong pixel-centre convention) is far worse."""
    tex = cv2.GaussianBlur(photo, (0, 0), 2.0).astype("float64")
    fl = fly_over(tex, 3, SIZE, batch=2, generator=_gen(1), dtype=torch.float64)
    g = _gen(2)
    # integer frame pixels (read without interpolation): the frames' only blur is the pixel's box
    q = torch.stack((torch.randint(2, SIZE[1] - 2, (2, 300), generator=g),
                     torch.randint(2, SIZE[0] - 2, (2, 300), generator=g)), -1).to(torch.float64)
    tex_b = torch.from_numpy(tex)[None, None].expand(2, 1, -1, -1)
    half = torch.tensor([0.5, 0.0], dtype=torch.float64)
    for k in range(3):
        got = fl.frames[:, k, 0][torch.arange(2)[:, None], q[..., 1].long(), q[..., 0].long()]
        Hinv = torch.linalg.inv(fl.homographies[:, k])  # frame k -> photo
        p, ok = homography_targets(q, Hinv)
        assert bool(ok.all()) and bool((p >= 0).all()) and bool((p[..., 0] <= 751).all())
        err = (got - _bilinear(tex_b, p)).abs()
        off = (got - _bilinear(tex_b, homography_targets(q + half, Hinv)[0])).abs()
        assert float(err.mean()) < 0.2, float(err.mean())
        assert float(off.mean()) > 5 * float(err.mean()), (float(off.mean()), float(err.mean()))

@pytest.mark.parametrize("which", ["euroc", "motorcycle"])
@pytest.mark.parametrize("quantize", [False, True], ids=["float", "uint8"])
def test_lk_on_clean_flight_is_sub_pixel(which, quantize, photo, moto):
    tex = photo if which == "euroc" else moto
    fl = fly_over(tex, 4, (128, 128), batch=3, generator=_gen(3), quantize=quantize)
    prev, nxt, rel = fl.pairs()
    if quantize:
        prev, nxt = prev.to(torch.uint8), nxt.to(torch.uint8)
    pts, valid = good_features_to_track(prev, 30, 0.01, 8)
    out, st = track_lk(prev, nxt, pts, valid, 21, 2)
    target, ok = homography_targets(pts.double(), rel)
    err = (out.double() - target).norm(dim=-1)[st & ok]
    assert int((st & ok).sum()) >= 0.9 * int(valid.sum()) > 100
    assert float(err.median()) < 0.08, float(err.median())
    assert float(err.quantile(0.9)) < 0.25, float(err.quantile(0.9))


def test_degradation_deterministic_and_shapes(photo):
    fl = fly_over(photo, 1, SIZE, batch=4, generator=_gen(0), dtype=torch.float64)
    img = fl.frames[:, 0]
    a, da = degrade(img, _gen(5))
    b, db = degrade(img, _gen(5))
    assert torch.equal(a, b) and all(torch.equal(getattr(da, n), getattr(db, n)) for n in
                                     ("blur_sigma", "vignetting", "exposure", "noise_sigma", "gamma"))
    c, _ = degrade(img, _gen(6))
    assert not torch.equal(a, c)
    assert a.shape == img.shape and a.dtype == torch.float64 and da.batch == 4
    assert float(a.min()) >= 0 and float(a.max()) <= 255
    u8, _ = degrade(img.round().to(torch.uint8), _gen(5), quantize=True)
    assert u8.dtype == torch.float32 and torch.equal(u8, torch.round(u8))
    # every kind is on by default: the parameters differ from the identity's
    idn = Degradation.identity(4)
    assert len(DEGRADATIONS) == 5
    for n in ("blur_sigma", "vignetting", "exposure", "noise_sigma", "gamma"):
        assert not torch.equal(getattr(da, n), getattr(idn, n)), n
    # the identity only clips
    x = img * 1.2 - 10
    torch.testing.assert_close(idn.apply(x), x.clamp(0, 255), rtol=0, atol=1e-12)


def _one(batch: int = 1, **kw) -> Degradation:
    d = Degradation.identity(batch)
    return Degradation(**{n: torch.full((batch,), float(kw.get(n, getattr(d, n)[0])), dtype=torch.float64)
                          for n in ("blur_sigma", "vignetting", "exposure", "noise_sigma", "gamma")})


def test_each_degradation_does_what_it_says(photo):
    H, W = 64, 80
    flat = torch.full((1, 1, H, W), 100.0, dtype=torch.float64)
    tex = torch.from_numpy(photo[100:100 + H, 200:200 + W].copy()).double()[None, None]
    # exposure: a gain; gamma: the response curve
    torch.testing.assert_close(_one(exposure=1.5).apply(flat), flat * 1.5)
    torch.testing.assert_close(_one(gamma=2.0).apply(flat), 255 * (flat / 255) ** 2)
    # vignetting: centre (nearly) kept, corners at 1 / (1 + k)^2
    v = _one(vignetting=1.0).apply(flat)
    assert abs(float(v[0, 0, H // 2, W // 2]) - 100) < 0.1 and abs(float(v[0, 0, 0, 0]) - 25) < 1e-9
    # blur: mean kept (away from clipping), fine detail reduced
    b = _one(blur_sigma=1.5).apply(tex)
    assert abs(float(b.mean() - tex.mean())) < 1.0
    assert float((b[..., 1:] - b[..., :-1]).abs().mean()) < 0.7 * float((tex[..., 1:] - tex[..., :-1]).abs().mean())
    # noise: zero-mean, the given sigma
    n = _one(noise_sigma=5.0).apply(flat, _gen(0)) - flat
    assert abs(float(n.mean())) < 0.3 and abs(float(n.std()) - 5.0) < 0.3
    # per image: a batch of two with blur on one only leaves the other as it was
    two = Degradation(torch.tensor([0.0, 2.0], dtype=torch.float64), *(getattr(_one(2), n) for n in
                      ("vignetting", "exposure", "noise_sigma", "gamma")))
    out = two.apply(tex.expand(2, 1, H, W))
    torch.testing.assert_close(out[0], tex[0])
    assert not torch.allclose(out[1], tex[0], atol=0.5)


def test_degradation_hurts_lk(photo):
    """Strong enough to matter: the default degradation makes LK clearly worse than on clean frames."""
    fl = fly_over(photo, 4, (128, 128), batch=3, generator=_gen(3))
    prev, nxt, rel = fl.pairs()
    pts, valid = good_features_to_track(prev, 30, 0.01, 8)
    target, ok = homography_targets(pts.double(), rel)
    g = _gen(4)
    errs = []
    for a, b in ((prev, nxt), (degrade(prev, g)[0], degrade(nxt, g)[0])):
        out, st = track_lk(a, b, pts, valid, 21, 2)
        errs.append(float((out.double() - target).norm(dim=-1)[st & ok].median()))
    assert errs[1] > 4 * errs[0], errs


def test_bad_arguments(photo):
    with pytest.raises(ValueError, match="texture"):
        fly_over(torch.zeros(2, 1, 50, 50), 2, (20, 20), batch=3)
    with pytest.raises(ConfigError):
        fly_over(photo, 0, SIZE)
    with pytest.raises(ConfigError, match="range"):
        Degradation.sample(2, _gen(0), exposure=(0.0, 2.0))
    with pytest.raises(ValueError, match="blur_sigma"):
        Degradation.identity(2).apply(torch.zeros(3, 1, 8, 8))
