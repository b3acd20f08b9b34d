"""Offset-free estimation: integrating disturbance models, their detectability, the agents'
steady-state Kalman gains, the observer and the steady-state targets as an affine map of the
estimate (docs/algorithm.md, "Offset-free tracking").

Each subsystem i measures y_i = C_i x_i and carries n_d,i integrating disturbances d_i:

    x+ = A x + B u + B_d d,   d+ = d,   y = C x + C_d d

with A, B the coupled system's (its couplings A_ij, B_ij included) and B_d, C_d, C block diagonal.
Agent i's estimate uses its own y_i only; the coupling enters through its neighbours' previous
estimates and their inputs in the prediction. If the loop converges with the targets recomputed
from the estimate, the tracked outputs meet their requests with zero offset, whatever the constant
disturbance or the plant-model mismatch (Pannocchia & Rawlings, AIChE J. 49, 2003; Maeder,
Borrelli & Morari, Automatica 45, 2009).

Modules:

- :mod:`dmpc.estimation.model`: the disturbance models and the detectability checks;
- :mod:`dmpc.estimation.kalman`: noise weights, the gains and the coupled estimator's stability;
- :mod:`dmpc.estimation.observer`: the estimate, step by step;
- :mod:`dmpc.estimation.targets`: the offset-free steady-state targets.

Pure: numpy and scipy only, no I/O. The observer's step needs numpy and scipy.sparse only;
scipy.linalg (about 8 MB per process) is loaded by the design functions and by the targets'
factorisation (scipy.sparse.linalg), not by the observer.
"""
