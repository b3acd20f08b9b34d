"""Cooperative distributed MPC (``tv-box-coop``): every agent minimises the whole system's cost
over its own inputs, and the coordinator combines the agents' proposals so that every iterate is
a feasible point of the centralised problem (docs/algorithm.md, "Cooperative DMPC").

Pure: numpy, scipy and OSQP only.
"""
