"""2D polynomial warps between pixel positions (paper, 3.1.1: the seventh-order mapping between the curved
and the unfolded facade in an image).

A warp of total degree ``D`` maps pixel positions (x, y) (pixel centres at i + 0.5) to (x', y'):

    x' = sum_{i + j <= D} cx_ij P_i(u) P_j(v),   y' = sum_{i + j <= D} cy_ij P_i(u) P_j(v),

with ``P_k`` the Legendre polynomials and (u, v) the source position normalised to [-1, 1] over the source
domain ``[x0, x1] x [y0, y1]`` (``u = (2 x - x0 - x1) / (x1 - x0)``). The Legendre basis spans exactly the
same space as the monomials x^i y^j; it is used because its design matrix stays well conditioned up to
degree 7 (monomials in raw pixels reach condition numbers beyond 1e20). Coefficients are least-squares fits
through an SVD; the fit reports the RMS and largest residual (px) at the samples and the design matrix's
condition number (1 is perfect; it grows when samples leave parts of the domain empty, e.g. near the
image border).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.polynomial import legendre


@dataclass(frozen=True, eq=False)
class PolyWarp:
    """A fitted 2D polynomial warp. ``domain`` = (x0, y0, x1, y1) of the source (px)."""

    degree: int
    domain: tuple[float, float, float, float]
    coef_x: np.ndarray  # [M] Legendre coefficients of x'
    coef_y: np.ndarray  # [M]
    rms_px: float
    max_px: float
    condition: float

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        """Map positions [N, 2] (px) to [N, 2] (px)."""
        V = design_matrix(np.asarray(xy, dtype=np.float64), self.degree, self.domain)
        return np.stack([V @ self.coef_x, V @ self.coef_y], axis=1)

    @classmethod
    def identity(cls, domain: tuple[float, float, float, float]) -> PolyWarp:
        """The identity on ``domain`` (degree 1, zero residual, condition 1)."""
        x0, y0, x1, y1 = domain
        # P_0 = 1, P_1(u) = u; order of terms is that of ``_exponents(1)``: (0,0), (0,1), (1,0)
        cx = np.array([(x0 + x1) / 2, 0.0, (x1 - x0) / 2])
        cy = np.array([(y0 + y1) / 2, (y1 - y0) / 2, 0.0])
        return cls(1, tuple(map(float, domain)), cx, cy, 0.0, 0.0, 1.0)

    @property
    def is_identity(self) -> bool:
        return self.degree == 1 and np.allclose(self(np.array([[0.0, 0.0], [1.0, 2.0]])),
                                                [[0.0, 0.0], [1.0, 2.0]])

    def to_dict(self) -> dict:
        return {"degree": self.degree, "basis": "legendre, total degree", "domain_px": list(self.domain),
                "coef_x": self.coef_x.tolist(), "coef_y": self.coef_y.tolist(),
                "rms_px": self.rms_px, "max_px": self.max_px,
                "condition": self.condition if np.isfinite(self.condition) else None}

    @classmethod
    def from_dict(cls, d: dict) -> PolyWarp:
        return cls(int(d["degree"]), tuple(d["domain_px"]), np.array(d["coef_x"], float),
                   np.array(d["coef_y"], float), float(d["rms_px"]), float(d["max_px"]),
                   float("inf") if d["condition"] is None else float(d["condition"]))


def _exponents(degree: int) -> list[tuple[int, int]]:
    """(i, j) with i + j <= degree, i the power of u, j of v; (degree+1)(degree+2)/2 terms."""
    return [(i, j) for i in range(degree + 1) for j in range(degree + 1 - i)]


def design_matrix(xy: np.ndarray, degree: int, domain: tuple[float, float, float, float]) -> np.ndarray:
    """[N, M] Legendre products P_i(u) P_j(v) of positions [N, 2] normalised over ``domain``."""
    x0, y0, x1, y1 = domain
    u = (2.0 * xy[:, 0] - x0 - x1) / (x1 - x0)
    v = (2.0 * xy[:, 1] - y0 - y1) / (y1 - y0)
    Pu, Pv = legendre.legvander(u, degree), legendre.legvander(v, degree)  # [N, degree + 1]
    return np.stack([Pu[:, i] * Pv[:, j] for i, j in _exponents(degree)], axis=1)


def fit_polywarp(src: np.ndarray, dst: np.ndarray, degree: int,
                 domain: tuple[float, float, float, float] | None = None) -> PolyWarp:
    """Least-squares warp of ``degree`` taking ``src`` [N, 2] to ``dst`` [N, 2] (px).

    ``domain`` defaults to the bounding box of ``src``. Raises ValueError with fewer samples than terms."""
    src, dst = np.asarray(src, dtype=np.float64), np.asarray(dst, dtype=np.float64)
    n_terms = (degree + 1) * (degree + 2) // 2
    if len(src) < n_terms or src.shape != dst.shape:
        raise ValueError(f"a degree-{degree} warp needs at least {n_terms} sample pairs, got {len(src)} "
                         f"(shapes {src.shape} and {dst.shape})")
    if domain is None:
        lo, hi = src.min(axis=0), src.max(axis=0)
        domain = (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
    V = design_matrix(src, degree, domain)
    s = np.linalg.svd(V, compute_uv=False)
    condition = float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
    coef = np.linalg.lstsq(V, dst, rcond=None)[0]
    err = np.linalg.norm(V @ coef - dst, axis=1)
    return PolyWarp(degree, tuple(map(float, domain)), coef[:, 0], coef[:, 1],
                    float(np.sqrt(np.mean(err**2))), float(err.max()), condition)
