"""The distortion-versus-focal curve lam(f) of a zoom lens (paper section 7.2, eq. 35's second option
with a better-behaved family): the corner shift as a low-order polynomial in the field of view."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ptz_selfcal.camera.distortion import (
    corner_shift_of_lambda,
    corner_shift_of_lambda_derivative,
    half_diagonal,
    lambda_of_corner_shift,
)

Array = NDArray[np.float64]


def _robust_polynomial(A: Array, s: Array, w: Array, threshold: float) -> tuple[Array, float]:
    """Weighted Huber IRLS fit s ~ A c; returns c and the weighted robust residual sum of squares."""
    robust = np.ones_like(s)
    coeffs = np.zeros(A.shape[1])
    for _ in range(10):
        sw = np.sqrt(w * robust)
        coeffs = np.linalg.lstsq(A * sw[:, None], s * sw, rcond=None)[0]
        res = np.abs(A @ coeffs - s)
        robust = np.where(res <= threshold, 1.0, threshold / np.maximum(res, 1e-15))
    return coeffs, float(np.sum(w * robust * (A @ coeffs - s) ** 2))


class DistortionVsFocal:
    """lam(f) through the corner shift s (distortion %, as lens data sheets quote it) versus 1/f.

    s(f) = c0 + c1 u + c2 u^2,  u = f_ref / f  (field of view), and lam from s at rho = D / f, D the
    image half-diagonal (camera/distortion.lambda_of_corner_shift). Why this curve and not eq. 35's
    cubic in f: a zoom lens's distortion is a smooth function of the field of view, strongest (barrel)
    at the wide end and fading, often through zero, towards the tele end; a polynomial in 1/f is low
    order for that behaviour and stays bounded as f grows, where a cubic in f explodes. Outside the
    fitted range s is extrapolated proportionally to 1/f (distortion fades with the field of view),
    never by the polynomial. The fit is weighted, robust (Huber IRLS); the degree (at most `degree`) is
    chosen by BIC, and reduced when the focal range seen so far cannot support it.
    """

    def __init__(self, width: int, height: int, degree: int = 2, f_ref: float | None = None) -> None:
        self.half_diagonal = half_diagonal(width, height)
        self.degree = degree
        self.f_ref = f_ref
        self.coefficients: Array | None = None
        self.f_range: tuple[float, float] | None = None
        self.residual_rms: float = float("nan")

    # conversions between lam and the corner shift s at focal length f
    def shift_from_lambda(self, f: ArrayLike, lam: ArrayLike) -> Array:
        return corner_shift_of_lambda(lam, self.half_diagonal / np.asarray(f, dtype=float))

    def lambda_from_shift(self, f: ArrayLike, shift: ArrayLike) -> Array:
        return lambda_of_corner_shift(shift, self.half_diagonal / np.asarray(f, dtype=float))

    def fit(
        self, f: ArrayLike, lam: ArrayLike, weights: ArrayLike | None = None, huber_px: float = 1.0
    ) -> DistortionVsFocal:
        """Fit from per-keyframe (f, lam) estimates; weights = 1 / sigma^2 of lam (or None).

        huber_px: the Huber threshold in pixels of corner displacement (robust against bad keyframes).
        """
        f = np.asarray(f, dtype=float).ravel()
        lam = np.asarray(lam, dtype=float).ravel()
        ok = np.isfinite(f) & np.isfinite(lam) & (f > 0)
        w = np.ones_like(f) if weights is None else np.asarray(weights, dtype=float).ravel()
        ok &= np.isfinite(w) & (w > 0)
        f, lam, w = f[ok], lam[ok], w[ok]
        if len(f) == 0:
            raise ValueError("no valid samples")
        if self.f_ref is None:
            self.f_ref = float(f.min())
        u = self.f_ref / f
        s = self.shift_from_lambda(f, lam)
        # weights on s: sigma_s = |ds/dlam| sigma_lam
        w = w / corner_shift_of_lambda_derivative(lam, self.half_diagonal / f) ** 2
        w = w / w.max()
        distinct = len(np.unique(np.round(u, 3)))
        span = u.max() - u.min()
        max_degree = max(min(self.degree, distinct - 1, 1 if span < 0.15 else self.degree), 0)
        threshold = huber_px / self.half_diagonal
        # degree by BIC (unknown noise level): n ln(RSS / n) + (d + 1) ln n, each fit robust
        best: tuple[float, Array, Array] | None = None
        n = len(s)
        for degree in range(max_degree + 1):
            if degree > 0 and n < degree + 3:
                break
            A = np.vander(u, degree + 1, increasing=True)
            coeffs, rss = _robust_polynomial(A, s, w, threshold)
            bic = n * np.log(max(rss / n, 1e-300)) + (degree + 1) * np.log(n)
            if best is None or bic < best[0]:
                best = (bic, coeffs, A)
        assert best is not None
        _, coeffs, A = best
        self.coefficients = np.concatenate([coeffs, np.zeros(self.degree + 1 - len(coeffs))])
        self.f_range = (float(f.min()), float(f.max()))
        self.residual_rms = float(np.sqrt(np.mean((A @ coeffs - s) ** 2)) * self.half_diagonal)
        return self

    def predict_shift(self, f: ArrayLike) -> Array:
        if self.coefficients is None or self.f_range is None or self.f_ref is None:
            raise RuntimeError("DistortionVsFocal is not fitted")
        f = np.asarray(f, dtype=float)
        u = self.f_ref / f
        u_lo, u_hi = self.f_ref / self.f_range[1], self.f_ref / self.f_range[0]
        u_b = np.clip(u, u_lo, u_hi)
        s_b = np.polynomial.polynomial.polyval(u_b, self.coefficients)
        return s_b * (u / u_b)  # proportional to 1/f outside the fitted range

    def predict(self, f: ArrayLike) -> Array:
        """lam at focal length(s) f."""
        return self.lambda_from_shift(f, self.predict_shift(f))

    def in_range(self, f: float) -> bool:
        return self.f_range is not None and self.f_range[0] <= f <= self.f_range[1]

    def fitted(self) -> bool:
        return self.coefficients is not None

    def to_dict(self) -> dict[str, Any]:
        """Plain YAML-able state (for the calibrator's state file)."""
        return {
            "half_diagonal": self.half_diagonal,
            "degree": self.degree,
            "f_ref": self.f_ref,
            "coefficients": None if self.coefficients is None else [float(c) for c in self.coefficients],
            "f_range": None if self.f_range is None else [float(v) for v in self.f_range],
            "residual_rms": self.residual_rms,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DistortionVsFocal:
        """Inverse of to_dict; ValueError on invalid content."""
        try:
            curve = cls(1, 1, int(data["degree"]), None if data["f_ref"] is None else float(data["f_ref"]))
            curve.half_diagonal = float(data["half_diagonal"])
            if data["coefficients"] is not None:
                curve.coefficients = np.array([float(c) for c in data["coefficients"]])
                lo, hi = (float(v) for v in data["f_range"])
                curve.f_range = (lo, hi)
            curve.residual_rms = float(data.get("residual_rms", float("nan")))
        except (KeyError, TypeError) as exc:
            raise ValueError(f"invalid DistortionVsFocal state: {exc}") from exc
        if curve.coefficients is not None and (
            len(curve.coefficients) != curve.degree + 1 or not np.all(np.isfinite(curve.coefficients))
        ):
            raise ValueError("invalid DistortionVsFocal coefficients")
        return curve
