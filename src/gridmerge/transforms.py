"""2-D geometric transforms between maps, in pixels and in metres.

Each transform is a small class holding a ``(3, 3)`` homogeneous matrix ``params`` that
maps source points to destination points, in the style of scikit-image's
``SimilarityTransform``. ``from_estimate(src, dst)`` fits one to point correspondences
and returns either the transform or a falsy :class:`FailedEstimation` that says why.

In gridmerge, an alignment's transform maps map **b**'s image pixels to map **a**'s image
pixels (``x`` = column, ``y`` = row, origin at the centre of the top-left cell).
:func:`pixel_to_metric` turns such a transform into one between the two maps' metric
frames (ROS conventions), and :func:`metric_to_pixel` turns it back.

Examples
--------
>>> import numpy as np
>>> from gridmerge.transforms import SimilarityTransform
>>> t = SimilarityTransform(rotation=np.deg2rad(30), scale=0.95, translation=(-86, -36))
>>> src = np.array([[0.0, 0.0], [100.0, 0.0], [0.0, 50.0]])
>>> est = SimilarityTransform.from_estimate(src, t(src))
>>> bool(est), round(float(np.rad2deg(est.rotation)), 6), round(est.scale, 6)
(True, 30.0, 0.95)
>>> np.allclose(est.inverse(t(src)), src)
True
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Sequence

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from .grid import OccupancyGrid

__all__ = [
    "FailedEstimation",
    "AffineTransform",
    "SimilarityTransform",
    "ScaledRotationTransform",
    "pixel_to_metric",
    "metric_to_pixel",
    "TRANSFORMS",
]


class FailedEstimation:
    """A falsy result of ``from_estimate``: the estimation failed, and ``message`` says why.

    Examples
    --------
    >>> f = FailedEstimation("points are collinear")
    >>> bool(f), f.message
    (False, 'points are collinear')
    """

    __slots__ = ("message",)

    def __init__(self, message: str):
        self.message = message

    def __bool__(self) -> bool:
        return False

    def __repr__(self) -> str:
        return f"FailedEstimation({self.message!r})"


def _as_points(xy, name: str = "points") -> np.ndarray:
    pts = np.asarray(xy, dtype=float)
    if pts.ndim == 1 and pts.size == 2:
        pts = pts.reshape(1, 2)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"{name} must be an (N, 2) array, got shape {pts.shape}")
    return pts


def _check_pair(src, dst) -> tuple[np.ndarray, np.ndarray]:
    src = _as_points(src, "src")
    dst = _as_points(dst, "dst")
    if src.shape != dst.shape:
        raise ValueError(f"src and dst must have the same shape, got {src.shape} and {dst.shape}")
    return src, dst


class AffineTransform:
    """A general 2-D affine transform (6 parameters).

    Parameters
    ----------
    matrix : (3, 3) or (2, 3) array_like, optional
        Homogeneous matrix mapping source to destination points. Identity by default.

    Attributes
    ----------
    params : (3, 3) float array
        The homogeneous matrix.
    """

    #: Number of parameters of the model (degrees of freedom).
    dof = 6
    #: Minimal number of correspondences that determine the model.
    min_samples = 3

    def __init__(self, matrix=None):
        if matrix is None:
            params = np.eye(3)
        else:
            m = np.asarray(matrix, dtype=float)
            if m.shape == (2, 3):
                m = np.vstack([m, [0.0, 0.0, 1.0]])
            if m.shape != (3, 3):
                raise ValueError(f"matrix must be (2, 3) or (3, 3), got {m.shape}")
            if not np.allclose(m[2], [0.0, 0.0, 1.0]):
                raise ValueError("the last row of an affine matrix must be [0, 0, 1]")
            params = m.copy()
        self.params = params

    # ----------------------------------------------------------- estimation
    @classmethod
    def from_estimate(cls, src, dst, weights=None):
        """Least-squares fit to ``(N, 2)`` correspondences ``src -> dst``.

        Returns the transform, or a :class:`FailedEstimation` when the points do not
        determine it (too few, collinear, non-finite).
        """
        src, dst = _check_pair(src, dst)
        if len(src) < cls.min_samples:
            return FailedEstimation(f"need at least {cls.min_samples} correspondences, got {len(src)}")
        if not (np.isfinite(src).all() and np.isfinite(dst).all()):
            return FailedEstimation("non-finite coordinates")
        return cls._estimate(src, dst, None if weights is None else np.asarray(weights, dtype=float))

    @classmethod
    def _estimate(cls, src, dst, weights):
        n = len(src)
        w = np.ones(n) if weights is None else weights
        sw = np.sqrt(w)[:, None]
        a = np.hstack([src, np.ones((n, 1))]) * sw
        if np.linalg.matrix_rank(a, tol=1e-9 * max(1.0, float(np.abs(a).max()))) < 3:
            return FailedEstimation("points are collinear")
        sol, *_ = np.linalg.lstsq(a, dst * sw, rcond=None)
        m = np.vstack([sol.T, [0.0, 0.0, 1.0]])
        if not np.isfinite(m).all():
            return FailedEstimation("estimation diverged")
        return cls(m)

    # ------------------------------------------------------------ behaviour
    def __call__(self, xy) -> np.ndarray:
        """Apply to ``(N, 2)`` points; returns ``(N, 2)`` float array."""
        pts = _as_points(xy)
        return pts @ self.params[:2, :2].T + self.params[:2, 2]

    def residuals(self, src, dst) -> np.ndarray:
        """``(N,)`` Euclidean distances between ``self(src)`` and ``dst``."""
        src, dst = _check_pair(src, dst)
        return np.hypot(*(self(src) - dst).T)

    @property
    def inverse(self) -> "AffineTransform":
        """The inverse transform (destination to source)."""
        return AffineTransform(np.linalg.inv(self.params))

    def __matmul__(self, other: "AffineTransform") -> "AffineTransform":
        """``(self @ other)(p) == self(other(p))``."""
        if not isinstance(other, AffineTransform):
            return NotImplemented
        return AffineTransform(self.params @ other.params)

    @property
    def matrix(self) -> np.ndarray:
        """``(2, 3)`` float array: the top two rows of :attr:`params`."""
        return self.params[:2].copy()

    @property
    def translation(self) -> np.ndarray:
        """``(2,)`` float array ``(tx, ty)``."""
        return self.params[:2, 2].copy()

    @property
    def rotation(self) -> float:
        """Rotation angle of the first axis, radians, counter-clockwise in ``(x, y)``."""
        return math.atan2(self.params[1, 0], self.params[0, 0])

    @property
    def scale(self) -> float:
        """Mean linear scale, ``sqrt(|det|)``."""
        return math.sqrt(abs(float(np.linalg.det(self.params[:2, :2]))))

    @property
    def scale_xy(self) -> tuple[float, float]:
        """Lengths of the images of the unit x and y axes."""
        return float(np.hypot(*self.params[:2, 0])), float(np.hypot(*self.params[:2, 1]))

    def is_finite(self) -> bool:
        return bool(np.isfinite(self.params).all())

    def __repr__(self) -> str:
        return f"{type(self).__name__}(matrix={np.array2string(self.params[:2], precision=6, separator=', ')})"

    def __eq__(self, other) -> bool:
        if not isinstance(other, AffineTransform):
            return NotImplemented
        return type(self) is type(other) and bool(np.array_equal(self.params, other.params))

    __hash__ = None  # type: ignore[assignment]

    def to_dict(self) -> dict:
        """JSON-ready description: kind, 2x3 matrix and the named parameters."""
        sx, sy = self.scale_xy
        return {
            "kind": type(self).__name__,
            "matrix": self.matrix.tolist(),
            "rotation_deg": math.degrees(self.rotation),
            "scale": self.scale,
            "scale_x": sx,
            "scale_y": sy,
            "translation": self.translation.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "AffineTransform":
        kind = TRANSFORMS.get(d.get("kind", cls.__name__), cls)
        return kind(np.asarray(d["matrix"], dtype=float))


class SimilarityTransform(AffineTransform):
    """Rotation, uniform scale and translation (4 parameters).

    ``p' = s R(theta) p + t``.

    Parameters
    ----------
    matrix : (3, 3) or (2, 3) array_like, optional
        Homogeneous matrix; must be a similarity (no shear, no reflection).
    rotation : float, optional
        Angle in radians (counter-clockwise in ``(x, y)``; with image rows pointing down
        this looks clockwise on screen).
    scale : float, optional
    translation : (2,) sequence of float, optional
    """

    dof = 4
    min_samples = 2

    def __init__(self, matrix=None, *, rotation=None, scale=None, translation=None):
        if matrix is not None and any(v is not None for v in (rotation, scale, translation)):
            raise ValueError("give either matrix or rotation/scale/translation, not both")
        if matrix is None:
            th = 0.0 if rotation is None else float(rotation)
            s = 1.0 if scale is None else float(scale)
            tx, ty = (0.0, 0.0) if translation is None else (float(translation[0]), float(translation[1]))
            c, sn = s * math.cos(th), s * math.sin(th)
            matrix = [[c, -sn, tx], [sn, c, ty], [0.0, 0.0, 1.0]]
        super().__init__(matrix)
        a, b = self.params[0, 0], self.params[1, 0]
        tol = 1e-6 * max(1.0, math.hypot(a, b))
        if abs(self.params[1, 1] - a) > tol or abs(self.params[0, 1] + b) > tol:
            raise ValueError("matrix is not a similarity (it has shear or reflection)")

    @classmethod
    def _estimate(cls, src, dst, weights):
        # Closed-form weighted least squares (Umeyama without reflection): the model is
        # linear in (a, b, tx, ty) with [[a, -b], [b, a]].
        n = len(src)
        w = np.ones(n) if weights is None else weights
        wsum = float(w.sum())
        if not wsum > 0:
            return FailedEstimation("weights sum to zero")
        ms = (w[:, None] * src).sum(0) / wsum
        md = (w[:, None] * dst).sum(0) / wsum
        s0 = src - ms
        d0 = dst - md
        var = float((w * (s0**2).sum(1)).sum())
        if var <= 1e-12 * max(1.0, float(np.abs(src).max()) ** 2):
            return FailedEstimation("source points coincide")
        a = float((w * (s0[:, 0] * d0[:, 0] + s0[:, 1] * d0[:, 1])).sum()) / var
        b = float((w * (s0[:, 0] * d0[:, 1] - s0[:, 1] * d0[:, 0])).sum()) / var
        if math.hypot(a, b) < 1e-12:
            return FailedEstimation("degenerate correspondences (zero scale)")
        r = np.array([[a, -b], [b, a]])
        t = md - r @ ms
        return cls(np.array([[a, -b, t[0]], [b, a, t[1]], [0.0, 0.0, 1.0]]))

    @property
    def inverse(self) -> "SimilarityTransform":
        return SimilarityTransform(np.linalg.inv(self.params))

    def __matmul__(self, other):
        if type(other) is SimilarityTransform:
            return SimilarityTransform(self.params @ other.params)
        return super().__matmul__(other)

    @property
    def scale(self) -> float:
        return float(math.hypot(self.params[0, 0], self.params[1, 0]))


class ScaledRotationTransform(AffineTransform):
    """The paper's 5-parameter transform ``T(dx, dy) R(theta) S(sx, sy)`` (eq. 7-8).

    ``params = [[sx cos t, -sy sin t, dx], [sx sin t, sy cos t, dy], [0, 0, 1]]``.

    Parameters
    ----------
    rotation : float
        ``theta`` in radians.
    scale : (2,) sequence of float or float
        ``(sx, sy)``; a single number sets both.
    translation : (2,) sequence of float
        ``(dx, dy)``.
    matrix : (3, 3) or (2, 3) array_like, optional
        Alternatively, a matrix of that form (its parameters are read back from it).

    Examples
    --------
    >>> t = ScaledRotationTransform(rotation=0.5, scale=(0.9, 1.1), translation=(3, 4))
    >>> [round(v, 6) for v in t.parameters]
    [3.0, 4.0, 0.5, 0.9, 1.1]
    """

    dof = 5
    min_samples = 3

    def __init__(self, matrix=None, *, rotation=None, scale=None, translation=None):
        if matrix is not None:
            if any(v is not None for v in (rotation, scale, translation)):
                raise ValueError("give either matrix or rotation/scale/translation, not both")
            super().__init__(matrix)
            dx, dy, th, sx, sy = _five_from_matrix(self.params)
            rebuilt = _five_to_matrix(dx, dy, th, sx, sy)
            if not np.allclose(rebuilt, self.params, atol=1e-6 * max(1.0, float(np.abs(self.params[:2, :2]).max()))):
                raise ValueError("matrix is not of the form T(dx, dy) R(theta) S(sx, sy)")
            return
        th = 0.0 if rotation is None else float(rotation)
        if scale is None:
            sx = sy = 1.0
        elif np.ndim(scale) == 0:
            sx = sy = float(scale)  # type: ignore[arg-type]
        else:
            sx, sy = (float(v) for v in scale)  # type: ignore[union-attr]
        dx, dy = (0.0, 0.0) if translation is None else (float(translation[0]), float(translation[1]))
        super().__init__(_five_to_matrix(dx, dy, th, sx, sy))

    @classmethod
    def from_parameters(cls, dx: float, dy: float, theta: float, sx: float, sy: float) -> "ScaledRotationTransform":
        """Build from the paper's parameter vector ``(dx, dy, theta, sx, sy)``."""
        return cls(rotation=theta, scale=(sx, sy), translation=(dx, dy))

    @property
    def parameters(self) -> list[float]:
        """The paper's parameter vector ``[dx, dy, theta, sx, sy]``."""
        return list(_five_from_matrix(self.params))

    @property
    def rotation(self) -> float:
        return _five_from_matrix(self.params)[2]

    @classmethod
    def _estimate(cls, src, dst, weights):
        # Linear start: exact affine solve (3 points: the paper's 6 linear equations),
        # projected onto the 5-parameter form; then Gauss-Newton on the 5 parameters
        # when there are more points than that.
        aff = AffineTransform._estimate(src, dst, weights)
        if not aff:
            return aff
        p = np.array(_five_from_matrix(aff.params))
        if not np.isfinite(p).all() or p[3] <= 0 or p[4] <= 0:
            return FailedEstimation("degenerate correspondences")
        if len(src) > 3:
            p = _gauss_newton_five(p, src, dst, weights)
            if p is None:
                return FailedEstimation("estimation diverged")
        return cls.from_parameters(*p)

    def to_dict(self) -> dict:
        d = super().to_dict()
        dx, dy, th, sx, sy = self.parameters
        d.update(rotation_deg=math.degrees(th), scale_x=sx, scale_y=sy, scale=math.sqrt(sx * sy))
        return d


