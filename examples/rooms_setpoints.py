"""Setpoints: the five rooms of scenarios/rooms.yaml through a night of setback and a morning warm-up.

    python examples/rooms_setpoints.py [--out runs/examples] [--start 22]

The scenario's `setpoints` ask each room's air for a temperature from a given time on (as
deviations from 21 degC, `at` in seconds). This prints, per room and setpoint, when it held, what
was asked, where the air was when the next one took over, and the tracking summary at the end;
the figures (states and inputs with the targets dashed and the setpoints dotted, the cost with the
setpoint changes marked) are saved as PNG.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import dmpc

ROOMS = Path(__file__).resolve().parents[1] / "scenarios" / "rooms.yaml"
NOMINAL = 21.0
"""degC: the rooms' states are deviations from it."""


def clock(seconds: float, start_hour: float) -> str:
    """The time of day ``seconds`` after ``start_hour`` o'clock, as HH:MM."""
    minutes = int(round(start_hour * 60 + seconds / 60)) % (24 * 60)
    return f"{minutes // 60:02d}:{minutes % 60:02d}"


def segments(asked: np.ndarray) -> list[tuple[int, int]]:
    """The steps [a, b) over which one setpoint (K,) held, in order."""
    changes = [k for k in range(1, asked.size) if asked[k] != asked[k - 1]]
    bounds = [0, *changes, asked.size]
    return list(zip(bounds[:-1], bounds[1:]))


def setpoint_rows(result: dmpc.Result, start_hour: float) -> list[str]:
    """One line per room and setpoint: from, until, asked, the air when the next one took over."""
    rows = [f"{'room':<6} {'from':>5} {'until':>5} {'asked':>8} {'air then':>9} {'error':>7}"]
    for name in result.names:
        asked = result.setpoint[name][:, 0]
        air = result.x[name][:, 0]
        for a, b in segments(asked):
            error = air[b] - asked[a]
            rows.append(f"{name:<6} {clock(result.t[a], start_hour):>5} {clock(result.t[b], start_hour):>5} "
                        f"{NOMINAL + asked[a]:>6.1f} C {NOMINAL + air[b]:>7.2f} C {error:>+6.2f} K")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("runs/examples"), help="folder for the figures")
    parser.add_argument("--start", type=float, default=22.0, help="the hour of day at t = 0 (for the table)")
    args = parser.parse_args()
    result = dmpc.simulate(dmpc.load_scenario(ROOMS))
    summary = result.summary
    print(f"verdict {result.verdict}, {summary['steps']} steps of {result.dt:g} s, {summary['fallbacks']} fallbacks")
    for warning in summary["warnings"]:
        print(f"  warning {warning['kind']}: {warning['message']}")
    print("\n".join(setpoint_rows(result, args.start)))
    tracking = summary["tracking"]
    print(f"at the end: largest error {tracking['max_abs_error']:.3f} K; the reference governor held the target "
          f"back at {len(tracking['governor_steps'])} steps")
    args.out.mkdir(parents=True, exist_ok=True)
    for name, figure in result.plot().items():
        figure.savefig(args.out / f"rooms_setpoints_{name}.png", dpi=100)
    print(f"figures: {args.out}/rooms_setpoints_*.png")


if __name__ == "__main__":
    main()
