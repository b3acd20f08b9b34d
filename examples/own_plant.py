"""Your own plant: the carts with stiffening springs (nonlinear, RK4) against the linear controllers.

    python examples/own_plant.py [--steps 60] [--run]

``--run`` also runs it as separate processes over Zenoh (dmpc.run), which import the plant
function from examples/plants.py.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from plants import carts_stiffening_springs

import dmpc

CARTS = Path(__file__).resolve().parents[1] / "scenarios" / "carts-continuous.yaml"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--run", action="store_true", help="also run it as processes over Zenoh")
    args = parser.parse_args()
    scenario = dmpc.load_scenario(CARTS, steps=args.steps, horizon=34)  # what horizon: auto picks, given
    linear = dmpc.simulate(scenario)
    own = dmpc.simulate(scenario, plant=carts_stiffening_springs)
    gap = max(np.abs(own.x[name] - linear.x[name]).max() for name in own.names)
    print(f"linear plant: verdict {linear.verdict}, closed-loop cost {linear.cost:.4f}")
    print(f"own plant:    verdict {own.verdict}, closed-loop cost {own.cost:.4f} "
          f"(states differ by up to {gap:.3g}; plant {own.summary['plant']})")
    if args.run:
        over_zenoh = dmpc.run(scenario, plant=carts_stiffening_springs)
        same = max(np.abs(over_zenoh.x[name] - own.x[name]).max() for name in own.names)
        print(f"dmpc.run:     verdict {over_zenoh.verdict}, closed-loop cost {over_zenoh.cost:.4f} "
              f"(largest difference from simulate {same:.2g})")


if __name__ == "__main__":
    main()