def _five_to_matrix(dx, dy, th, sx, sy) -> np.ndarray:
    c, s = math.cos(th), math.sin(th)
    return np.array([[sx * c, -sy * s, dx], [sx * s, sy * c, dy], [0.0, 0.0, 1.0]])


def _five_from_matrix(m: np.ndarray) -> tuple[float, float, float, float, float]:
    """Closest ``(dx, dy, theta, sx, sy)`` to an affine matrix.

    ``sx`` and ``sy`` are the lengths of the two columns; theta averages the directions of
    the first column and of the second column turned back by 90 degrees.
    """
    a, b = m[0, 0], m[1, 0]
    c, d = m[0, 1], m[1, 1]
    sx = math.hypot(a, b)
    sy = math.hypot(c, d)
    t1 = math.atan2(b, a)
    t2 = math.atan2(-c, d)
    th = math.atan2(math.sin(t1) + math.sin(t2), math.cos(t1) + math.cos(t2))
    return float(m[0, 2]), float(m[1, 2]), th, sx, sy


def _gauss_newton_five(p0, src, dst, weights, iterations: int = 20):
    p = np.asarray(p0, dtype=float).copy()
    w = np.ones(len(src)) if weights is None else weights
    x, y = src[:, 0], src[:, 1]
    for _ in range(iterations):
        dx, dy, th, sx, sy = p
        c, s = math.cos(th), math.sin(th)
        px = sx * c * x - sy * s * y + dx
        py = sx * s * x + sy * c * y + dy
        r = np.concatenate([px - dst[:, 0], py - dst[:, 1]])
        one, zero = np.ones_like(x), np.zeros_like(x)
        jx = np.stack([one, zero, -sx * s * x - sy * c * y, c * x, -s * y], axis=1)
        jy = np.stack([zero, one, sx * c * x - sy * s * y, s * x, c * y], axis=1)
        j = np.vstack([jx, jy])
        ww = np.concatenate([w, w])
        jtw = j.T * ww
        try:
            step = np.linalg.solve(jtw @ j, -(jtw @ r))
        except np.linalg.LinAlgError:
            return None
        p += step
        if not np.isfinite(p).all():
            return None
        if np.abs(step).max() < 1e-12:
            break
    return p


