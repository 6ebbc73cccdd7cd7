"""Common base of the camodocal camera models and the small numeric helpers they share.

Convention (all models):
    * pixels ``uv: (..., 2)`` float, ``(u, v)`` = (column, row), pixel centres at integer
      coordinates (camodocal/OpenCV convention);
    * rays / points ``P: (..., 3)`` float, camera frame, z forward. ``lift`` returns camodocal's
      ``liftProjective`` vector, which is *not* normalised (Pinhole/MEI/Scaramuzza) or is a unit
      vector (Kannala-Brandt), exactly as upstream;
    * any number of leading dimensions; CPU or CUDA; float32 or float64. Parameters are cast to
      the input's dtype and device on every call (the cast is differentiable, so gradients reach
      float64 parameters from float32 inputs).

Parameters are ``torch.nn.Parameter`` objects created with ``requires_grad=False``: the camera is a
plain fixed calibration by default (no autograd graph is built through it), ``cam.to(device,
dtype)`` moves and casts them, ``cam.state_dict()`` saves them, and ``cam.requires_grad_()`` (the
standard ``nn.Module`` call) switches on gradients for all of them so that ``cam.parameters()`` can go
to an optimiser. ``torch.func.functional_call(cam, {name: tensor}, (P,))`` evaluates ``forward``
(= ``project``) with other parameter values.

A model holds one camera (0-d parameters; Scaramuzza's polynomials are 1-D). Leading dimensions of
the points broadcast against it. B different calibrations (any mix of models) with a leading stream
dimension are a ``batch.CameraBatch``, which runs these models' own ``_lift_impl`` /
``_project_impl`` on ``(B, 1, ...)``-shaped parameters: the impls must stay elementwise.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar, Dict, List, Mapping, Tuple

import torch
from torch import nn

from .._checks import check_shape


class CameraModel(nn.Module):
    """Base class of the camodocal models (``PinholeCamera``, ``MeiCamera``, ...).

    Subclasses set ``model_type`` (the camodocal YAML string), ``param_names`` (order of the
    constructor's positional parameters and of ``params_dict``), ``vector_params`` (name -> length
    for 1-D parameters) and implement ``_lift_impl(uv, **params)`` / ``_project_impl(P, **params)``
    on already checked and cast tensors.

    Attributes:
        model_type: camodocal model string, e.g. ``"PINHOLE"``.
        camera_name: free text from the YAML (``camera_name``).
        width, height: image size in pixels (``image_width``, ``image_height``); 0 when unknown.
    """

    model_type: ClassVar[str] = ""
    param_names: ClassVar[Tuple[str, ...]] = ()
    vector_params: ClassVar[Dict[str, int]] = {}
    #: parameters that must be > 0 (the focal lengths: ``lift`` divides by them) and >= 0
    positive_params: ClassVar[Tuple[str, ...]] = ()
    nonnegative_params: ClassVar[Tuple[str, ...]] = ()

    def __init__(
        self,
        params: Mapping[str, Any],
        *,
        width: int = 0,
        height: int = 0,
        camera_name: str = "camera",
        dtype: torch.dtype = torch.float64,
        device: torch.device | None = None,
    ) -> None:
        super().__init__()
        missing = [n for n in self.param_names if n not in params]
        extra = [n for n in params if n not in self.param_names]
        if missing or extra:
            raise ValueError(
                f"{type(self).__name__}: parameters must be exactly {list(self.param_names)}; "
                f"missing {missing}, unexpected {extra}"
            )
        for name in self.param_names:
            value = params[name]
            if isinstance(value, torch.Tensor):
                t = value.detach().to(device=device if device is not None else value.device, dtype=dtype).clone()
            else:
                t = torch.as_tensor(value, dtype=dtype, device=device)
            want = (self.vector_params[name],) if name in self.vector_params else ()
            if tuple(t.shape) != want:
                raise ValueError(f"{type(self).__name__}: parameter {name}: expected shape {want}, got {tuple(t.shape)}")
            # requires_grad=False: a calibration is constant unless the user opts in with
            # cam.requires_grad_() (then every parameter is a leaf an optimiser can update).
            self.register_parameter(name, nn.Parameter(t, requires_grad=False))
        self.width = int(width)
        self.height = int(height)
        self.camera_name = str(camera_name)

    # ------------------------------------------------------------------ construction / export
    @classmethod
    def from_params(cls, params: Mapping[str, Any], **kwargs: Any) -> CameraModel:
        """Build from a ``{name: value}`` mapping (the layout ``params_dict`` returns).

        ``kwargs`` go to the constructor (``width``, ``height``, ``camera_name``, ``dtype``,
        ``device`` and model options such as ``undistort_iters``).
        """
        params = dict(params)
        missing = [n for n in cls.param_names if n not in params]
        extra = [n for n in params if n not in cls.param_names]
        if missing or extra:
            raise ValueError(
                f"{cls.__name__}.from_params: parameters must be exactly {list(cls.param_names)}; "
                f"missing {missing}, unexpected {extra}"
            )
        return cls(**params, **kwargs)

    @classmethod
    def param_problems(cls, params: Mapping[str, Any]) -> List[Tuple[str, str]]:
        """What makes the calibration values ``params`` (``{name: number}``, lists for vectors, the
        ``params_dict`` layout) unusable for this model, as ``[(name, problem)]``; empty when none.

        Every value must be finite, ``positive_params`` (focal lengths) > 0 and
        ``nonnegative_params`` >= 0; a model adds its own rules in ``_model_problems``. An element of
        a vector parameter is named ``name[i]``. The readers of calibration files
        (``camera_from_config``, ``config.camera_from_sensor_yaml``) raise a ``ConfigError`` naming
        the file's key for the first problem: upstream would accept the values and return NaN or
        garbage rays (``fx: 0`` divides by zero in every ``lift``).
        """
        values: Dict[str, List[float]] = {
            n: torch.as_tensor(params[n], dtype=torch.float64).detach().cpu().reshape(-1).tolist()
            for n in cls.param_names
        }
        problems: List[Tuple[str, str]] = []
        for name, vals in values.items():
            for i, v in enumerate(vals):
                if not math.isfinite(v):
                    problems.append((f"{name}[{i}]" if name in cls.vector_params else name,
                                     f"must be a finite number, got {v!r}"))
        if problems:
            return problems
        for name in cls.positive_params:
            if not values[name][0] > 0:
                problems.append((name, f"must be > 0 (a focal length in pixels), got {values[name][0]!r}"))
        for name in cls.nonnegative_params:
            if not values[name][0] >= 0:
                problems.append((name, f"must be >= 0, got {values[name][0]!r}"))
        return problems + cls._model_problems(values)

    @classmethod
    def _model_problems(cls, values: Mapping[str, List[float]]) -> List[Tuple[str, str]]:
        """Model-specific rules of :meth:`param_problems` on finite values (``{name: [floats]}``)."""
        return []

    def params_dict(self) -> Dict[str, Any]:
        """Parameters as Python floats (lists for Scaramuzza's polynomials), in ``param_names`` order."""
        out: Dict[str, Any] = {}
        for name in self.param_names:
            t = getattr(self, name).detach().cpu()
            out[name] = t.tolist() if t.dim() else float(t)
        return out

    def _extra_repr_items(self) -> Dict[str, Any]:
        return {}

    def extra_repr(self) -> str:
        items = [f"camera_name={self.camera_name!r}", f"width={self.width}", f"height={self.height}"]
        for name, value in self.params_dict().items():
            if isinstance(value, list):
                items.append(f"{name}=[{', '.join(repr(v) for v in value)}]")
            else:
                items.append(f"{name}={value!r}")
        items += [f"{k}={v!r}" for k, v in self._extra_repr_items().items()]
        p = next(iter(self.parameters()), None)
        if p is not None:
            items.append(f"dtype={p.dtype}, device={p.device}")
        return ", ".join(items)

    # ------------------------------------------------------------------ public maths
    def _params_like(self, x: torch.Tensor) -> Dict[str, torch.Tensor]:
        return {n: getattr(self, n).to(device=x.device, dtype=x.dtype) for n in self.param_names}

    def _as_float(self, x: torch.Tensor) -> torch.Tensor:
        if x.is_floating_point():
            return x
        # integer pixel coordinates are legal input; compute in the camera's own dtype
        return x.to(getattr(self, self.param_names[0]).dtype)

    #: models whose ``lift`` accepts ``jacobian="implicit"`` (a converged inverse)
    implicit_lift: ClassVar[bool] = False

    def lift(self, uv: torch.Tensor, *, jacobian: str = "unrolled") -> torch.Tensor:
        """camodocal ``liftProjective``: pixels to the model's (unnormalised) ray.

        Args:
            uv: ``(..., 2)`` float, pixels ``(u, v)``.
            jacobian: ``"unrolled"`` (default): camodocal's values, differentiated as computed
                (for Pinhole / MEI the fixed count of fixed-point evaluations). ``"implicit"``
                (Pinhole, MEI, Kannala-Brandt): the *converged* inverse (damped Newton, finite for
                any finite input) with the implicit-function Jacobian of the converged inverse,
                exact to second order (:func:`radtan_undistort_converged`); Kannala-Brandt's
                ``lift`` is converged already, both values are the same.

        Returns:
            ``(..., 3)`` in uv's dtype/device; see each model for normalisation and invalid lanes.
        """
        check_shape(uv, ("*", 2), "uv")
        uv = self._as_float(uv)
        if jacobian == "unrolled":
            return self._lift_impl(uv, **self._params_like(uv))
        if jacobian != "implicit":
            raise ValueError(f"jacobian must be 'unrolled' or 'implicit', got {jacobian!r}")
        if not self.implicit_lift:
            raise ValueError(f"{type(self).__name__}.lift has no jacobian='implicit' option")
        return self._lift_impl(uv, **self._params_like(uv), converged=True)

    def project(self, P: torch.Tensor) -> torch.Tensor:
        """camodocal ``spaceToPlane``: camera-frame points to pixels.

        Args:
            P: ``(..., 3)`` float, points or rays in the camera frame (any scale).

        Returns:
            ``(..., 2)`` pixels ``(u, v)``.
        """
        check_shape(P, ("*", 3), "P")
        P = self._as_float(P)
        return self._project_impl(P, **self._params_like(P))

    def undistort(self, uv: torch.Tensor, *, jacobian: str = "unrolled") -> torch.Tensor:
        """Normalised undistorted image coordinates ``(x/z, y/z)`` of ``lift(uv, jacobian=...)``: ``(..., 2)``.

        This is what VINS' ``undistortedPoints`` computes (it divides by z without a check, so rays
        with ``z <= 0`` give inf/negative values exactly as upstream).
        """
        P = self.lift(uv, jacobian=jacobian)
        return P[..., :2] / P[..., 2:3]

    def forward(self, P: torch.Tensor) -> torch.Tensor:
        """Same as ``project`` (a camera module maps 3-D points to pixels)."""
        return self.project(P)

    def _lift_impl(self, uv: torch.Tensor, **p: torch.Tensor) -> torch.Tensor:  # pragma: no cover
        raise NotImplementedError

    def _project_impl(self, P: torch.Tensor, **p: torch.Tensor) -> torch.Tensor:  # pragma: no cover
        raise NotImplementedError


# ---------------------------------------------------------------------- shared numerics
def radtan_distortion(
    x: torch.Tensor, y: torch.Tensor, k1: torch.Tensor, k2: torch.Tensor, p1: torch.Tensor, p2: torch.Tensor
) -> Tuple[torch.Tensor, torch.Tensor]:
    """camodocal ``distortion(p_u)``: displacement ``(d_x, d_y)`` of undistorted normalised ``(x, y)``.

    ``d_x = x(k1 r² + k2 r⁴) + 2 p1 x y + p2 (r² + 2x²)``, ``d_y = y(k1 r² + k2 r⁴) + 2 p2 x y + p1 (r² + 2y²)``.
    The evaluation order follows upstream term by term so results agree to the last bits.
    """
    mx2 = x * x
    my2 = y * y
    mxy = x * y
    rho2 = mx2 + my2
    rad = k1 * rho2 + k2 * rho2 * rho2
    dx = x * rad + 2.0 * p1 * mxy + p2 * (rho2 + 2.0 * mx2)
    dy = y * rad + 2.0 * p2 * mxy + p1 * (rho2 + 2.0 * my2)
    return dx, dy


def radtan_undistort(
    mxd: torch.Tensor,
    myd: torch.Tensor,
    k1: torch.Tensor,
    k2: torch.Tensor,
    p1: torch.Tensor,
    p2: torch.Tensor,
    evaluations: int,
) -> Tuple[torch.Tensor, torch.Tensor]:
    """camodocal's recursive distortion inversion (Pinhole and MEI ``liftProjective``).

    ``m_u <- m_d - d(m_d)``, then ``evaluations - 1`` times ``m_u <- m_d - d(m_u)`` (upstream: 8
    evaluations in total). This is a plain fixed point, not a solver: it stops after the fixed count
    whether or not it converged (at the EuRoC image corners the residual is ~0.1 px after 8).

    The ``noDistortion`` shortcut (all four coefficients exactly 0 => ``m_u = m_d``) is value-identical
    for finite input (every displacement is then ±0), so the loop always runs: that keeps the
    gradient w.r.t. the coefficients correct at zero distortion, where a ``where(no_dist, m_d, ...)``
    would cut it. The shortcut is applied only where the loop produced a non-finite value (inf input:
    ``0 * inf`` is NaN in the loop, while upstream returns ``m_d``).
    """
    # x and y stacked as one (2, ...) tensor: each operation of radtan_distortion on both
    # components at once, in the same order (the same values), in about half the kernels; the
    # parameters (p1, p2), 2 (p1, p2) and (p2, p1) are stacked once per call
    full = torch.broadcast_shapes(mxd.shape, myd.shape, k1.shape, k2.shape, p1.shape, p2.shape)
    Md = torch.stack((mxd.expand(full), myd.expand(full)))  # (2, *full)
    pshape = torch.broadcast_shapes(p1.shape, p2.shape)
    P = torch.stack((p1.expand(pshape), p2.expand(pshape))).view((2,) + (1,) * (len(full) - len(pshape)) + pshape)
    two_p = 2.0 * P
    Q = P.flip(0)

    def displacement(X):  # (dx, dy) of radtan_distortion, stacked
        M2 = X * X
        mxy = X[0] * X[1]
        rho2 = M2[0] + M2[1]
        rad = k1 * rho2 + k2 * rho2 * rho2
        return X * rad + two_p * mxy + Q * (rho2 + 2.0 * M2)

    Mu = Md - displacement(Md)
    for _ in range(evaluations - 1):
        Mu = Md - displacement(Mu)
    no_dist = (k1 == 0) & (k2 == 0) & (p1 == 0) & (p2 == 0)
    Mu = torch.where(no_dist & ~torch.isfinite(Mu), Md, Mu)
    return Mu[0], Mu[1]


def _radtan_residual(x, y, mxd, myd, k1, k2, p1, p2):
    """``r = m + d(m) - m_d`` ``(2, ...)`` and its Jacobian ``dr/dm`` ``(2, 2, ...)`` (analytic)."""
    dx, dy = radtan_distortion(x, y, k1, k2, p1, p2)
    r2 = x * x + y * y
    rad = k1 * r2 + k2 * r2 * r2
    drad = 2.0 * (k1 + 2.0 * k2 * r2)  # d rad / d(x, y) = drad * (x, y)
    jxx = 1 + rad + x * x * drad + 2.0 * p1 * y + 6.0 * p2 * x
    jxy = x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
    jyx = x * y * drad + 2.0 * p2 * y + 2.0 * p1 * x
    jyy = 1 + rad + y * y * drad + 2.0 * p2 * x + 6.0 * p1 * y
    return torch.stack((x + dx - mxd, y + dy - myd)), torch.stack((torch.stack((jxx, jxy)), torch.stack((jyx, jyy))))


def _solve22(A, r, ok):
    """``A^-1 r`` for ``(2, 2, ...)`` / ``(2, ...)``, 0 where not ``ok`` (inputs replaced first: no NaN)."""
    one, zero = torch.ones_like(A[0, 0]), torch.zeros_like(A[0, 0])
    a, b = torch.where(ok, A[0, 0], one), torch.where(ok, A[0, 1], zero)
    c, d = torch.where(ok, A[1, 0], zero), torch.where(ok, A[1, 1], one)
    r0, r1 = torch.where(ok, r[0], zero), torch.where(ok, r[1], zero)
    det = a * d - b * c
    det = torch.where(ok & (det != 0), det, one)
    return torch.stack(((d * r0 - b * r1) / det, (a * r1 - c * r0) / det))


#: damped Newton for the radial-tangential inverse: iterations, step fractions tried per iteration
#: (the one with the smallest residual wins, 0 = stay: the residual never grows), tolerance
RADTAN_NEWTON_ITERS = 40
RADTAN_STEP_FRACTIONS = (1.0, 0.5, 0.25, 0.125, 2.0**-5, 2.0**-8, 0.0)
RADTAN_CONVERGED_TOL = 1e-9


def radtan_undistort_converged(mxd, myd, k1, k2, p1, p2):
    """The converged inverse of camodocal's distortion, ``m + d(m) = m_d``, by damped Newton.

    A fixed count (``RADTAN_NEWTON_ITERS``, no host sync) of Newton steps with the true Jacobian,
    each scaled by the fraction of ``RADTAN_STEP_FRACTIONS`` with the smallest residual (including
    0), so the residual never grows and every value stays finite — camodocal's plain fixed point
    ``m <- m_d - d(m)`` diverges (inf/NaN) where ``|d'| > 1``, e.g. the EuRoC calibration with
    ``k2 = 0`` at 22 % of the pixels with 64 evaluations. Starts at ``m_d``.

    Derivatives: implicit, exact to second order — two differentiable Newton steps from the
    detached solution (``N(m) = m - J^-1 r``; the first gives ``dm = -J^-1 dr``, the second the
    second derivatives), the value unchanged. Where no inverse exists (a strongly non-monotone
    polynomial: the residual stays above ``RADTAN_CONVERGED_TOL (1 + |m_d|)``) or ``J`` is singular,
    the value is the damped iteration's last point (finite) and its gradient is 0.

    Returns:
        ``(m_u.x, m_u.y)`` and the ``converged`` mask.
    """
    with torch.no_grad():
        xd, yd = mxd.detach(), myd.detach()
        kd = [t.detach() for t in (k1, k2, p1, p2)]
        finite = torch.isfinite(xd) & torch.isfinite(yd)
        x, y = torch.where(finite, xd, 0.0), torch.where(finite, yd, 0.0)
        xs, ys = x, y
        tru = torch.ones_like(x, dtype=torch.bool)
        for _ in range(RADTAN_NEWTON_ITERS):
            r, J = _radtan_residual(x, y, xs, ys, *kd)
            s = _solve22(J, r, tru)
            best = (r * r).sum(0)
            bx, by = x, y
            for t in RADTAN_STEP_FRACTIONS[:-1]:
                cx, cy = x - t * s[0], y - t * s[1]
                rc, _ = _radtan_residual(cx, cy, xs, ys, *kd)
                e = (rc * rc).sum(0)
                better = e < best  # NaN (overflow) is never better
                best = torch.where(better, e, best)
                bx, by = torch.where(better, cx, bx), torch.where(better, cy, by)
            x, y = bx, by
        r, J = _radtan_residual(x, y, xs, ys, *kd)
        det = J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0]
        conv = finite & (r.abs().amax(0) <= RADTAN_CONVERGED_TOL * (1 + xs.abs() + ys.abs())) & (det.abs() > 1e-12)
    m = torch.stack((x, y))

    def step(mm):
        r, J = _radtan_residual(mm[0], mm[1], torch.where(conv, mxd, 0.0), torch.where(conv, myd, 0.0), k1, k2, p1, p2)
        return -_solve22(J, r, conv)

    c1 = step(m)
    m1 = m + (c1 - c1.detach())
    c2 = m1 + step(m1)
    out = m + torch.where(conv, c2 - c2.detach(), 0.0)
    # non-finite input stays as the unrolled path gives it (NaN in, NaN out)
    out = torch.where(finite, out, torch.full_like(out, math.nan))  # a constant: no NaN gradient
    return out[0], out[1], conv


def safe_norm2(a: torch.Tensor, b: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """``(sqrt(a² + b²), nonzero_mask)`` with a finite gradient at the origin (mask False only there).

    ``sqrt`` has an infinite derivative at 0 and ``torch.where`` differentiates both branches, so the
    square root is taken of 1 in the zero lanes and the result replaced by 0 there.
    """
    n2 = a * a + b * b
    # test for == 0 (not > 0) so that NaN input stays NaN, as upstream's plain sqrt would give
    nz = ~(n2 == 0)
    n = torch.where(nz, torch.sqrt(torch.where(nz, n2, torch.ones_like(n2))), torch.zeros_like(n2))
    return n, nz


def check_iters(value: int, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name}: expected a positive int, got {value!r}")
    return value


NAN = math.nan
