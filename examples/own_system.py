"""Your own system from numpy arrays: two carts joined by a spring, simulated in this process.

    python examples/own_system.py [--out runs/examples] [--steps 40]
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import dmpc


def two_carts(steps: int) -> dmpc.Scenario:
    """Two double integrators sampled at dt = 0.1 s, joined by a spring, with names and units."""
    dt, spring = 0.1, 0.2
    A = np.array([[1.0, dt], [-spring * dt, 1.0]])
    B = np.array([[dt ** 2 / 2], [dt]])
    pull = np.array([[0.0, 0.0], [spring * dt, 0.0]])
    cart = dict(A=A, B=B, Q=np.diag([1.0, 0.1]), R=np.array([[0.1]]),
                input={"lower": [-1.0], "upper": [1.0]}, state={"lower": [-2.0, -1.0], "upper": [2.0, 1.0]},
                states=[{"name": "p", "unit": "m"}, {"name": "v", "unit": "m/s"}],
                inputs=[{"name": "a", "unit": "m/s^2"}])
    return dmpc.load_scenario({
        "name": "two-carts", "dt": dt, "steps": steps,
        "subsystems": [dict(cart, name="left", x0=[1.5, 0.0]), dict(cart, name="right", x0=[-1.0, 0.2])],
        "couplings": [{"target": "left", "source": "right", "A": pull},
                      {"target": "right", "source": "left", "A": pull}],
    })


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("runs/examples"), help="folder for the figures")
    parser.add_argument("--steps", type=int, default=40)
    args = parser.parse_args()
    scenario = two_carts(args.steps)
    design = dmpc.design(scenario)
    print(design.table())
    result = dmpc.simulate(scenario)
    print(result.table())
    args.out.mkdir(parents=True, exist_ok=True)
    for name, figure in result.plot().items():
        figure.savefig(args.out / f"own_system_{name}.png", dpi=100)
    print(f"figures: {args.out}/own_system_*.png")


if __name__ == "__main__":
    main()
