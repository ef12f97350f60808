"""The BEM baseline: the contact disc in boundary elements on a half-space, Boussinesq's Green's
function, the capacitance matrix of the contact set (James & Pai 1999/2001; docs/model.md section
12.4).

The tip is a flat frictionless disc of radius ``a``: only normal tractions act, so of the
Boussinesq-Cerruti half-space solution only Boussinesq's normal point load enters (Cerruti's
tangential loads carry no traction here). The disc is cut into square elements of side ``a / n_in``;
the normal displacement at element i under a unit normal load on element j (i != j) is Boussinesq's
``(1 - nu^2) / (pi E r_ij)``, and each element's own is the centre deflection of its equal-area disc
under uniform pressure, ``2 (1 - nu^2) / (pi E R)``, ``pi R^2`` the element's area: the load spread
over the tip's area, not a point. The compliance matrix ``C`` of the contact set maps element forces
to displacements; its inverse, the capacitance matrix, gives the forces that hold every element at
the indentation ``d``: ``f = C^-1 1 d``, the stiffness ``k = 1^T C^-1 1``.
"""
from __future__ import annotations

import math

import numpy as np

# Boundary elements across the tip's radius (ours): 4 gives 52 on the disc, the flat tip's stiffness
# within 1% of Sneddon's, and a contact set the servo solves in a few microseconds (tissue/contact.py)
N_IN = 4


def disc_elements(a: float, n_in: int = N_IN):
    """(side, centres (n, 2)) of the square elements whose centres lie within the disc of radius a."""
    s = a / n_in
    g = (np.arange(-n_in, n_in) + 0.5) * s
    X, Y = np.meshgrid(g, g)
    keep = np.hypot(X, Y) <= a
    return s, np.stack([X[keep], Y[keep]], axis=1)


def element_count(n_in: int = N_IN) -> int:
    """The number of boundary elements on the tip's disc."""
    return len(disc_elements(1.0, n_in)[1])


def compliance(E: float, nu: float, a: float, n_in: int = N_IN) -> np.ndarray:
    """The contact disc's compliance matrix (m/N): normal displacement at each element per unit
    normal force on each element, on a half-space of Young's modulus E (Pa) and Poisson ratio nu."""
    s, xy = disc_elements(a, n_in)
    c = (1.0 - nu * nu) / (math.pi * E)
    r = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])
    np.fill_diagonal(r, 1.0)
    C = c / r
    np.fill_diagonal(C, 2.0 * c / (s / math.sqrt(math.pi)))
    return C


def flat_punch(E: float, nu: float, a: float, n_in: int = N_IN) -> float:
    """Stiffness (N/m) of a flat tip of radius ``a`` on the half-space: the sum of the capacitance
    matrix (the compliance matrix's inverse)."""
    C = compliance(E, nu, a, n_in)
    return float(np.linalg.solve(C, np.ones(len(C))).sum())
