"""The HD-MPC four-tank benchmark (scenarios/fourtank.yaml, docs/fourtank.md): its operating point
and linearisation from the equations, what the input-coupling check says, and the closed loop on
the nonlinear tanks with the paper's method (tv-box), the cooperative one (tv-box-coop) and the
centralised MPC.

    .venv/bin/python examples/fourtank.py            # the benchmark's partition: tv-box fails, tv-box-coop works
    .venv/bin/python examples/fourtank.py --swap     # the pumps swapped between the subsystems: tv-box works too
    .venv/bin/python examples/fourtank.py --own      # valve splits 0.7 / 0.6 (scenarios/fourtank_own.yaml)
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import yaml

import dmpc
from dmpc.cli.coupling import coupling_text, coupling_warning
from dmpc.plant.fourtank import linearisation, rates
from dmpc.scenario.schema import fourtank_positions
from dmpc.setup import prepare
from dmpc.setup.coupling_check import design_coupling
from dmpc.setup.plant import fourtank_plant

ROOT = Path(__file__).resolve().parents[1]


def scenario_data(own: bool, swap: bool) -> dict:
    """The scenario as a mapping, with the nonlinear tanks as its plant (``own``: the valve splits
    0.7 / 0.6 of scenarios/fourtank_own.yaml); ``swap``: subsystem a (tanks 1, 3) takes pump b, b
    takes pump a."""
    data = yaml.safe_load((ROOT / "scenarios" / ("fourtank_own.yaml" if own else "fourtank.yaml")).read_text())
    data["plant"] = {"model": "fourtank", **({"fourtank": {"gamma": [0.7, 0.6]}} if own else {})}
    if swap:
        a, b = data["subsystems"]
        to_a, to_b = data["couplings"]
        a["B"], to_a["B"] = to_a["B"], a["B"]
        b["B"], to_b["B"] = to_b["B"], b["B"]
        a["input"], b["input"] = b["input"], a["input"]
        a["inputs"], b["inputs"] = b["inputs"], a["inputs"]
    return data


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--swap", action="store_true", help="each subsystem takes the pump that feeds its tanks most")
    parser.add_argument("--own", action="store_true", help="valve splits 0.7 / 0.6 (scenarios/fourtank_own.yaml)")
    parser.add_argument("--steps", type=int, default=None, help="steps to simulate (default: the scenario's 600)")
    args = parser.parse_args()
    np.set_printoptions(precision=6, linewidth=120)

    scenario = dmpc.load_scenario(scenario_data(args.own, args.swap))
    plant = fourtank_plant(scenario)  # what plant.model: fourtank simulates
    tanks, q0, h0 = plant.tanks, plant.q0, plant.h0  # h0: dmpc.plant.fourtank.equilibrium(tanks, q0)
    print(f"splits gamma_a, gamma_b = {tanks.gamma}; q0 = {q0} m^3/h")
    print(f"equilibrium h0 = {h0} m (rates there: {np.max(np.abs(rates(tanks, h0, q0))):.1e} m/s)")
    A, B = linearisation(tanks, h0)
    print("continuous-time linearisation, order h1..h4 and qa, qb:")
    print(f"A [1/s] =\n{A}\nB [(m/s)/(m^3/h)] =\n{B}")

    prepared = prepare(scenario)
    system = prepared.system
    print(f"\ndiscrete model (dt = {scenario.dt:g} s), partition "
          + ", ".join(f"{s.name} = ({', '.join(q.name for q in scn.states)}; {scn.inputs[0].name})"
                      for s, scn in zip(system.subsystems, scenario.resolved_subsystems())))
    for s in system.subsystems:
        print(f"  A_{s.name}{s.name} = {s.A.tolist()}\n  B_{s.name}{s.name} = {s.B.ravel().tolist()}")
    for c in system.couplings:
        t, src = system.subsystems[c.target].name, system.subsystems[c.source].name
        print(f"  B_{t}{src} = {c.B.ravel().tolist()}")

    coupling = design_coupling(prepared)
    print(f"\ninput coupling: {coupling_text(coupling, prepared.names)}")
    warning = coupling_warning(coupling, "tv-box", prepared.names)
    print(f"warning: {warning}" if warning else "no warning for tv-box")

    print("\nclosed loop on the nonlinear tanks (plant.model: fourtank):")
    for method in ("tv-box", "tv-box-coop", "centralized"):
        result = dmpc.simulate(scenario, method=method, steps=args.steps)
        fallbacks = result.summary.get("fallbacks", 0)
        print(f"  {method:12s} verdict {result.verdict}, fallbacks {fallbacks}, closed-loop cost {result.cost:.4f}")
        where, _ = fourtank_positions(scenario)
        x = result.stacked_x()
        for k in sorted({len(result.t) // 2, len(result.t) - 1}):
            shown = ", ".join(f"h{i + 1} {level:.4f}" for i, level in enumerate(h0 + x[k, where]))
            print(f"    t = {result.t[k]:6.0f} s: {shown} m")


if __name__ == "__main__":
    main()
