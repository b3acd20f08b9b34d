"""A continuous-time model: the carts with springs and dampers, discretised by dmpc (dt = 0.1 s).

Prints the discrete model the controllers use, how far it is from the exact one, and the
closed loop with the plant simulating the controllers' own model and the exact one.

    python examples/continuous_carts.py [--steps 80]
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import dmpc

CARTS = Path(__file__).resolve().parents[1] / "scenarios" / "carts-continuous.yaml"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=80)
    args = parser.parse_args()
    # horizon: the value `horizon: auto` picks for this start (34), given so that each design is one solve
    scenario = dmpc.load_scenario(CARTS, steps=args.steps, horizon=34)
    design = dmpc.design(scenario)
    model = design.model
    print(f"{model['method']} at dt = {model['dt']} s; cart 1's discrete A:\n{np.array(model['subsystems'][0]['A'])}")
    print(f"largest entry of (controllers' [A B] - exact [A B]): {model['model_error']:.3g}")
    for block in model["fill_in"]["blocks"]:
        print(f"exact model, outside the graph: {block['matrix']}_{block['target']},{block['source']} "
              f"up to {block['largest']:.3g}")
    try:
        dmpc.design(dmpc.load_scenario(scenario, discretisation__method="exact-zoh"))
    except dmpc.ScenarioError as exc:
        print(f"exact-zoh without truncate: {exc}")
    truncated = dmpc.design(dmpc.load_scenario(scenario, discretisation__method="exact-zoh",
                                               discretisation__truncate=True))
    print(f"exact-zoh with truncate: dropped entries up to {truncated.model['fill_in']['largest']:.3g}, "
          f"horizon {truncated.horizon}")
    for plant in ("nominal", "exact"):
        result = dmpc.simulate(dmpc.load_scenario(scenario, plant__model=plant))
        print(f"plant {plant:7s} (controllers: local-zoh): verdict {result.verdict}, "
              f"closed-loop cost {result.cost:.4f}, |x(end)| {np.abs(result.stacked_x()[-1]).max():.2e}")


if __name__ == "__main__":
    main()
