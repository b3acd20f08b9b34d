"""What ``dmpc design`` and ``dmpc validate`` say about input coupling (:mod:`dmpc.offline.input_coupling`):
the figures in words, and the one warning line where a non-cooperative method is likely to fail."""
from __future__ import annotations

from dmpc.offline.input_coupling import InputCoupling
from dmpc.setup.coupling_check import COOPERATIVE_METHOD, non_cooperative


def coupling_text(ic: InputCoupling, names: list[str]) -> str:
    """The figures of ``ic`` on one line, for the design report; subsystems by their ``names``."""
    strongest = ic.strongest
    if strongest is None:
        drive = "none (B_ij = 0)"
    else:
        s, t = names[strongest.source], names[strongest.target]
        steady = "" if strongest.steady_ratio is None else f", at steady state {strongest.steady_ratio:.3g}"
        drive = f"largest |B_{t}{s}|/|B_{s}{s}| = {strongest.ratio:.3g} ({s} drives {t}{steady})"
    bound = " (bound)" if ic.radius_kind == "bound" else ""
    rounds = f"{ic.rounds} round{'s' * (ic.rounds > 1)}"
    loop = (f"closed loop without constraints {ic.loop_radius:.4g} per step" if ic.loop_radius is not None
            else f"closed loop not computed (size {ic.loop_dimension})")
    return f"{drive}; spectral radius of a Jacobi round {ic.radius:.3g}{bound}, {loop} (N = {ic.horizon}, {rounds})"


def coupling_warning(ic: InputCoupling | None, method: str, names: list[str]) -> str | None:
    """The warning (without its ``warning:`` prefix) when ``method`` is non-cooperative and the
    check ``ic`` says it is likely to fail; None otherwise. Subsystems by their ``names``."""
    if ic is None or not ic.likely_to_fail or not non_cooperative(method):
        return None
    strongest = ic.strongest
    assert strongest is not None  # likely_to_fail needs some B_ij != 0
    s, t = names[strongest.source], names[strongest.target]
    ratio = f"|B_{t}{s}|/|B_{s}{s}| = {strongest.ratio:.2f}"
    drive = (f"subsystem {s}'s inputs drive {t} more than {s} ({ratio})" if strongest.ratio > 1
             else f"subsystem {s}'s inputs drive {t} ({ratio})")
    if ic.diverges:
        fails = f"the non-cooperative iteration diverges (spectral radius {ic.radius:.2f})"
    else:
        fails = (f"{method}'s closed loop is unstable even without constraints (spectral radius "
                 f"{ic.loop_radius:.4f} per step at N = {ic.horizon})")
    return f"{drive}; {fails}: use the cooperative method (options.method: {COOPERATIVE_METHOD}, or --method {COOPERATIVE_METHOD})"
