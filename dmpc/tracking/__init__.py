"""Setpoint tracking: steady-state targets, the terminal sets around them and the reference governor.

Pure numerics on :class:`dmpc.core.system.CoupledSystem` (no bus, no files); docs/algorithm.md,
"Setpoints", states the method and its guarantees.
"""
