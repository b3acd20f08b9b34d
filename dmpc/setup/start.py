"""The start problem of a control method, for the horizon search of the design
(:class:`dmpc.offline.horizon.StartProblem`): its terminal constraint at k = 0, and its
distributed first step tried with the agents' controllers and the coordinator, without a bus."""
from __future__ import annotations

from dataclasses import dataclass, replace

from dmpc.core.qp_status import SOLVED
from dmpc.core.steps import Coupling, ProtocolOptions, StepRecord
from dmpc.core.system import CoupledSystem, LinearSet
from dmpc.methods import Method, initial_terminal_set, method_spec
from dmpc.offline import ControllerDesign
from dmpc.runtime.direct import DirectLoop


@dataclass(frozen=True)
class MethodStart:
    """The k = 0 step of ``method`` on ``system``.

    Attributes
    ----------
    system : CoupledSystem
    method : str
    coupling : {"feedforward", "nominal"}
    protocol : ProtocolOptions
        The Jacobi settings the k = 0 step runs with.
    """

    system: CoupledSystem
    method: Method
    coupling: Coupling
    protocol: ProtocolOptions

    def terminal_rows(self, design: ControllerDesign) -> LinearSet:
        """The method's terminal set at k = 0 with ``design``, as rows on the global state z(N)."""
        return initial_terminal_set(self.method, self.system, design)

    def distributed_plans(self, design: ControllerDesign) -> bool:
        """Whether the distributed k = 0 step with ``design`` gives every agent a plan (always, for a
        method
        of one QP)."""
        if not method_spec(self.method).distributed:
            return True  # one QP: central feasibility is the whole story
        records: list[StepRecord] = []
        DirectLoop(self.system, design, replace(self.protocol, steps=1), self.method, self.coupling).run(
            1, records.append)
        # an agent whose QP failed in a later Jacobi round keeps an earlier plan (no fallback), but
        # its problem from the final assumptions was infeasible: that counts as infeasible too
        return bool(records) and not any(records[0].fallback) and all(s in SOLVED for s in records[0].status)