TRANSFORMS = {
    "AffineTransform": AffineTransform,
    "SimilarityTransform": SimilarityTransform,
    "ScaledRotationTransform": ScaledRotationTransform,
}


def _same_kind(transform: AffineTransform, matrix: np.ndarray) -> AffineTransform:
    try:
        return type(transform)(matrix)
    except ValueError:  # a 5-parameter model seen from a rotated map frame is a general affine
        return AffineTransform(matrix)


def pixel_to_metric(transform: AffineTransform, src: "OccupancyGrid", dst: "OccupancyGrid") -> AffineTransform:
    """Turn a transform between two maps' image pixels into one between their metric frames.

    Parameters
    ----------
    transform : AffineTransform
        Maps ``src``'s image pixels to ``dst``'s image pixels.
    src, dst : OccupancyGrid
        The maps, whose ``resolution`` and ``origin`` define their metric frames.

    Returns
    -------
    AffineTransform
        Of the same kind where possible (a similarity stays one), mapping points of ``src``'s map frame (metres) to ``dst``'s map
        frame. Its rotation is the yaw of ``src``'s frame in ``dst``'s, its translation the
        position of ``src``'s frame origin, and its scale the metric scale (1 when both maps
        agree on the size of the world).
    """
    m = dst.pixel_to_metric_matrix() @ transform.params @ src.metric_to_pixel_matrix()
    return _same_kind(transform, m)


def metric_to_pixel(transform: AffineTransform, src: "OccupancyGrid", dst: "OccupancyGrid") -> AffineTransform:
    """The inverse operation of :func:`pixel_to_metric`."""
    m = dst.metric_to_pixel_matrix() @ transform.params @ src.pixel_to_metric_matrix()
    return _same_kind(transform, m)


def corner_error(estimate: AffineTransform | np.ndarray, truth: AffineTransform | np.ndarray, shape: Sequence[int]) -> float:
    """Largest distance, in destination pixels, between the images of the four corners
    of a source image of ``shape = (H, W)`` under ``estimate`` and under ``truth``."""
    e = estimate.params if isinstance(estimate, AffineTransform) else AffineTransform(estimate).params
    t = truth.params if isinstance(truth, AffineTransform) else AffineTransform(truth).params
    h, w = shape[:2]
    c = np.array([[0.0, 0.0, 1.0], [w - 1.0, 0.0, 1.0], [w - 1.0, h - 1.0, 1.0], [0.0, h - 1.0, 1.0]])
    d = (c @ e.T)[:, :2] - (c @ t.T)[:, :2]
    return float(np.hypot(d[:, 0], d[:, 1]).max())
