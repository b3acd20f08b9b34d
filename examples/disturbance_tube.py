"""A bounded disturbance with and without the tube: the same seeded w(k) on the continuous carts.

The velocity bound is tightened to |v| <= 1.2 m/s so that the plans ride it. Without the tube
(options.tube: none) the disturbance pushes the carts over it; with options.tube: robust the
disturbance bound is part of the tube, every constraint is tightened by what it can add up to,
and the bound holds.

    python examples/disturbance_tube.py [--steps 40]
"""
from __future__ import annotations

import argparse
from pathlib import Path

import dmpc

CARTS = Path(__file__).resolve().parents[1] / "scenarios" / "carts-continuous.yaml"
CARTS_NAMES = ("1", "2", "3")


def scenario(steps: int, tube: str) -> dmpc.Scenario:
    """The carts with |v| <= 1.2, a uniform disturbance |w_v| <= 0.005 (seed 3) and the given tube."""
    bounds = {f"subsystems.{i}.state": {"lower": [-5.0, -1.2], "upper": [5.0, 1.2]} for i in range(3)}
    revisions = {f"subsystems.{i}.revision_bound": {"state": [0.01, 0.01], "input": [0.03]} for i in range(3)}
    disturbance = {"kind": "uniform", "bound": {name: [0.0, 0.005] for name in CARTS_NAMES}, "seed": 3}
    return dmpc.load_scenario(CARTS, steps=steps, horizon=38, options__tube=tube, plant__disturbance=disturbance,
                              **bounds, **revisions)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=40)
    args = parser.parse_args()
    for tube in ("none", "robust"):
        result = dmpc.simulate(scenario(args.steps, tube))
        excess = max(result.summary["state_bound_excess"].values())
        print(f"tube {tube:6s}: verdict {result.verdict}, largest state-bound excess {excess:+.4g} "
              f"(> 0: broken), fallbacks {result.summary['fallbacks']}, closed-loop cost {result.cost:.4f}")


if __name__ == "__main__":
    main()
