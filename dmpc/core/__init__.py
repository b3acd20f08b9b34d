"""The numerical core, the lowest layer: the coupled system and its sets, the units and names of
its quantities, the discretisation of continuous-time models, the MPC QPs and their statuses,
the plans and their shifted candidates, what one step of a run is made of, and the noise on
the measured outputs.

Pure: it imports numpy, scipy and OSQP, and nothing of dmpc outside this package.
"""
