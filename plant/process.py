"""``dmpc plant --coordinator external``: the simulated plant alone, as a process on the bus."""
from __future__ import annotations

from dataclasses import dataclass

from dmpc.bus.interface import Bus
from dmpc.bus.messages import COORDINATOR_GRACE
from dmpc.plant.models import make_plant
from dmpc.plant.role import PlantRole
from dmpc.terminal.exit_codes import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK


@dataclass(frozen=True)
class PlantRoleOutcome:
    code: int
    message: str
    steps: int


def run_plant_role(prepared, bus: Bus, run_id: str, startup_timeout: float,
                   sensors: list[str] | None = None, outputs: bool = False) -> PlantRoleOutcome:
    """Serve the plant (or the sensors of ``sensors``) until the coordinator stops the run.

    Parameters
    ----------
    prepared : dmpc.prepared.Prepared
        The scenario and plant model (``prepared.plant``) to simulate.
    bus : Bus
        An open bus; closed by the caller.
    run_id : str
    startup_timeout : float
        Seconds to wait for step 0's inputs.
    sensors : list of str, optional
        Subsystems reported one by one as ``sensor-<name>``; None reports the whole state.
    outputs : bool
        Report the measured outputs y_i = C_i x_i of the subsystems whose C is not the identity
        in place of their states (:class:`~dmpc.plant.role.PlantRole`).
    """
    who = "plant" if sensors is None else f"sensors {', '.join(sensors)}"
    role = PlantRole(bus, make_plant(prepared), prepared.system, run_id, sensors=sensors, outputs=outputs)
    role.announce()
    try:
        started = bus.run(until=lambda: role.k > 0 or role.stopped, timeout=startup_timeout)
        if not started:
            seen = "seen alive" if role.coordinator_seen else "not seen alive"
            return PlantRoleOutcome(EXIT_FAILED, f"{who}: no inputs from the coordinator within {startup_timeout:g} s "
                                                 f"(the coordinator: {seen}; run id '{run_id}')", 0)
        while True:
            bus.run(until=lambda: role.stopped or role.coordinator_lost)
            if role.stopped:
                break
            if not bus.run(until=lambda: role.stopped or not role.coordinator_lost, timeout=COORDINATOR_GRACE):
                return PlantRoleOutcome(EXIT_FAILED, f"{who}: lost the coordinator after {role.k} steps; exiting",
                                        role.k)
    except KeyboardInterrupt:
        return PlantRoleOutcome(EXIT_INTERRUPTED, f"{who}: interrupted after {role.k} steps", role.k)
    drops = f"; {role.rejects.counts_line()}" if role.rejects.total else ""
    if role.stop_reason != "finished":
        return PlantRoleOutcome(EXIT_FAILED, f"{who}: the coordinator stopped the run ({role.stop_reason}){drops}",
                                role.k)
    return PlantRoleOutcome(EXIT_OK, f"{who}: finished after {role.k} steps{drops}", role.k)
