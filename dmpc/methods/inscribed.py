"""Polytopes inside ellipsoids, so that OSQP (linear constraints only) can impose an ellipsoid.

The ellipsoid {z : z' P z <= r} is the ball of radius sqrt(r) in the whitened coordinates
y = L' z, where P = L L' (Cholesky). A polytope {y : G y <= h} inside the unit ball, scaled by
sqrt(r), is therefore inside the ellipsoid: {z : G L' z <= sqrt(r) h}.

- n = 1: the interval itself (exact).
- n = 2: the regular polygon with ``facets`` sides and its vertices on the unit circle. Its
  inner radius is cos(pi / facets) (0.981 for 16 sides), so it covers 97 % of the disc's area.
- n >= 3: the facets with normals +-e_j and (+-e_j +-e_k)/sqrt(2), all at the same offset,
  scaled so that the farthest vertex lies on the unit sphere (vertices by Qhull). Above
  ``MAX_QHULL_DIM`` the vertex enumeration is too large and the cube {|y_j| <= 1/sqrt(n)},
  whose vertices lie on the sphere, is used instead.
"""
from __future__ import annotations

import itertools

import numpy as np

DEFAULT_FACETS = 16
MAX_QHULL_DIM = 6


def unit_ball_polytope(n: int, facets: int = DEFAULT_FACETS) -> tuple[np.ndarray, np.ndarray]:
    """A polytope {y : G y <= h} inside the unit ball of R^n, touching the sphere at its vertices.

    Parameters
    ----------
    n : int
        Dimension, >= 1.
    facets : int
        Number of sides of the polygon for n = 2 (>= 3); ignored otherwise.

    Returns
    -------
    G : ndarray, shape (p, n)
        Unit facet normals.
    h : ndarray, shape (p,)
        Offsets, all equal and positive.
    """
    if n < 1:
        raise ValueError(f"dimension must be >= 1, got {n}")
    if n == 1:
        return np.array([[1.0], [-1.0]]), np.ones(2)
    if n == 2:
        if facets < 3:
            raise ValueError(f"a polygon needs at least 3 sides, got {facets}")
        angles = 2.0 * np.pi * np.arange(facets) / facets
        G = np.column_stack([np.cos(angles), np.sin(angles)])
        return G, np.full(facets, np.cos(np.pi / facets))
    if n > MAX_QHULL_DIM:
        return np.vstack([np.eye(n), -np.eye(n)]), np.full(2 * n, 1.0 / np.sqrt(n))
    rows = [s * e for e in np.eye(n) for s in (1.0, -1.0)]
    for j, k in itertools.combinations(range(n), 2):
        for sj, sk in itertools.product((1.0, -1.0), repeat=2):
            g = np.zeros(n)
            g[j], g[k] = sj, sk
            rows.append(g / np.sqrt(2.0))
    G = np.array(rows)
    h = np.ones(G.shape[0])
    return G, h / max_vertex_norm(G, h)


def max_vertex_norm(G: np.ndarray, h: np.ndarray) -> float:
    """The largest Euclidean norm of a vertex of the bounded polytope {y : G y <= h} (0 inside).

    Parameters
    ----------
    G : ndarray, shape (p, n)
    h : ndarray, shape (p,)
    """
    return float(np.max(np.linalg.norm(polytope_vertices(G, h), axis=1)))


def polytope_vertices(G: np.ndarray, h: np.ndarray) -> np.ndarray:
    """The vertices of the bounded polytope {y : G y <= h} with the origin in its interior.

    Returns
    -------
    ndarray, shape (v, n)
    """
    n = G.shape[1]
    if n == 1:
        upper = np.min(h[G[:, 0] > 0] / G[G[:, 0] > 0, 0])
        lower = np.max(h[G[:, 0] < 0] / G[G[:, 0] < 0, 0])
        return np.array([[lower], [upper]])
    from scipy.spatial import HalfspaceIntersection  # offline geometry only (n >= 3 or checks)

    hs = HalfspaceIntersection(np.column_stack([G, -h]), np.zeros(n))
    return hs.intersections


def whitening(P: np.ndarray) -> np.ndarray:
    """L' with P = L L' (Cholesky), so that z' P z = ||L' z||^2; shape (n, n)."""
    return np.linalg.cholesky(P).T


def inscribed_rows(P: np.ndarray, facets: int = DEFAULT_FACETS) -> tuple[np.ndarray, np.ndarray]:
    """Rows T, h with {z : T z <= sqrt(r) h} inside {z : z' P z <= r} for every r >= 0.

    Parameters
    ----------
    P : ndarray, shape (n, n)
        Symmetric positive definite.
    facets : int
        Polygon sides for n = 2.

    Returns
    -------
    T : ndarray, shape (p, n)
    h : ndarray, shape (p,)
    """
    G, h = unit_ball_polytope(P.shape[0], facets)
    return G @ whitening(P), h
